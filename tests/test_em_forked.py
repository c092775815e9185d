"""Work in forked children: the speculative second search, greedy trials, halves of batched block fits."""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
import time

import numpy as np
import pytest

import stickfigure as sf
from stickfigure._threads import available_cpus
from stickfigure.models.em import refine
from stickfigure.models.em import structure as S
from stickfigure.models.em.forked import Speculative, _fork_context, in_halves
from stickfigure.models.em.initialise import initial_state
from stickfigure.models.em.model import Priors, normalise
from stickfigure.models.em.trials import greedy_trials

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks only on Linux")


@pytest.fixture(autouse=True)
def _no_other_threads():
    # Forking is refused while other Python threads run (tqdm's monitor included): stop a
    # monitor that earlier tests' progress bars (render, CLI) left running.
    for t in threading.enumerate():
        if type(t).__name__ == "TMonitor":
            t.exit()
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


@linux
def test_a_child_that_dies_is_reported_with_its_exit_code():
    with Speculative(lambda: os._exit(3), name="the job") as job:
        with pytest.raises(RuntimeError, match=r"the job's process died \(exit code 3\)"):
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


def _grandchild_pid(path):
    # A child that forks a child of its own (the second start's trials do) and waits.
    with Speculative(lambda: time.sleep(60)) as inner:
        with open(path, "w") as f:
            f.write(str(inner._proc.pid))
        time.sleep(60)


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (exited, not yet reaped by its parent) counts as gone.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@linux
def test_cancel_stops_the_childs_own_children(tmp_path):
    path = tmp_path / "pid"
    with Speculative(lambda: _grandchild_pid(path)) as job:
        t = time.monotonic()
        while not path.exists() or not path.read_text():
            assert time.monotonic() - t < 30
            time.sleep(0.05)
        inner = int(path.read_text())
        assert _alive(inner)
        job.cancel()
    t = time.monotonic()
    while _alive(inner):  # killed outright, the child would leave it running for 60 s
        assert time.monotonic() - t < 10
        time.sleep(0.05)


def _forgets_its_child():
    # A child left without its ``with`` block (as when a cancellation lands between forking
    # it and the block taking charge), whose result fills the pipe nobody reads.
    Speculative(lambda: b"x" * (16 << 20))
    time.sleep(60)


def _finishes(scenario, seconds=30.0):
    """Whether ``scenario()`` ends within ``seconds``, run in a forked harness process of its own
    process group, so that a scenario that hangs fails the test instead of hanging it."""
    def harness():
        os.setpgid(0, 0)
        scenario()

    proc = multiprocessing.get_context("fork").Process(target=harness)
    proc.start()
    proc.join(seconds)
    if proc.is_alive():
        os.killpg(proc.pid, 9)
        proc.join()
        return False
    assert proc.exitcode == 0, proc.exitcode
    return True


def _cancel_after(job, wait):
    with Speculative(job) as outer:
        time.sleep(wait)
        outer.cancel()
    assert not multiprocessing.active_children()


@linux
def test_cancel_does_not_wait_for_a_child_nobody_collects():
    # 1 s: the grandchild is writing by now
    assert _finishes(lambda: _cancel_after(_forgets_its_child, 1.0))


def _forks_for_ever():
    ballast = bytearray(64 << 20)  # noqa: F841  (a larger address space: each fork takes longer)
    while True:
        with Speculative(lambda: 1) as job:
            job.result()


def _cancels_a_forking_child_repeatedly():
    for k in range(10):
        _cancel_after(_forks_for_ever, 0.2 + 0.013 * k)


@linux
def test_a_cancellation_during_a_fork_is_not_lost(capfd):
    # A SIGTERM that came while the child forked was raised inside the after-fork hooks
    # (logging's _releaseLock), swallowed there, and the child ran on: a loop of forks
    # cancelled 20 times hung on the sixth, with "Exception ignored" on stderr.
    assert _finishes(_cancels_a_forking_child_repeatedly, 120.0), "a cancelled child ran on"
    err = capfd.readouterr().err
    # The swallowed cancellation's own text (fd 2 is shared with any process still running).
    assert "Exception ignored" not in err or "_Cancelled" not in err, err[-2000:]


