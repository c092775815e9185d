"""Running the second start's structure search beside the first, in a forked process.

The second, finer start (:func:`stickfigure.models.em.fit_stages`) is only kept
when the first search leaves a stick that is not rigid, which is known only
when the first search ends. On a machine with two cores the second search is
therefore started *speculatively* in a child process at the same time as the
first, and stopped as soon as the first search shows it is not needed: the
wall time is that of the longer search instead of the sum of both, and nothing
is lost where the second is not needed (the first runs in this process, as it
would alone).

The results do not depend on whether the second search runs in a child
process or afterwards in this one: it draws from its own generator (spawned
from the caller's, which :meth:`numpy.random.Generator.spawn` does without
advancing the caller's stream), so the first search, the second and the final
re-fit draw the same numbers either way.

Only the ``fork`` start method is used (Linux): the child inherits the data and
the state without pickling them, and only its result travels back through a
pipe. Forking a process that runs other Python threads can deadlock the child
(a lock held by a thread that does not exist there), so with other threads
alive (tqdm's progress-bar monitor excepted: the child shows no progress), and
on other platforms, the second search runs after the first, in this process.
"""

from __future__ import annotations

import multiprocessing
import sys
import threading
import traceback
from typing import Any, Callable

__all__ = ["Speculative"]


def _fork_context() -> Any:
    """The fork context where forking this process is safe (Linux, no other Python thread), else None."""
    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return None
    # tqdm's monitor thread (alive after any progress bar) only takes tqdm's own lock, which the
    # child never uses: it shows no progress bar.
    if any(t is not threading.main_thread() and type(t).__name__ != "TMonitor" for t in threading.enumerate()):
        return None
    return multiprocessing.get_context("fork")


def _child(conn: Any, job: Callable[[], Any]) -> None:
    try:
        out = ("ok", job())
    except BaseException:  # reported to the parent, which raises it there
        out = ("error", traceback.format_exc())
    try:
        conn.send(out)
    finally:
        conn.close()


class Speculative:
    """A job started now in a forked child and either collected or cancelled later.

    ``Speculative(job, parallel=True)`` forks a child that runs ``job()`` (where
    that is safe: see the module docstring);
    :meth:`result` waits for it and returns its value (raising ``RuntimeError``
    with the child's traceback if it failed), :meth:`cancel` stops it. Where
    forking is not possible or ``parallel`` is false, :meth:`result` runs ``job()``
    in this process (``here()`` instead when given: the same work, e.g. with a
    progress bar the child must not show) and :meth:`cancel` does nothing. Use as
    a context manager so the child never outlives an exception in the parent.
    ``name`` says what the job is in the errors :meth:`result` raises.
    """

    def __init__(self, job: Callable[[], Any], *, parallel: bool = True,
                 here: Callable[[], Any] | None = None, name: str = "the job") -> None:
        self._job = job if here is None else here
        self._name = name
        self._proc = None
        self._conn = None
        ctx = _fork_context() if parallel else None
        if ctx is not None:
            recv, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child, args=(send, job), daemon=True)
            proc.start()
            send.close()
            self._proc, self._conn = proc, recv
        #: Whether the job was forked into a child process (it stays true after the result).
        self.forked = self._proc is not None

    def result(self) -> Any:
        if self._proc is None:
            return self._job()
        try:
            status, payload = self._conn.recv()  # before join: a large result fills the pipe
        except EOFError:
            self._proc.join()
            raise RuntimeError(f"{self._name}'s process died (exit code {self._proc.exitcode})") from None
        finally:
            self._close()
        if status != "ok":
            raise RuntimeError(f"{self._name} failed in its process:\n{payload}")
        return payload

    def cancel(self) -> None:
        if self._proc is not None:
            self._proc.terminate()
            self._close()

    def _close(self) -> None:
        if self._proc is not None:
            self._proc.join()
            self._conn.close()
            self._proc = self._conn = None

    def __enter__(self) -> "Speculative":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.cancel()
