"""The speculative second search: collected, cancelled, failing, or run in this process."""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time

import pytest

from stickfigure._threads import available_cpus
from stickfigure.models.em.starts import Speculative, _fork_context

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks only on Linux")


@pytest.fixture(autouse=True)
def _no_other_threads():
    # Forking is refused while other Python threads run (tqdm's monitor excepted).
    assert _fork_context() is not None or not sys.platform.startswith("linux"), threading.enumerate()


def _pid_and(x):
    return os.getpid(), x


@linux
def test_result_comes_from_a_child_process():
    with Speculative(lambda: _pid_and([1, 2, 3])) as job:
        assert job.forked
        pid, value = job.result()
        assert job.forked  # still says how it ran
    assert pid != os.getpid() and value == [1, 2, 3]
    assert not multiprocessing.active_children()


@linux
def test_cancel_stops_the_child():
    with Speculative(lambda: time.sleep(60)) as job:
        assert job.forked
        t = time.monotonic()
        job.cancel()
    assert time.monotonic() - t < 10
    assert not multiprocessing.active_children()


@linux
def test_a_failure_in_the_child_is_raised_here():
    def boom():
        raise ValueError("bad stick")

    with Speculative(boom, name="the test job") as job, \
            pytest.raises(RuntimeError, match=r"(?s)the test job failed in its process.*bad stick"):
        job.result()
    assert not multiprocessing.active_children()


def test_no_fork_while_other_threads_run():
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        with Speculative(lambda: os.getpid()) as job:
            assert not job.forked
            assert job.result() == os.getpid()
    finally:
        stop.set()
        t.join()


def test_without_parallel_the_job_runs_here_when_asked():
    calls = []
    with Speculative(lambda: "child", parallel=False, here=lambda: calls.append(os.getpid()) or "here") as job:
        assert not job.forked and not calls  # nothing runs until the result is asked for
        assert job.result() == "here"
    assert calls == [os.getpid()]


def test_available_cpus_counts_what_this_process_may_use():
    # The default of n_jobs (em's starts, mcmc's chains): the affinity mask, not the host's count.
    n = available_cpus()
    assert 1 <= n <= (os.cpu_count() or n)
    if hasattr(os, "sched_getaffinity"):
        assert n == len(os.sched_getaffinity(0))