def _collects_a_slow_large_result():
    # As in_halves does: waits in result() for a child that, later, writes more than a pipe holds.
    def slow_large():
        time.sleep(1.0)
        return b"x" * (16 << 20)

    with Speculative(slow_large) as inner:
        return inner.result()


@linux
def test_a_child_cancelled_while_it_waits_for_a_result_stops_that_child():
    # Cancelled inside result(), the child joined its own child without stopping it, and that
    # one waited for ever to write a result nobody read (2 demo runs in 40 hung so).
    assert _finishes(lambda: _cancel_after(_collects_a_slow_large_result, 0.3))


@linux
def test_a_child_that_writes_to_a_closed_pipe_exits_quietly(capfd):
    # Interrupted in result(), this process stops the child; a child past its cancellation
    # point that still writes gets a broken pipe and exits without a traceback.
    job = Speculative(lambda: b"x" * (16 << 20))
    job._conn.close()
    job._proc.join(30)
    assert job._proc.exitcode == 0
    job._proc = job._conn = None
    assert "Traceback" not in capfd.readouterr().err


@linux
def test_nice_lowers_the_childs_priority():
    with Speculative(lambda: os.nice(0), nice=5) as job:
        job._proc.join()  # done first (a result asked for earlier would be raced at this priority)
        assert job.result() == min(os.nice(0) + 5, 19)


def _nice_after_a_while():
    time.sleep(1.0)
    return os.nice(0)


def _may_renice():
    try:
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) - 1)
    except OSError:
        return False
    os.nice(1)
    return True


@linux
def test_a_niced_job_still_running_gets_the_priority_back_when_needed():
    mine = os.nice(0)
    allowed = _may_renice()
    with Speculative(_nice_after_a_while, nice=19) as job:
        value = job.result()  # asked for at once: the child is still sleeping
    assert value == (mine if allowed else 19)


@linux
def test_a_niced_job_that_is_done_gives_its_own_result():
    with Speculative(os.getpid, nice=19) as job:
        first = job._proc.pid
        job._proc.join()  # done before its result is asked for: no rival
        assert job.result() == first


def _tagged(items):
    return [(os.getpid(), x * x) for x in items]


@pytest.mark.parametrize("parallel", [False, True])
def test_in_halves_keeps_order_and_splits_by_weight(parallel):
    items = list(range(7))
    out = in_halves(_tagged, items, parallel=parallel, weights=[1, 1, 1, 1, 1, 1, 20])
    assert [v for _, v in out] == [x * x for x in items]
    pids = {p for p, _ in out}
    if parallel and _fork_context() is not None:
        # Cut where the weights reach half their total: the heavy last item alone in the child.
        assert [p == os.getpid() for p, _ in out] == [True] * 6 + [False]
    else:
        assert pids == {os.getpid()}
    assert in_halves(_tagged, [3], parallel=parallel) == [(os.getpid(), 9)]


def _toy_trials(parallel, wins):
    """Greedy trials over keys 0..9: a trial wins when its key is in ``wins``; each win
    removes the next key (the model changed, so what follows does too)."""
    gone: set = set()
    log = []

    def propose(tried):
        for k in range(10):
            if k not in tried and k not in gone:
                tried.add(k)
                return k
        return None

    def run(k, r):
        return k, float(r.random()), os.getpid(), len(gone)

    def judge(k, res):
        assert res[3] == len(gone)  # run on the model as it is now, not a stale one
        log.append(res[:2])
        if k in wins:
            gone.add(k + 1)
            return True
        return False

    n = greedy_trials(propose, run, judge, np.random.default_rng(7), parallel=parallel)
    return n, log


