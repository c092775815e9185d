"""Greedy trials with the next one run beside the current one.

Some refinements of the structure search are greedy loops: propose a change of the
current model, fit it (an EM run of up to ``n_iter`` sweeps), keep it when it wins,
else propose the next (:func:`.refine.resplit_pairs`, :func:`.refine.dissolve_small_sticks`,
:func:`.refine.heldout_dissolve`, :func:`.bridge.unpair_hubs`, :func:`.tree.reattach_subtrees`).
Most trials lose, and they are costly: on the human-sized random figure seed 2 (one
process) the held-out check's 12 trials, each run to the 200-sweep cap, took about 40 %
of the search with their predictions.
A losing trial leaves the model as it was, and so the proposal that follows it. So
while one trial runs here, the trial that follows if it loses runs in a forked child
(:class:`.forked.Speculative`); when this one wins, the child is stopped and the next
proposal is made from the new model. On one core (``parallel`` false, or where forking
is not safe) the same trials run one after the other.

Each trial draws from its own generator, the k-th judged trial from the k-th child
spawned from the caller's generator (:func:`numpy.random.Generator.spawn`, which does
not advance the caller's stream). A trial's random numbers therefore depend neither
on how many the trials before it drew (an EM run that converges early draws fewer)
nor on the process it ran in: the result does not depend on ``parallel``.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

from .forked import Speculative

__all__ = ["greedy_trials"]


def greedy_trials(propose: Callable[[set], Hashable | None], run: Callable[[Hashable, np.random.Generator], Any],
                  judge: Callable[[Hashable, Any], bool], rng: np.random.Generator, *,
                  parallel: bool = False) -> int:
    """Run trials until ``propose`` has none left; returns how many were judged.

    Parameters
    ----------
    propose : callable ``propose(tried) -> key or None``
        The next trial on the current model, None when there is none. ``tried`` is
        the set of what was proposed before; ``propose`` adds what it proposes (and
        whatever it passes over for good) to it. It must only read the model.
    run : callable ``run(key, rng) -> result``
        Fits the trial ``key`` from the current model with generator ``rng``; must
        not change the model (it may run in a child process, so ``result`` must be
        picklable).
    judge : callable ``judge(key, result) -> bool``
        Keeps the trial (making ``result`` the current model) and returns True, or
        returns False and leaves the model as it was.
    rng : numpy.random.Generator
        Parent of the trials' generators; its own stream is not advanced.
    parallel : bool
        Run the trial that follows a loss beside the current one, in a forked child.
    """
    from .structure import child_rng

    gens: list[np.random.Generator] = []

    def gen(k: int) -> np.random.Generator:  # spawned in order, whichever process uses them
        while len(gens) <= k:
            gens.append(child_rng(rng))
        return gens[k]

    tried: set = set()
    k = 0
    while True:
        key = propose(tried)
        if key is None:
            return k
        # What follows if this trial loses: the model stays, so the proposal does too.
        after = set(tried)
        nxt = propose(after)
        g_this, g_next = gen(k), gen(k + 1)
        job = (lambda key2=nxt, g=g_next: run(key2, g)) if nxt is not None else (lambda: None)
        # Without parallel, Speculative runs the job only when its result is asked for.
        with Speculative(job, parallel=parallel and nxt is not None, name="a speculative trial") as ahead:
            result = run(key, g_this)
            k += 1
            if judge(key, result) or nxt is None:
                continue  # (leaving the block stops the child)
            tried = after
            result = ahead.result()
            k += 1
            judge(nxt, result)
