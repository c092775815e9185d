"""Sub-tree moves on the learned forest: cut a joint and re-attach the cut-off part elsewhere.

The greedy search of section 4.2 never undoes a merge. A merge that was the best
at its stage can join two parts that are not neighbours in the body: on motion
capture the thorax and pelvis sticks move nearly as one, so at the stage where a
leg is joined either fits its hip; and a stick dissolved after the search
(:func:`.refine.heldout_dissolve`) is contracted into a joint that links its two
neighbours, whatever they are. The sub-tree move of Meeds et al. (section 3.1.3 of
``000_f464b5e531ae41b5``) answers both in their MCMC: detach a sub-tree from its parent
and re-attach it to another node outside it. :func:`reattach_subtrees` is its greedy counterpart, scored by the
same objective as the merges:

1. For every endpoint ``e`` on a joint ``j``, detaching it cuts its tree in two:
   the part ``A`` holding ``e``'s stick and the rest ``B``. Its current link costs
   the pairwise least-squares joint residual ``r_0`` of ``e``'s stick and its
   nearest partner on ``j`` (:func:`.structure.joint_least_squares`, mean squared
   distance per stick and frame of the two sticks' predictions of a common point).
2. The best other link between ``A`` and ``B`` has residual ``r_1`` (every stick
   pair, one stick in each part). Only cuts with ``r_1 < ratio * r_0`` are tried
   (the residual is a cheap bound; the trial costs EM runs).
3. A trial detaches ``e`` (its own vertex again), scores every merge between the
   two parts by the merge scoring of the search (:func:`.structure.score_candidates`,
   the original link among them), and if the best is not the original link
   performs it and re-runs EM. It is kept when ``criterion`` (the selection's BIC
   or objective) improves; then the next round starts from the new forest.

A move keeps the number of joints and sticks, so BIC and the objective compare
like with like: the change is the fit of the re-placed joint alone.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .model import Observations, Priors, StickState, chain_degree
from .updates import stick_centroids, update_endpoints

__all__ = ["detach_endpoint", "cut_proposals", "reattach_subtrees", "join_trees", "with_spare_endpoint",
           "without_spare_endpoints"]


def detach_endpoint(st: StickState, e: int, priors: Priors) -> StickState:
    """A copy of ``st`` where endpoint ``e`` leaves its (shared) vertex for a new one of its own.

    The new vertex starts at the endpoint's mean with the old vertex's precision;
    the old vertex keeps its precision with one endpoint fewer.
    """
    j = int(st.vertex_of[e])
    J, F, D = st.mu_v.shape
    out = st.copy()
    a = float(st.alpha[j] / st.beta[j])
    n = float(np.sum(st.vertex_of == j))
    out.vertex_of[e] = J
    out.alpha[j] = priors.alpha0 + 0.5 * D * F * (n - 1.0)
    out.beta[j] = out.alpha[j] / a
    alpha_new = priors.alpha0 + 0.5 * D * F
    out.alpha = np.append(out.alpha, alpha_new)
    out.beta = np.append(out.beta, alpha_new / a)
    out.mu_v = np.concatenate([out.mu_v, st.mu_e[e][None]])
    out.tau_v = np.concatenate([out.tau_v, (a + st.tau_t * chain_degree(F))[None]])
    if st.ghosts is not None:
        out.ghosts = st.ghosts.grown(1)
    out._design = None
    out._quat = None
    update_endpoints(out)
    return out


def with_spare_endpoint(st: StickState, priors: Priors) -> StickState:
    """A copy of ``st`` with one more endpoint per stick (E -> E + 1), each on a vertex of its own.

    The new endpoint starts at the centroid of its stick's points (in the stick's
    frame); its vertex at the endpoint's prediction, with the precision the prior and
    the noise level give (:func:`.refine.start_vertices`, as
    :func:`.initialise.initial_state` starts every vertex). Endpoint ``i`` of stick
    ``s`` keeps its place ``i`` among the stick's endpoints; the spare is the last.
    """
    from .refine import start_vertices

    S, E = st.n_sticks, st.ends_per_stick
    J, F, D = st.mu_v.shape
    out = st.copy()
    old = (np.arange(S)[:, None] * (E + 1) + np.arange(E)[None, :]).ravel()
    new = np.arange(S) * (E + 1) + E
    n = S * (E + 1)
    out.vertex_of = np.empty(n, np.int64)
    out.vertex_of[old] = st.vertex_of
    out.vertex_of[new] = J + np.arange(S)
    centroid = stick_centroids(st)
    out.ends = np.empty((n, 3))
    out.ends[old] = st.ends
    out.ends[new] = centroid
    pred = np.einsum("sfdk,sk->sfd", st.rot, centroid) + st.trans  # (S, F, D)
    out.mu_e = np.empty((n, F, D))
    out.mu_e[old] = st.mu_e
    out.mu_e[new] = pred
    out.tau_e = np.empty(n)
    out.tau_e[old] = st.tau_e
    out.alpha = np.concatenate([st.alpha, np.ones(S)])
    out.beta = np.concatenate([st.beta, np.ones(S)])
    out.mu_v = np.concatenate([st.mu_v, np.zeros((S, F, D))])
    out.tau_v = np.concatenate([st.tau_v, np.ones((S, F))])
    start_vertices(out, J + np.arange(S), out.mu_e, priors)
    if st.ghosts is not None:
        out.ghosts = st.ghosts.grown(S)
    out._design = None
    out._quat = None
    update_endpoints(out, new)
    return out


def without_spare_endpoints(st: StickState) -> StickState | None:
    """``st`` with one endpoint fewer per stick (E -> E - 1), or None when a stick is on E joints
    (or E is 2: a stick keeps its two ends).

    From every stick one endpoint on a vertex of its own (the last such) is removed
    with its vertex, which holds no other endpoint: the undone
    :func:`with_spare_endpoint`, wherever the moves left the stick's free endpoints.
    """
    S, E = st.n_sticks, st.ends_per_stick
    cnt = st.vertex_counts()
    alone = (cnt[st.vertex_of] == 1).reshape(S, E)
    if E <= 2 or not alone.any(axis=1).all():
        return None
    drop = np.arange(S) * E + (E - 1 - np.argmax(alone[:, ::-1], axis=1))
    keep_e = np.ones(S * E, bool)
    keep_e[drop] = False
    keep_v = np.ones(st.n_vertices, bool)
    keep_v[st.vertex_of[drop]] = False
    vmap = np.cumsum(keep_v) - 1
    out = st.copy()
    out.vertex_of = vmap[st.vertex_of[keep_e]]
    for name in ("ends", "mu_e", "tau_e"):
        setattr(out, name, getattr(st, name)[keep_e].copy())
    for name in ("mu_v", "tau_v", "alpha", "beta"):
        setattr(out, name, getattr(st, name)[keep_v].copy())
    if st.ghosts is not None:
        out.ghosts = st.ghosts.take(keep_v)
    out._design = None
    out._quat = None
    return out


def _cut_key(st: StickState, e: int) -> tuple:
    """A cut named by point sets: those of endpoint ``e``'s stick and of its partners on its
    vertex (a move's EM run may move points between sticks; then the cut is a new one)."""
    E = st.ends_per_stick
    mates = np.flatnonzero(st.vertex_of == st.vertex_of[e])
    return (tuple(np.flatnonzero(st.labels == e // E).tolist()),
            tuple(sorted(tuple(np.flatnonzero(st.labels == x // E).tolist()) for x in mates if x != e)))


def cut_proposals(st: StickState, obs: Observations, ratio: float) -> list[tuple[float, int]]:
    """Endpoints worth detaching: ``(r_1 / r_0, e)`` for every cut whose best other link has a
    least-squares joint residual below ``ratio`` times the current one, best ratio first."""
    from .structure import components, joint_least_squares, pair_stats

    E = st.ends_per_stick
    cnt = st.vertex_counts()
    seen = st.design(obs).n
    stats = pair_stats(st)
    # Centroid of each stick's points in its own frame: the ridge's anchor for a joint that
    # is not there yet (the residual is a minimum over the joint's place, the anchor only
    # fixes the directions the motion leaves open).
    size = st.stick_sizes()
    cen = st.design(obs).stick_sum(st.local) / np.maximum(size, 1)[:, None]
    pair: dict[tuple[int, int], float] = {}

    def residual(a: int, b: int) -> float:
        key = (min(a, b), max(a, b))
        if key not in pair:
            pair[key] = joint_least_squares(st, list(key), [cen[key[0]], cen[key[1]]], stats=stats, seen=seen)[1]
        return pair[key]

    whole = components(st)[0]
    out: list[tuple[float, int]] = []
    for j in np.flatnonzero(cnt >= 2):
        ends = np.flatnonzero(st.vertex_of == j)
        # With two endpoints both detachments make the same cut: try one.
        for e in ends[:1] if ends.size == 2 else ends:
            s = int(e // E)
            r0 = min(joint_least_squares(st, [s, int(x // E)], [st.ends[e], st.ends[x]], stats=stats, seen=seen)[1]
                     for x in ends if x != e)
            comp = components(st, e)[0]
            side = comp == comp[s]
            rest = (whole == whole[s]) & ~side  # a forest: the cut always separates
            r1 = min(residual(int(a), int(b)) for a in np.flatnonzero(side) for b in np.flatnonzero(rest))
            if r1 < ratio * r0:
                out.append((r1 / max(r0, 1e-300), int(e)))
    out.sort()
    return out


def reattach_subtrees(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
                      value: float, criterion: Callable[[StickState, float], float], *, ratio: float = 0.8,
                      max_trials: int | None = None) -> tuple[StickState, float, int, list[dict]]:
    """Greedy sub-tree moves (module docstring) until no proposed cut improves ``criterion``.

    Returns the state, its objective, the EM sweeps run, and one record per kept
    move: ``{"sticks": [a, b], "was": [c, d]}``, the stick pairs of the new and the
    old link (stick numbers of the state at that move). A cut is tried once per
    kept move (``max_trials``, default twice the sticks, bounds the trials). The
    trials are greedy (:func:`.trials.greedy_trials`: each draws from its own
    generator spawned from ``rng``; with ``settings.n_jobs`` > 1 the trial that
    follows a loss runs beside the current one).
    """
    from .structure import apply_merge, components, merge_candidates, out_of_reach, run_em, score_candidates
    from .trials import greedy_trials

    E = st.ends_per_stick
    max_trials = 2 * st.n_sticks if max_trials is None else max_trials
    cur = {"st": st, "value": value, "best": criterion(st, value)}
    moves: list[dict] = []
    sweeps = 0

    def propose(tried: set) -> int | None:
        # A cut is tried once per kept move: its key carries the number of moves kept so far.
        now = cur["st"]
        if len(tried) >= max_trials:
            return None
        props = [e for _, e in cut_proposals(now, obs, ratio) if (len(moves), _cut_key(now, e)) not in tried]
        if not props:
            return None
        tried.add((len(moves), _cut_key(now, props[0])))
        return int(props[0])

    def run(e: int, r: np.random.Generator) -> tuple[StickState, float, int, dict] | None:
        now = cur["st"]
        j = int(now.vertex_of[e])
        partners = sorted({int(x // E) for x in np.flatnonzero(now.vertex_of == j) if x != e})
        cut = detach_endpoint(now, e, priors)
        if cut.vertex_counts()[j] >= 2 and cut.only_one_point_sticks(j):
            return None  # it would leave a joint that ties nothing (StickState.only_one_point_sticks)
        comp = components(cut)[0]
        whole = components(now)[0]
        tree = whole == whole[e // E]
        cands = []
        for c in merge_candidates(cut, settings, cut.design(obs).n):
            sticks = np.unique(c.ends // E)
            on = comp[sticks] == comp[e // E]
            if tree[sticks].all() and on.any() and not on.all():  # links the two parts of the cut
                cands.append(c)
        if not cands:
            return None
        blocks = score_candidates(cut, obs, priors, settings, cands, r)
        b = int(np.argmax([c.score for c in cands]))
        c = cands[b]
        sticks = sorted({int(x) for x in c.ends // E})
        if j in (c.j1, c.j2) and {x for x in sticks if comp[x] == comp[e // E]} == {int(e // E)}:
            return None  # the best is the old link (e's stick back on j): nothing to move
        trial = apply_merge(cut, c, priors, settings, blocks[b])
        trial, val, n = run_em(trial, obs, priors, settings, settings.n_iter, r,
                               stop=out_of_reach(cur["best"], criterion))
        return trial, val, n, {"sticks": [int(x) for x in sticks], "was": [int(e // E), partners[0]]}

    def judge(e: int, result: tuple[StickState, float, int, dict] | None) -> bool:
        nonlocal sweeps
        if result is None:
            return False
        trial, val, n, move = result
        sweeps += n
        score = criterion(trial, val)
        if score <= cur["best"]:
            return False
        moves.append(move)
        cur.update(st=trial, value=val, best=score)
        return True

    greedy_trials(propose, run, judge, rng, parallel=settings.n_jobs > 1)
    return cur["st"], cur["value"], sweeps, moves


def join_trees(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
               value: float, max_trees: int) -> tuple[StickState, float, int, list[list[int]]]:
    """Join a forest of more than ``max_trees`` trees by the best merges between trees.

    The search selects a forest where no joint between two trees pays by the
    criterion. That is right for independent objects, but on a figure known to be
    one piece (a motion-capture take of one subject) a forest means a segment the
    sticks do not resolve: on CMU 85_02 seen from 42/14 and 298/14 degrees the right
    thigh marker sits on the hip or pelvis stick, the leg's joint with it is not
    rigid, and the leg is left as a tree of its own (joining it lowered BIC by 760 and
    1390 there). Each step scores every valid merge that links two trees as the search
    scores merges (:func:`.structure.score_candidates`), performs the best and
    re-runs EM, until ``max_trees`` trees are left (or no such merge is valid).

    Returns the state, its objective, the EM sweeps run and the stick pairs joined
    (stick numbers of the state at each join).
    """
    from .structure import apply_merge, components, merge_candidates, run_em, score_candidates

    E = st.ends_per_stick
    joined: list[list[int]] = []
    sweeps = 0
    while True:
        comp = components(st)[0]
        if int(comp.max()) + 1 <= max_trees:
            break
        cands = [c for c in merge_candidates(st, settings, st.design(obs).n)
                 if np.unique(comp[np.unique(c.ends // E)]).size > 1]
        if not cands:
            break
        blocks = score_candidates(st, obs, priors, settings, cands, rng)
        b = int(np.argmax([c.score for c in cands]))
        joined.append(sorted({int(x) for x in cands[b].ends // E}))
        st = apply_merge(st, cands[b], priors, settings, blocks[b])
        st, value, n = run_em(st, obs, priors, settings, settings.n_iter, rng)
        sweeps += n
    return st, value, sweeps, joined