@pytest.mark.parametrize("wins", [set(), {0, 4}, {2, 3, 8}, set(range(10))])
def test_greedy_trials_do_not_depend_on_parallel(wins):
    n1, serial = _toy_trials(False, wins)
    n2, forked = _toy_trials(True, wins)
    assert n1 == n2 == len(serial) and forked == serial
    # Each judged trial has its own generator: the k-th spawned from the caller's.
    kids = np.random.default_rng(7).spawn(n1)
    assert [v for _, v in serial] == [float(g.random()) for g in kids]
    expected, gone = [], set()
    for k in range(10):
        if k not in gone:
            expected.append(k)
            if k in wins:
                gone.add(k + 1)
    assert [k for k, _ in serial] == expected


@linux
def test_greedy_trials_run_the_next_trial_in_a_child():
    pids = []

    def propose(tried):
        k = len(tried)
        if k >= 4:
            return None
        tried.add(k)
        return k

    greedy_trials(propose, lambda k, r: os.getpid(), lambda k, pid: pids.append(pid) and False,
                  np.random.default_rng(0), parallel=True)
    assert len(pids) == 4 and pids[0] == pids[2] == os.getpid() and pids[1] != os.getpid() != pids[3]
    assert not multiprocessing.active_children()


def _scene(n_sticks, seed):
    traj = sf.synthetic.random_figure(n_sticks=n_sticks, frames=80, noise=0.01, seed=seed)
    xy = traj.xy.copy()
    xy[np.random.default_rng(0).random(xy.shape[:2]) < 0.1] = np.nan
    obs, _, _ = normalise(xy)
    return traj, obs


def test_merge_scores_are_the_same_in_halves():
    # Bit for bit: a block's fit does not depend on the blocks beside it.
    traj, obs = _scene(6, 5)
    pri = Priors()
    st = initial_state(obs, traj.labels_true, traj.n_parts_true, pri, np.random.default_rng(0))
    st, _, _ = S.run_em(st, obs, pri, S.EMSettings(), 30, np.random.default_rng(0), resample=False)
    out = {}
    for jobs, batch in [(1, 2_000_000), (2, 2_000_000), (1, 1)]:
        cands = S.merge_candidates(st, S.EMSettings())
        settings = S.EMSettings(n_jobs=jobs, batch_size=batch, merge_rank="objective")  # every block fitted
        blocks = S.score_candidates(st, obs, pri, settings, cands, np.random.default_rng(0))
        out[jobs, batch] = ([c.score for c in cands], blocks)
    assert len(out[1, 2_000_000][0]) > 2
    for key in [(2, 2_000_000), (1, 1)]:
        assert out[key][0] == out[1, 2_000_000][0]
        for a, b in zip(out[key][1], out[1, 2_000_000][1]):
            np.testing.assert_array_equal(a.rot, b.rot)
            np.testing.assert_array_equal(a.mu_v, b.mu_v)


def test_residual_ranking_fits_only_the_best_block_and_the_same_one():
    # merge_rank="residual" ranks without the sweeps, so only the merge taken is fitted; its block is
    # the one every-candidate scoring gives it, bit for bit, and so is the merged model.
    traj, obs = _scene(6, 5)
    pri = Priors()
    st = initial_state(obs, traj.labels_true, traj.n_parts_true, pri, np.random.default_rng(0))
    st, _, _ = S.run_em(st, obs, pri, S.EMSettings(), 30, np.random.default_rng(0), resample=False)
    every = S.EMSettings(merge_rank="objective")
    cands = S.merge_candidates(st, every)
    all_blocks = S.score_candidates(st, obs, pri, every, cands, np.random.default_rng(0))
    ranked = S.merge_candidates(st, S.EMSettings())
    blocks = S.score_candidates(st, obs, pri, S.EMSettings(), ranked, np.random.default_rng(0))
    assert [c.score for c in ranked] == [-c.residual for c in ranked]
    b = int(np.argmin([c.residual for c in ranked]))
    assert len(ranked) > 2 and [i for i, x in enumerate(blocks) if x is not None] == [b]
    for name in ("rot", "trans", "local", "ends", "mu_e", "tau_e", "mu_v", "tau_v", "alpha", "beta"):
        np.testing.assert_array_equal(getattr(blocks[b], name), getattr(all_blocks[b], name))
    one = S.apply_merge(st, ranked[b], pri, S.EMSettings(), blocks[b])
    two = S.apply_merge(st, cands[b], pri, every, all_blocks[b])
    np.testing.assert_array_equal(one.rot, two.rot)
    np.testing.assert_array_equal(one.mu_v, two.mu_v)


