"""Work run beside the structure search, in forked processes.

Three kinds of work use the second core (``n_jobs`` > 1):

* **The second start** (:func:`stickfigure.models.em.fit_stages`) is only kept
  when the first search leaves a stick that is not rigid, which is known only
  when the first search ends. It is therefore started *speculatively* in a child
  process (:class:`Speculative`) at the same time as the first, at the lowest
  priority, and stopped as soon as the first search shows it is not needed. When
  it is needed and not yet done, it gets its priority back where the system
  allows it (a niced process can be starved on a busy machine).
* **Greedy trials** (:mod:`.trials`): the trial that follows a loss runs beside
  the current one.
* **Batched fits of independent blocks** (:func:`in_halves`): the merge
  candidates' block EM runs and the articulated-split candidates are disjoint
  unions of blocks, so half of them is fitted in a child.

The results never depend on ``n_jobs``: the second start and every trial draw
from their own generators (spawned from the caller's, which
:meth:`numpy.random.Generator.spawn` does without advancing the caller's
stream), and a block's fit does not depend on the blocks fitted beside it
(bit for bit: tests/test_em_forked.py).

Only the ``fork`` start method is used (Linux): the child inherits the data and
the state without pickling them, and only its result travels back through a
pipe. Forking a process that runs other Python threads can deadlock the child
(a lock held by a thread that does not exist there), so with other threads
alive (tqdm's progress-bar monitor included: em's own bar starts none), and
on other platforms, the work runs in this process, one part after the other.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
import traceback
from typing import Any, Callable

__all__ = ["Speculative", "in_halves"]


def _fork_context() -> Any:
    """The fork context where forking this process is safe (Linux, no other Python thread), else None."""
    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return None
    # Any thread, tqdm's progress-bar monitor included: a fork taken while it refreshes a bar
    # leaves tqdm's or stderr's lock held in the child. (The demo's hangs, once suspected of
    # this, came from result: see there.)
    if any(t is not threading.main_thread() for t in threading.enumerate()):
        return None
    return multiprocessing.get_context("fork")


class _Cancelled(BaseException):
    """Raised in a child when its parent cancels it (SIGTERM)."""


#: Seconds after which a cancellation the child has not acted on is raised again (:func:`_on_sigterm`).
CANCEL_RETRY_S = 0.2

#: Set by :func:`_child` once it has stopped its job (done or cancelled): from then on a
#: cancellation, or a repeat of one, has nothing left to stop (:func:`_on_sigterm`).
_finishing = False


def _on_sigterm(signum: int, frame: Any) -> None:
    """Raise :class:`_Cancelled` now, and again every ``CANCEL_RETRY_S`` (SIGALRM) until :func:`_child`
    ends: Python swallows an exception raised inside a finalizer, a ``__del__`` or an after-fork
    hook ("Exception ignored in: <Finalize object, dead>", seen when the signal came while
    multiprocessing closed a pipe), and the child would run on as if never cancelled while its
    parent waits to join it. (Timers are not inherited across fork; the parent is not affected.)

    Nothing is raised once the child is finishing (``_finishing``): a repeat that landed in
    :func:`_child`'s cleanup before it disarmed the timer escaped ``_child``, and
    multiprocessing printed "Process ForkProcess-1:" (its traceback cut short by the next
    repeat) for a cancellation that had already been honoured.
    """
    if _finishing:
        return
    signal.signal(signal.SIGALRM, _on_sigterm)
    signal.setitimer(signal.ITIMER_REAL, CANCEL_RETRY_S, CANCEL_RETRY_S)
    raise _Cancelled


def _quiet_unraisable(unraisable: Any) -> None:
    """``sys.unraisablehook`` of a child: a cancellation swallowed in a finalizer is raised again
    (:func:`_on_sigterm`), so its "Exception ignored" report would only be noise."""
    if not isinstance(unraisable.exc_value, _Cancelled):
        sys.__unraisablehook__(unraisable)


def _disarm() -> None:
    """No more repeats of a cancellation (see :func:`_on_sigterm`)."""
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    signal.signal(signal.SIGALRM, signal.SIG_IGN)


def _child(conn: Any, reader: Any, job: Callable[[], Any], group: bool, gate: tuple | None = None) -> None:
    # The parent's end of the pipe, inherited: closed, so that the pipe breaks when the parent
    # closes it (a write nobody will read then fails instead of waiting, see Speculative._close).
    reader.close()
    if gate is not None:
        # Wait until the parent has set this process's group and priority (its end closed or
        # written): the job must not start at the parent's priority.
        wait, signal_end = gate
        signal_end.close()
        try:
            wait.recv_bytes()
        except EOFError:
            pass
        wait.close()
    if group:
        try:
            os.setpgid(0, 0)  # (the parent does it too: whichever runs first)
        except OSError:
            pass
        # Out of the terminal's foreground group, a write (a warning) would stop it under
        # ``stty tostop`` and leave the parent waiting for ever.
        signal.signal(signal.SIGTTOU, signal.SIG_IGN)
    # A cancelled child unwinds its own ``with Speculative`` blocks, which cancel its children
    # in turn (a child may fork: the second start's trials); killed outright, they would run on.
    # SIGTERM arrives blocked (see _start); a cancellation that came before this point is
    # delivered at the unblocking, inside the ``try`` that handles it.
    global _finishing
    _finishing = False
    signal.signal(signal.SIGTERM, _on_sigterm)
    sys.unraisablehook = _quiet_unraisable
    try:
        try:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
            out = ("ok", job())
        except _Cancelled:
            raise
        except BaseException:  # reported to the parent, which raises it there
            out = ("error", traceback.format_exc())
        conn.send(out)
    except (_Cancelled, BrokenPipeError):  # nobody waits for the result any more
        pass
    finally:
        # First, before any call: Python runs a signal's handler only at some instructions (a
        # call, a backward jump, a function's start), and none comes between the job's end (or
        # the ``except`` above) and this line, so no repeat lands before it.
        _finishing = True
        _disarm()
        conn.close()
        _stop_children()


def _stop_children() -> None:
    """Stop the children this process started and has not collected.

    A cancellation (SIGTERM) can arrive anywhere, even between forking a child and
    the ``with`` block taking charge of it. Such a child would outlive the unwinding,
    and at exit multiprocessing joins its (non-daemonic) children, while the child
    waits to write a result nobody reads: both would wait for ever (the test
    ``test_cancel_does_not_wait_for_a_child_nobody_collects`` builds that case).
    Further cancellations are ignored meanwhile, so this cleanup runs to its end.
    """
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _disarm()
    for proc in multiprocessing.active_children():
        proc.terminate()
        proc.join()


def _start(proc: Any) -> None:
    """``proc.start()`` with SIGTERM blocked while it forks.

    Python runs a signal's handler at the next bytecode, and right after ``fork`` that is
    inside the interpreter's after-fork hooks (logging's ``_releaseLock``, threading's
    ``_after_fork``). There a cancellation (:func:`_on_sigterm`) was swallowed as "Exception
    ignored", with the logging lock possibly left held, and the child ran on as if never
    cancelled while its parent waited to join it (a loop of forks cancelled 20 times hung
    on the sixth). Blocked, the signal waits until the hooks are done and then lands in
    ordinary code. The new child inherits the mask and unblocks it in :func:`_child`.
    """
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


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
    ``nice`` lowers the child's scheduling priority (:func:`os.nice`): a job that may
    well be thrown away should leave the cores to work that is surely needed, such as
    the speculative trials (:mod:`.trials`) the first search runs beside itself. When
    its result is asked for before it is ready, it gets this process's priority back
    where the system allows it (:meth:`result`).
    """

    def __init__(self, job: Callable[[], Any], *, parallel: bool = True,
                 here: Callable[[], Any] | None = None, name: str = "the job", nice: int = 0) -> None:
        self._job = job if here is None else here
        self._name = name
        self._nice = nice
        self._proc = None
        self._conn = None
        ctx = _fork_context() if parallel else None
        if ctx is not None:
            recv, send = ctx.Pipe(duplex=False)
            gate = ctx.Pipe(duplex=False) if nice else None
            # Not a daemon: a daemonic process may not have children of its own. It never outlives
            # the ``with`` block that started it (cancel).
            proc = ctx.Process(target=_child, args=(send, recv, job, bool(nice), gate), daemon=False)
            _start(proc)
            if gate is not None:
                # Its own process group, so that it and the children it forks can be reniced
                # together (result); the priority set from here, so that result cannot undo it
                # before the child has set it.
                try:
                    os.setpgid(proc.pid, proc.pid)
                except OSError:  # the child has done it already
                    pass
                try:
                    os.setpriority(os.PRIO_PROCESS, proc.pid, os.getpriority(os.PRIO_PROCESS, 0) + nice)
                except OSError:  # already gone
                    pass
                # The child waits for this before its job (without it, a job that starts at once
                # ran at this process's priority until the line above; a test saw it do so).
                gate[0].close()
                try:
                    gate[1].send_bytes(b"go")
                except OSError:  # already gone
                    pass
                gate[1].close()
            send.close()
            self._proc, self._conn = proc, recv
        #: Whether the job was forked into a child process (it stays true after the result).
        self.forked = self._proc is not None

    def result(self) -> Any:
        """The job's value: the child's, or ``job()`` run here when nothing was forked.

        A child started with ``nice`` that is still running gets this process's
        priority back, with the children it forked (its process group), where the
        system allows it (``os.setpriority``: root with CAP_SYS_NICE, or a raised
        RLIMIT_NICE): on a machine kept busy by other work a niced process gets
        almost no CPU time, and it must not hold up a result that is now needed.
        Where that is not allowed it keeps its priority, which costs nothing on an
        idle machine. (Racing it with a copy at normal priority was tried: the
        copy's own forked work took both cores from the niced child, which lost its
        head start, and a human-sized figure took 136 s instead of 98.)
        Interrupted while it waits (a cancellation of this process, or Ctrl-C), it
        stops the child before re-raising.
        """
        if self._proc is None:
            return self._job()
        if self._nice and not self._conn.poll():
            try:
                os.setpriority(os.PRIO_PGRP, self._proc.pid, os.getpriority(os.PRIO_PROCESS, 0))
            except OSError:
                pass
        try:
            status, payload = self._conn.recv()  # before join: a large result fills the pipe
        except EOFError:
            proc = self._proc
            self._close()
            raise RuntimeError(f"{self._name}'s process died (exit code {proc.exitcode})") from None
        except BaseException:
            # Interrupted while waiting (this process cancelled, or Ctrl-C): the result is no
            # longer wanted, and a child writing a result larger than the pipe holds would never
            # exit if joined without being stopped (2 of 32 demo runs hung so).
            self.cancel()
            raise
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
            # The read end first: a child still writing then gets a broken pipe instead of
            # waiting for a reader while this process waits for it to exit.
            self._conn.close()
            self._proc.join()
            self._proc = self._conn = None

    def __enter__(self) -> "Speculative":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.cancel()


def in_halves(fn: Callable[[list], list], items: list, *, parallel: bool, weights: Any = None) -> list:
    """``fn(items)`` computed as ``fn(first half) + fn(second half)``, the second half in a forked child.

    ``fn`` maps a list of independent items to one result per item, so that
    splitting the list changes nothing (a disjoint union of blocks fitted
    together or apart gives the same numbers). The halves are cut where the
    cumulative ``weights`` (the items' costs; default 1 each) reach half their
    total. With one item or ``parallel`` false, ``fn(items)`` runs here; where
    forking is not safe, both halves run here, one after the other.
    """
    n = len(items)
    if n < 2 or not parallel:
        return list(fn(items))
    w = [1.0] * n if weights is None else [float(x) for x in weights]
    total, acc, h = sum(w), 0.0, 0
    while h < n - 1 and acc + w[h] <= total / 2:
        acc += w[h]
        h += 1
    h = max(h, 1)
    second = items[h:]
    with Speculative(lambda: list(fn(second)), parallel=parallel, name="a batch of block fits") as other:
        out = list(fn(items[:h]))
        return out + other.result()