def test_articulated_split_candidates_are_the_same_in_halves(monkeypatch):
    # Two parts under one label each: every stick is a split candidate.
    from stickfigure.models.em import forked

    sizes = []

    def record(fn, items, **kw):
        sizes.append(len(items))
        return in_halves(fn, items, **kw)

    monkeypatch.setattr(forked, "in_halves", record)
    traj, obs = _scene(6, 8)
    pri = Priors()
    labels = traj.labels_true // 2
    st = initial_state(obs, labels, int(labels.max()) + 1, pri, np.random.default_rng(0))
    st, _, _ = S.run_em(st, obs, pri, S.EMSettings(), 30, np.random.default_rng(0), resample=False)
    one = refine.articulated_split_candidates(st, obs, pri, return_gain=True, n_jobs=1)
    two = refine.articulated_split_candidates(st, obs, pri, return_gain=True, n_jobs=2)
    assert one and min(sizes) > 2  # candidates of several sticks were fitted in halves
    assert [(s, g) for s, _, g in one] == [(s, g) for s, _, g in two]
    for (_, a, _), (_, b, _) in zip(one, two):
        np.testing.assert_array_equal(a, b)


@linux
def test_a_cancellation_swallowed_by_a_finalizer_is_raised_again(monkeypatch):
    # Python reports an exception raised in a finalizer ("Exception ignored in: <Finalize
    # object, dead>") and carries on; the child re-raises the cancellation by SIGALRM until it
    # ends, and keeps the report of that one case off stderr.
    import signal
    from types import SimpleNamespace

    from stickfigure.models.em import forked

    seen = []
    monkeypatch.setattr(forked.sys, "__unraisablehook__", seen.append)
    forked._quiet_unraisable(SimpleNamespace(exc_value=forked._Cancelled()))
    other = SimpleNamespace(exc_value=ValueError("x"))
    forked._quiet_unraisable(other)
    assert seen == [other]
    old = signal.getsignal(signal.SIGALRM)
    try:
        with pytest.raises(forked._Cancelled):
            forked._on_sigterm(signal.SIGTERM, None)
        assert signal.getitimer(signal.ITIMER_REAL)[1] == pytest.approx(forked.CANCEL_RETRY_S)
        forked._disarm()
        assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
    finally:
        forked._disarm()
        signal.signal(signal.SIGALRM, old)


@linux
def test_a_repeat_during_the_childs_cleanup_is_not_reported(monkeypatch, capfd):
    # A repeat of the cancellation (SIGALRM) that landed in the child's cleanup before it
    # disarmed the timer escaped the child, and multiprocessing printed "Process
    # ForkProcess-1:" (seen once in a fit). Here the cleanup is made slow, so that repeats
    # surely land in it.
    from stickfigure.models.em import forked

    real = forked._disarm

    def slow_disarm():
        time.sleep(0.3)
        real()

    monkeypatch.setattr(forked, "CANCEL_RETRY_S", 0.02)
    monkeypatch.setattr(forked, "_disarm", slow_disarm)  # inherited by the forked child
    with Speculative(lambda: time.sleep(30.0)) as job:
        assert job.forked
        time.sleep(0.3)
        start = time.perf_counter()
        job.cancel()
    assert time.perf_counter() - start < 10.0
    err = capfd.readouterr().err
    assert "ForkProcess" not in err and "_Cancelled" not in err, err[-2000:]
