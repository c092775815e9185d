"""Structure learning (section 4.2, Fig. 3): EM with resampling, then greedy vertex merging.

1. ``run_em``: EM sweeps, resampling R every ``resample_every`` iterations.
2. Repeatedly: list every *valid* vertex-pair merge (the two vertices lie in
   different trees of the stick/vertex forest, so a stick never gets both
   endpoints on one vertex and no cycle appears), score each by the change of
   the objective after ``n_iter_merge`` EM iterations on a warm-started copy,
   perform the best and re-optimise with ``n_iter`` iterations (resampling R).
   Every stage's model and objective are kept.

Deviations from the printed algorithm, each a parameter (docs/em.md):

* ``merge_scope="local"`` (default): a candidate's 20 iterations update only
  the sticks that own an endpoint on one of the two vertices, their endpoints
  and all their vertices, with the global precisions and the rest of the model
  held fixed (endpoints of other sticks on those vertices enter as fixed
  *ghosts*). The score is then the exact change of the full objective under
  that block update. All candidates are optimised together as one disjoint
  union of blocks (batched). ``"full"`` runs the 20 iterations on a copy of the
  whole model, one candidate at a time (the paper; slow).
* ``merge_init="joint"`` (default): the merged vertex starts at the least-squares
  joint of the sticks involved: the local points ``k_i`` minimising
  ``sum_f sum_i |R_s(i),f k_i + t_s(i),f - v_f|^2`` (v_f eliminated; a small ridge
  towards the current k). The paper's ``"mean"`` starts the merged vertex at the
  average of the two and leaves K unchanged, so the 20 iterations must move the
  endpoints themselves. With ``"joint"``, the two endpoints of a stick that is
  not yet joined to anything are interchangeable and only one merge per stick
  pair is scored (the endpoint nearer the solution is used).
* ``max_candidates`` (default 40): score only the candidates with the smallest
  least-squares joint residual (a cheap bound); ``None`` scores all of them (the
  paper). The bound only matters for large figures (more than 9 sticks at the
  first stage); pruned candidates come back at later stages.
* ``merge_baseline`` (default True): a candidate's score is compared with the
  model run for the same ``n_iter_merge`` iterations without the merge (once per
  stage), instead of with the model before those iterations. EM on sticks with
  few points keeps creeping up for hundreds of iterations (an alternating
  least-squares valley between rotations and local shape), and without the
  baseline that creep is credited to whichever merge touches those sticks.
  With ``merge_rank="residual"`` (the default) no score is an objective change
  and the baseline is not run.
* ``reuse_scores`` (default True): a candidate's score is kept from the stage
  where it was computed while none of its sticks was involved in a later merge
  or changed more than a quarter of its points; the best candidate is always re-scored before it is taken
  (lazy greedy), so a stale score can only delay a merge, never force one.
  Each stage then scores O(J) new candidates instead of O(J^2).
* ``refine_sticks`` (default True): after the first EM run, split sticks that are
  not rigid and join pairs that move as one, both by BIC (``refine.py``).
* ``tol``: stop an EM run early once the objective changed by less than
  ``tol * |objective|`` over ``resample_every`` iterations and the last resampling
  moved at most 2% of the points (sampled assignments keep flipping a few
  ambiguous points near joints). ``tol=0`` runs the fixed number of iterations.
* ``remerge`` (default True): when the held-out check (``refine.heldout_dissolve``)
  dissolves sticks, the merge loop (:func:`greedy_merges`) goes on from that state,
  because a dissolved stick takes its joints with it and the trees it linked would
  stay apart; the best stage by the selection criterion among the dissolved state
  and those merges is kept.
* ``split_dissolved`` (default 4): before that, one round of articulated splits
  (``refine.articulated_split_round``) on the sticks of at least this many points,
  so that a stick that took a dissolved segment's points (a thigh's markers on the
  pelvis) gives the segment back before the search re-attaches what hung from it;
  0 turns it off.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import numpy as np

from .assign import resample_assignments
from .forked import in_halves
from .model import (Ghosts, Observations, Priors, StickState, chain_degree, free_endpoint_terms, objective,
                    objective_terms)
from .updates import em_sweep, update_endpoints

__all__ = ["EMSettings", "run_em", "components", "merge_candidates", "Candidate", "score_candidates",
           "apply_merge", "learn_structure", "Stage", "stick_edges", "n_parameters", "bic",
           "rigid_joints", "search_frames", "extend_frames", "out_of_reach"]


@dataclass(frozen=True)
class EMSettings:
    """Parameters of the learning algorithm (see :class:`stickfigure.models.em.EMSkeleton`)."""

    n_iter: int = 200
    n_iter_merge: int = 20
    resample_every: int = 10
    resample: str = "sample"
    min_stick_points: int = 3
    merge_scope: str = "local"
    merge_init: str = "joint"
    max_candidates: int | None = 40
    max_merges: int | None = None
    tol: float = 1e-4
    batch_size: int = 2_000_000
    n_procrustes: int = 1
    merge_baseline: bool = True
    n_polish: int = 3
    reuse_scores: bool = True
    refine_sticks: bool = True
    endpoint_init: str = "axis"
    n_ends: int = 3
    articulated_rounds: int = 4
    split_axes: int = 1
    dissolve_points: int = 3
    resplit: bool = True
    holdout: float | None = 0.15
    holdout_masks: int = 1
    holdout_points: int = 2
    dissolve_scope: str = "all"
    remerge: bool = True
    split_dissolved: int = 4
    unpair: bool = True
    bridge_points: int = 2
    split_hubs: bool = True
    reattach: bool = True
    spare_end: bool = False
    hub_end: bool = True
    bic_free_ends: bool = True
    bic_rotations: str = "all"
    max_trees: int | None = None
    merge_rank: str = "residual"
    align_mirrors: bool = True
    # Processes the search may use (forked.py); the result does not depend on it.
    n_jobs: int = 1

    @property
    def state_ends(self) -> int:
        """Endpoints a stick has in the state: ``n_ends``, one more with ``hub_end``."""
        return self.n_ends + int(self.hub_end)


def child_rng(rng: np.random.Generator) -> np.random.Generator:
    """An independent generator drawn from ``rng`` without advancing its stream (``spawn``);
    for a bit generator without a seed sequence, seeded from ``rng``'s stream instead."""
    try:
        return rng.spawn(1)[0]
    except TypeError:
        return np.random.default_rng(int(rng.integers(2**63 - 1)))


# ----------------------------------------------------------------------------- EM runs
def run_em(st: StickState, obs: Observations, priors: Priors, settings: EMSettings, n_iter: int,
           rng: np.random.Generator, *, resample: bool = True, precisions: bool = True,
           local: bool = True, min_iter: int = 30,
           stop: Callable[[int, int, StickState, float], bool] | None = None) -> tuple[StickState, float, int]:
    """Up to ``n_iter`` EM sweeps, resampling R every ``settings.resample_every`` (not after the last).

    With ``settings.tol > 0`` the run stops early (never before ``min_iter`` sweeps)
    once converged. ``stop(sweeps_done, sweeps_left, state, objective)``, called at
    every convergence check (with ``settings.tol > 0``), ends the run when it returns
    True (a trial that can no longer win, :func:`out_of_reach`).
    Returns the state, its objective and the number of sweeps done.
    """
    every = settings.resample_every if resample and settings.resample_every else 0
    check = every or 10
    prev = None
    changed = 0
    # Sampled assignments keep flipping a few ambiguous points (near joints) for ever: a run has
    # converged when the objective settled and at most 2% of the points moved.
    settled = max(1, int(0.02 * obs.n_points))
    it = 0
    for it in range(1, n_iter + 1):
        em_sweep(st, obs, priors, precisions=precisions, local=local, n_procrustes=settings.n_procrustes,
                 global_rotations=it % check == 1, use_polar=it == 1)
        if it % check == 0 and it < n_iter:
            if settings.tol > 0:
                cur = objective(st, obs, priors)
                if (prev is not None and it >= min_iter and changed <= settled
                        and abs(cur - prev) <= settings.tol * abs(cur)):
                    break
                if stop is not None and stop(it, n_iter - it, st, cur):
                    break
                prev = cur
            if every:
                st, changed = resample_assignments(st, obs, priors, rng, mode=settings.resample,
                                                   min_points=settings.min_stick_points)
    return st, objective(st, obs, priors), it


def out_of_reach(best: float, criterion: Callable[[StickState, float], float],
                 safety: float = 2.0) -> Callable[[int, int, StickState, float], bool]:
    """A ``stop`` for :func:`run_em` that ends a trial which can no longer beat ``best``.

    The trials of the refinements (a dissolved stick, a re-split pair, a moved
    sub-tree) are kept only when ``criterion(state, objective)`` ends above the
    current model's, and most end thousands of BIC units below it (human-sized
    figures: 460-28 100 after the full run). The criterion's rise per block of
    sweeps between checks does not grow as EM goes on (measured: it slows or holds,
    resampling jumps aside), so from the last block's rise (the larger of the
    last two, against such a jump) the rest of the run adds at most
    ``blocks left x rise``; the trial stops when even ``safety`` times that
    leaves it below ``best``. Never before three checks (the first blocks' rise
    is the fastest).
    """
    hist: list[tuple[int, float]] = []  # (sweeps done, criterion) at each check

    def stop(done: int, left: int, st: StickState, value: float) -> bool:
        hist.append((done, criterion(st, value)))
        if len(hist) < 3:
            return False
        (_, c3), (i2, c2), (i1, c1) = hist[-3:]
        rise = max(c1 - c2, c2 - c3, 0.0)
        return c1 + safety * rise * left / (i1 - i2) < best

    return stop


# ----------------------------------------------------------------------- graph helpers
def components(st: StickState, without: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of the stick/vertex forest.

    ``without``: an endpoint left out of its vertex (the forest as it would be with that
    endpoint detached; :mod:`.tree` uses it to find the two parts of a cut).

    Returns
    -------
    comp_of_stick : (S,) int, comp_of_vertex : (J,) int
    """
    S, J = st.n_sticks, st.n_vertices
    parent = np.arange(S)

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    first = -np.ones(J, np.int64)
    E = st.ends_per_stick
    keep = np.ones(st.vertex_of.size, bool)
    if without is not None:
        keep[without] = False
    for i in np.flatnonzero(keep):
        j, s = st.vertex_of[i], i // E
        if first[j] < 0:
            first[j] = s
        else:
            ra, rb = find(s), find(int(first[j]))
            if ra != rb:
                parent[ra] = rb
    comp = np.array([find(s) for s in range(S)])
    _, comp = np.unique(comp, return_inverse=True)
    # A vertex belongs to the component of its (kept) endpoints; the only one that can be left
    # without any is the detached endpoint's own, which goes with that endpoint's stick.
    owner = first.copy()
    if without is not None and owner[st.vertex_of[without]] < 0:
        owner[st.vertex_of[without]] = without // E
    return comp, comp[owner]


def stick_edges(st: StickState, obs: Observations | None = None) -> tuple[list[tuple[int, int]], list[int]]:
    """Stick pairs joined by a shared vertex, and the vertex of each.

    A vertex shared by two sticks gives one edge. A vertex shared by k >= 3
    sticks gives k - 1 edges, a spanning tree of its sticks. Every such tree
    describes the same model (the sticks share one point), so the choice only
    says which sticks articulate about that point:

    * The minimum spanning tree of its sticks under the pairwise least-squares
      joint residual (how well the two sticks alone can share a point over all
      frames), so the tree links the sticks that really articulate about that
      point. Two 1-point sticks are linked only where no other spanning tree
      exists: a 1-point stick's rotation is fixed by its joints alone, so any
      two of them share a point closely whatever they are (CMU's two thigh
      markers as 1-point sticks on the pelvis's vertex were linked to each
      other, not both to the pelvis). A 2-point stick's point pair fixes two of
      its three angles, and a chain of two of them at one vertex can be right
      (HDM05's RTHI+RKNE and RSHN+RHEE beside the pelvis stick; CMU 85_02 from
      254/33 degrees: the pelvis, LTHI+LKNE and the 1-point LSHN, where the thigh
      has no other joint).
    * A stick whose only joint is this vertex (a *leaf*: nothing lies beyond
      it) is kept out of that tree where two or more sticks have joints
      elsewhere (*through* sticks: chains pass the vertex), and hangs from one
      of them, so that no chain runs through it: the through stick of least
      residual among those of two or more points, else (all are 1-point sticks,
      whose residuals with anything are small) the one whose side of the vertex
      holds the most points, the side nearer the figure's centre. This holds
      for leaves of three or more points, and for every leaf where the through
      sticks are all 1-point sticks. A 2-point leaf with a through stick of more
      points stays in the tree: it turns freely about the line through its
      points, and a chain link whose two joints met at one vertex is of this
      kind (the thigh above). On CMU 85_02 seen from 283/23 degrees the head,
      RSHO and RUPA (RSHO also joined to the thorax, RUPA to the forearm)
      share the neck's vertex; the spanning tree of all three ran the shoulder
      through the head (RSHO-head-RUPA: the pair is barred, and the head's
      residual with RUPA, 1.6e-6, is below that with RSHO, 3.6e-6). On the
      placed CMU 131_01 walk from 181/15 degrees the head stick, LTHI and the
      pelvis share a vertex, and the tree ran the hip through the head.
    """
    import networkx as nx

    edges: list[tuple[int, int]] = []
    verts: list[int] = []
    E = st.ends_per_stick
    sizes = st.stick_sizes()
    n_joints = st.joints_per_stick()
    for j in range(st.n_vertices):
        own = np.flatnonzero(st.vertex_of == j)
        k_of = {int(i // E): st.ends[i] for i in own}
        sticks = sorted(k_of)
        if len(sticks) < 2:
            continue
        if len(sticks) == 2:
            edges.append((sticks[0], sticks[1]))
            verts.append(j)
            continue
        through = [a for a in sticks if n_joints[a] >= 2]
        hang: list[int] = []
        if len(through) >= 2:
            one_point = bool(np.all(sizes[through] == 1))
            hang = [a for a in sticks if n_joints[a] < 2 and (one_point or sizes[a] >= 3)]
        tree_of = [a for a in sticks if a not in hang]
        g = nx.Graph()
        g.add_nodes_from(tree_of)
        small = {a for a in tree_of if sizes[a] < 2}
        if len(small) == len(tree_of):
            small = set()
        pairs = [(a, b) for ia, a in enumerate(tree_of) for b in tree_of[ia + 1:]]
        res = [joint_least_squares(st, [a, b], [k_of[a], k_of[b]])[1] for a, b in pairs]
        # An edge between two 1-point sticks weighs more than any other spanning tree: it is taken
        # only where no other spanning tree exists.
        extra = 1.0 + float(np.sum(res))
        for (a, b), r in zip(pairs, res):
            g.add_edge(a, b, weight=r + (extra if a in small and b in small else 0.0))
        found = [(min(a, b), max(a, b)) for a, b in nx.minimum_spanning_tree(g).edges()]
        for leaf in hang:
            found.append(tuple(sorted((leaf, _leaf_parent(st, leaf, through, k_of, own, sizes)))))
        for a, b in sorted(found):
            edges.append((a, b))
            verts.append(j)
    return edges, verts


def _leaf_parent(st: StickState, leaf: int, through: list[int], k_of: dict, own: np.ndarray,
                 sizes: np.ndarray) -> int:
    """The through stick a leaf hangs from (:func:`stick_edges`): the one of least residual
    among those of two or more points, else the one whose side of the vertex holds the most
    points (``sizes``: points per stick, as :meth:`StickState.stick_sizes`)."""
    E = st.ends_per_stick
    multi = [a for a in through if sizes[a] >= 2]
    if multi:
        res = [joint_least_squares(st, [leaf, a], [k_of[leaf], k_of[a]])[1] for a in multi]
        return int(multi[int(np.argmin(res))])
    held = []
    for a in through:
        e = int(own[own // E == a][0])
        comp = components(st, e)[0]  # a's side: the part cut off with its endpoint on the vertex
        held.append(int(sizes[comp == comp[a]].sum()))
    return int(through[int(np.argmax(held))])


def joint_support(st: StickState, edges: list[tuple[int, int]], verts: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """How far each joint sits from its sticks' points, and how well the sticks meet there.

    A joint of an articulated body lies at the end of the segments it joins, near
    the points on at least one of them. One far from the points of both sticks is
    a joint in mid-air (docs/em.md section 9): on CMU takes the wrong links between
    the two legs are of this kind. How far is too far depends on the figure
    (section 11), so this measures and does not judge.

    Parameters
    ----------
    st : StickState
    edges : list of (int, int)
        Stick pairs, as :func:`stick_edges` returns them.
    verts : list of int
        The vertex of each edge.

    Returns
    -------
    reach : ndarray, shape (n_edges, 2)
        For each of the edge's two sticks, the distance from its endpoint on the
        joint to the nearest of its points, in the stick's 3D local frame; NaN
        for a stick without points.
    gap : ndarray, shape (n_edges,)
        Root mean square over frames of the distance between the two sticks'
        predicted endpoints on the joint (0: the sticks meet exactly).
    """
    E = st.ends_per_stick
    reach = np.zeros((len(edges), 2))
    gap = np.zeros(len(edges))
    pred = st.end_predictions()  # (ES, F, D)
    for row, ((a, b), j) in enumerate(zip(edges, verts)):
        ends = []
        for col, s in enumerate((a, b)):
            own = s * E + np.arange(E)
            e = int(own[st.vertex_of[own] == j][0])
            ends.append(e)
            own_points = st.local[st.labels == s]
            # A stick can be left without points (its last one resampled away): no reach then.
            reach[row, col] = (float(np.min(np.linalg.norm(own_points - st.ends[e], axis=1))) if len(own_points)
                               else np.nan)
        gap[row] = float(np.sqrt(np.mean(np.sum((pred[ends[0]] - pred[ends[1]]) ** 2, axis=-1))))
    return reach, gap


def pair_stats(st: StickState, sticks: Any = None, weights: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame sums ``sum_f w_f R_a^T R_b`` (n, n, 3, 3), ``sum_f w_f R_a^T t_b`` (n, n, 3), ``sum_f w_f t_a . t_b``."""
    R = st.rot if sticks is None else st.rot[sticks]
    t = st.trans if sticks is None else st.trans[sticks]
    n, F, D, _ = R.shape
    if weights is not None:
        sw = np.sqrt(weights)[None, :, None]
        R = R * sw[..., None]
        t = t * sw
    Rf = R.reshape(n, F * D, 3)
    tf = t.reshape(n, F * D)
    RfT = np.swapaxes(Rf, 1, 2)  # (n, 3, FD)
    RR = RfT[:, None] @ Rf[None]  # (n, n, 3, 3)
    Rt = RfT @ tf.T  # (n, 3, n): [a, :, b] = sum R_a^T t_b
    return RR, np.transpose(Rt, (0, 2, 1)), tf @ tf.T


def joint_least_squares(st: StickState, sticks: list[int], k0: list[np.ndarray], *, ridge: float = 1e-3,
                        stats: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                        seen: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Local points ``k_a`` on each stick that best coincide over all frames.

    Minimises ``sum_f w_f sum_a |R_af k_a + t_af - v_f|^2`` with ``v_f`` the mean of the
    predictions (eliminated), plus ``ridge * sum_f w_f * sum_a |k_a - k0_a|^2`` to fix
    the directions the motion leaves undetermined (a hinge's axis). With ``seen``
    (S, F) visible-point counts, frames where one of the sticks shows fewer than 3
    points (its rotation there is whatever EM left, not what the data say) weigh
    1/100; otherwise all weigh 1.

    Returns
    -------
    k : ndarray, shape (n, 3)
    residual : float
        Mean squared distance of the predictions from their mean, per stick and frame.

    ``stats``: :func:`pair_stats` of all sticks (reused across candidates).
    """
    n = len(sticks)
    F = st.n_frames
    w = None
    if seen is not None:
        ok = np.all(seen[np.asarray(sticks)] >= 3, axis=0)
        if not ok.all() and ok.sum() >= min(10, F):
            w = np.where(ok, 1.0, 0.01)
    if w is not None:
        RR, Rt, tt = pair_stats(st, sticks, w)
        F = float(w.sum())
    elif stats is None:
        RR, Rt, tt = pair_stats(st, sticks)
    else:
        ix = np.asarray(sticks)
        RR, Rt, tt = (a[np.ix_(ix, ix)] for a in stats)
    M = np.eye(n) - 1.0 / n
    H = (M[:, :, None, None] * RR).transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    g = np.sum(M[:, :, None] * Rt, axis=1).reshape(3 * n)
    lam = ridge * F
    k0v = np.asarray(k0, dtype=float).reshape(3 * n)
    k = np.linalg.solve(H + lam * np.eye(3 * n), -g + lam * k0v)
    res = float(k @ H @ k + 2.0 * g @ k + np.sum(M * tt))
    return k.reshape(n, 3), max(res, 0.0) / (n * F)


# ----------------------------------------------------------------------- candidates
@dataclass
class Candidate:
    """A putative merge of vertices ``j1 < j2``."""

    j1: int
    j2: int
    residual: float
    ends: np.ndarray = field(repr=False)  # endpoints of the merged vertex
    k: np.ndarray | None = field(default=None, repr=False)  # their least-squares joint (merge_init="joint")
    score: float = np.nan
    key: tuple = ()  # identifies the merge across stages (endpoint ids are stable)
    fresh: bool = True  # scored at this stage (False: score reused from an earlier stage)


def merge_candidates(st: StickState, settings: EMSettings, seen: np.ndarray | None = None) -> list[Candidate]:
    """Every valid merge (deduplicated for ``merge_init="joint"``), with its joint residual."""
    comp_s, comp_v = components(st)
    J = st.n_vertices
    E = st.ends_per_stick
    cnt = st.vertex_counts()
    # A side is a joint (a vertex with >= 2 endpoints) or, for "joint" merges, a stick standing
    # for all its endpoints that are still alone: those are interchangeable, the one nearest the
    # least-squares joint is used. For "mean" merges every vertex is a side.
    alone = cnt == 1
    free = alone[st.vertex_of].reshape(st.n_sticks, E)  # (S, E)
    sides: list[tuple[str, int]] = []
    if settings.merge_init == "joint":
        sides += [("vertex", int(j)) for j in np.flatnonzero(~alone)]
        sides += [("stick", int(x)) for x in np.flatnonzero(st.open_sticks())]  # each has a free endpoint
    else:
        sides += [("vertex", j) for j in range(J)]

    def side_comp(side: tuple[str, int]) -> int:
        return int(comp_s[side[1]]) if side[0] == "stick" else int(comp_v[side[1]])

    def side_key(side: tuple[str, int]) -> tuple:
        if side[0] == "stick":
            return ("stick", side[1])
        return ("vertex",) + tuple(np.flatnonzero(st.vertex_of == side[1]).tolist())

    stats = pair_stats(st)
    size = st.stick_sizes()
    joints = st.joints_per_stick()
    out: list[Candidate] = []
    for ia, a in enumerate(sides):
        for b in sides[ia + 1:]:
            if side_comp(a) == side_comp(b):
                continue
            ends, k0 = [], []
            for kind, x in (a, b):
                if kind == "stick":
                    ends.append(-1 - x)  # resolved after the fit
                    k0.append(st.ends[E * x + np.flatnonzero(free[x])].mean(axis=0))
                else:
                    for i in np.flatnonzero(st.vertex_of == x):
                        ends.append(int(i))
                        k0.append(st.ends[i])
            sticks = [(-1 - e) if e < 0 else e // E for e in ends]
            k, res = joint_least_squares(st, sticks, k0, stats=stats, seen=seen)
            resolved = []
            for e, kk in zip(ends, k):
                if e < 0:  # the stick's free endpoint nearest the joint
                    x = -1 - e
                    cand_e = E * x + np.flatnonzero(free[x])
                    e = int(cand_e[np.argmin(np.linalg.norm(st.ends[cand_e] - kk, axis=1))])
                resolved.append(e)
            resolved = np.asarray(resolved)
            vs = sorted({int(st.vertex_of[e]) for e in resolved})
            if len(vs) != 2:
                continue
            # A stick of one point turns freely about it in every frame, so its endpoints constrain
            # each other by their distance alone: a third joint on it would be a free hub (tying
            # parts by nothing), which the criterion likes wherever a rigid joint fits badly.
            gains = resolved[alone[st.vertex_of[resolved]]] // E
            if np.any((size[gains] == 1) & (joints[gains] >= 2)):
                continue
            if st.only_one_point_sticks(vs):  # a joint that ties nothing (StickState.only_one_point_sticks)
                continue
            out.append(Candidate(j1=vs[0], j2=vs[1], residual=res, ends=resolved,
                                 k=k if settings.merge_init == "joint" else None,
                                 key=tuple(sorted([side_key(a), side_key(b)]))))
    if settings.max_candidates is not None and len(out) > settings.max_candidates:
        order = np.argsort([c.residual for c in out], kind="stable")[: settings.max_candidates]
        out = [out[i] for i in sorted(order)]
    return out


# ------------------------------------------------------------------------- merging
def merge_vertices(st: StickState, cand: Candidate, priors: Priors, init: str) -> StickState:
    """A copy of ``st`` with vertices ``cand.j1`` and ``cand.j2`` merged and warm-started."""
    j1, j2 = cand.j1, cand.j2
    D, F = st.n_dims, st.n_frames
    out = st.copy()
    ends = np.flatnonzero((st.vertex_of == j1) | (st.vertex_of == j2))
    n = float(ends.size)
    keep = np.ones(st.n_vertices, bool)
    keep[j2] = False
    vnew = np.cumsum(keep) - 1
    vnew[j2] = vnew[j1]
    out.vertex_of = vnew[st.vertex_of]
    jn = int(vnew[j1])
    out.mu_v, out.tau_v = st.mu_v[keep].copy(), st.tau_v[keep].copy()
    out.alpha, out.beta = st.alpha[keep].copy(), st.beta[keep].copy()
    if st.ghosts is not None:
        out.ghosts = st.ghosts.take(keep)
    a1, a2 = st.alpha[j1] / st.beta[j1], st.alpha[j2] / st.beta[j2]
    if init == "joint" and cand.k is not None:
        order = {int(e): r for r, e in enumerate(cand.ends)}
        for e in ends:
            out.ends[e] = cand.k[order[int(e)]]
        s = ends // st.ends_per_stick
        pred = (st.rot[s] @ out.ends[ends][:, None, :, None])[..., 0] + st.trans[s]
        mu = pred.mean(axis=0)
        ss = float(np.sum((pred - mu) ** 2))
        a = min(D * F * n / max(ss, 1e-300), max(a1, a2))
        out.mu_e[ends] = pred
    elif init == "mean":
        n1 = float(np.sum(st.vertex_of == j1))
        n2 = n - n1
        mu = (n1 * st.mu_v[j1] + n2 * st.mu_v[j2]) / n
        a = 1.0 / (n1 / (n * a1) + n2 / (n * a2))
    else:
        raise ValueError(f"merge_init must be 'joint' or 'mean', got {init!r}")
    out.mu_v[jn] = mu
    out.alpha[jn] = priors.alpha0 + 0.5 * D * F * n
    out.beta[jn] = out.alpha[jn] / a
    out.tau_v[jn] = a * n + st.tau_t * chain_degree(F)
    update_endpoints(out, ends)
    return out


def polish_joints(st: StickState, obs: Observations, priors: Priors, vertices: list[int], caps: list[float],
                  n_polish: int) -> None:
    """Re-fit the joints just created and the motions of their sticks together (in place).

    The least-squares joint uses the sticks' current rotations, which can be
    wrong where the data alone leave them ambiguous (a nearly planar stick can be
    mirrored frame by frame without changing its projection; only a joint off its
    plane tells the two apart). ``n_polish`` rounds of: least-squares joint for
    every vertex in ``vertices``; its endpoints and the vertex set to the joint;
    motions re-solved with the multi-start rotation search
    (:func:`~stickfigure.models.em.updates.best_rotations`) and local
    coordinates updated. Then each joint's precision starts at
    ``min(D F n / residual, cap)``. Every step is an EM coordinate update of the
    model with these vertices held hard, so the polish only moves the merge to a
    better starting point; the scoring EM iterations that follow are the judge.
    """
    from .updates import update_local, update_motions

    E = st.ends_per_stick
    D, F = st.n_dims, st.n_frames
    seen = st.design(obs).n
    involved = np.unique(np.concatenate([np.flatnonzero(st.vertex_of == j) // E for j in vertices]))
    for it in range(n_polish + 1):
        for j in vertices:
            ends = np.flatnonzero(st.vertex_of == j)
            k, _ = joint_least_squares(st, list(ends // E), list(st.ends[ends]), seen=seen)
            st.ends[ends] = k
            pred = (st.rot[ends // E] @ k[:, None, :, None])[..., 0] + st.trans[ends // E]
            mu = pred.mean(axis=0)
            if it < n_polish:
                st.mu_e[ends] = mu
            else:
                st.mu_e[ends] = pred
            st.mu_v[j] = mu
        if it < n_polish:
            update_motions(st, obs, global_search=True, sticks=involved, use_polar=False, n_newton=1,
                           only_mirrors=True)
            update_local(st, obs, priors)
    for j, cap in zip(vertices, caps):
        ends = np.flatnonzero(st.vertex_of == j)
        n = float(ends.size)
        ss = float(np.sum((st.mu_e[ends] - st.mu_v[j]) ** 2))
        a = min(D * F * n / max(ss, 1e-300), cap)
        st.alpha[j] = priors.alpha0 + 0.5 * D * F * n
        st.beta[j] = st.alpha[j] / a
        st.tau_v[j] = a * n + st.tau_t * chain_degree(F)
    update_endpoints(st)


def _block(st: StickState, obs: Observations, sticks: np.ndarray) -> tuple[StickState, Observations, dict]:
    """The sub-model of ``sticks``: their points, endpoints and vertices; other endpoints become ghosts."""
    S = st.n_sticks
    in_b = np.zeros(S, bool)
    in_b[sticks] = True
    pts = np.flatnonzero(in_b[st.labels])
    E = st.ends_per_stick
    ends = np.flatnonzero(np.repeat(in_b, E))
    verts = np.unique(st.vertex_of[ends])
    smap = -np.ones(S, np.int64)
    smap[sticks] = np.arange(sticks.size)
    vmap = -np.ones(st.n_vertices, np.int64)
    vmap[verts] = np.arange(verts.size)
    F, D = st.n_frames, st.n_dims
    # Ghosts: endpoints of other sticks on the block's vertices.
    other = np.flatnonzero(~np.repeat(in_b, E) & np.isin(st.vertex_of, verts))
    Jb = verts.size
    gn = np.zeros(Jb)
    gsum = np.zeros((Jb, F, D))
    gsq = np.zeros((Jb, F))
    gvar = np.zeros((Jb, F))
    if other.size:
        gv = vmap[st.vertex_of[other]]
        np.add.at(gn, gv, 1.0)
        np.add.at(gsum, gv, st.mu_e[other])
        np.add.at(gsq, gv, np.sum(st.mu_e[other] ** 2, axis=2))
        np.add.at(gvar, gv, np.broadcast_to((D / st.tau_e[other])[:, None], (other.size, F)))
    if st.ghosts is not None:
        g = st.ghosts
        gn += g.n[verts]
        gsum += g.sum[verts]
        gsq += g.sq[verts]
        gvar += g.var[verts]
    sub = StickState(labels=smap[st.labels[pts]], vertex_of=vmap[st.vertex_of[ends]], rot=st.rot[sticks],
                     trans=st.trans[sticks], local=st.local[pts], ends=st.ends[ends], mu_e=st.mu_e[ends],
                     tau_e=st.tau_e[ends], mu_v=st.mu_v[verts], tau_v=st.tau_v[verts], alpha=st.alpha[verts],
                     beta=st.beta[verts], tau_w=st.tau_w, tau_m=st.tau_m, tau_t=st.tau_t,
                     ghosts=Ghosts(gn, gsum, gsq, gvar))
    maps = {"sticks": sticks, "points": pts, "ends": ends, "verts": verts}
    return sub, obs.take(pts), maps


def _union(parts: list[tuple[StickState, Observations]]) -> tuple[StickState, Observations, np.ndarray, np.ndarray]:
    """Disjoint union of block models (one EM run optimises all of them independently).

    Returns the union, its observations, and the block id of every stick and vertex.
    """
    st0 = parts[0][0]
    so = vo = 0
    labels, vertex_of, sblock, vblock = [], [], [], []
    for b, (s, _) in enumerate(parts):
        labels.append(s.labels + so)
        vertex_of.append(s.vertex_of + vo)
        sblock.append(np.full(s.n_sticks, b))
        vblock.append(np.full(s.n_vertices, b))
        so += s.n_sticks
        vo += s.n_vertices

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(s, name) for s, _ in parts])

    gh = [s.ghosts for s, _ in parts]
    u = StickState(labels=np.concatenate(labels), vertex_of=np.concatenate(vertex_of), rot=cat("rot"),
                   trans=cat("trans"), local=cat("local"), ends=cat("ends"), mu_e=cat("mu_e"), tau_e=cat("tau_e"),
                   mu_v=cat("mu_v"), tau_v=cat("tau_v"), alpha=cat("alpha"), beta=cat("beta"), tau_w=st0.tau_w,
                   tau_m=st0.tau_m, tau_t=st0.tau_t,
                   ghosts=Ghosts(np.concatenate([g.n for g in gh]), np.concatenate([g.sum for g in gh]),
                                 np.concatenate([g.sq for g in gh]), np.concatenate([g.var for g in gh])))
    obs = Observations(np.concatenate([o.w for _, o in parts]), np.concatenate([o.mask for _, o in parts]))
    return u, obs, np.concatenate(sblock), np.concatenate(vblock)


def _cap(st: StickState, cand: Candidate) -> float:
    """Largest starting precision of a merged vertex: the larger of the two merged ones."""
    return float(max(st.alpha[cand.j1] / st.beta[cand.j1], st.alpha[cand.j2] / st.beta[cand.j2]))


def _g_prior_change(st: StickState, cand: Candidate) -> float:
    """Change of log P(G) (ML multinomial) when the two vertices merge."""
    n1 = float(np.sum(st.vertex_of == cand.j1))
    n2 = float(np.sum(st.vertex_of == cand.j2))
    tot = float(st.vertex_of.size)

    def f(n: float) -> float:
        return n * np.log(n / tot)

    return f(n1 + n2) - f(n1) - f(n2)


def baseline_state(st: StickState, obs: Observations, priors: Priors, settings: EMSettings) -> StickState:
    """The model without a merge, run for ``n_iter_merge`` iterations (once per stage).

    Global precisions stay fixed for ``merge_scope="local"``, as in the blocks.
    Scores measured against it credit a merge, not the convergence still going
    on in slowly converging sticks.
    """
    if not settings.merge_baseline:
        return st
    base_st = st.copy()
    for _ in range(settings.n_iter_merge):
        em_sweep(base_st, obs, priors, precisions=settings.merge_scope == "full", local=True,
                 n_procrustes=settings.n_procrustes)
    return base_st


def score_candidates(st: StickState, obs: Observations, priors: Priors, settings: EMSettings,
                     cands: list[Candidate], rng: np.random.Generator, base_st: StickState | None = None
                     ) -> list[StickState | None]:
    """Set ``cand.score`` for every candidate: the change of the objective, or with
    ``merge_rank="residual"`` minus the least-squares joint residual (:func:`_rank_by_residual`).
    Callers only rank by it (argmax).

    ``base_st``: :func:`baseline_state` of ``st`` (computed when omitted; not
    needed with ``merge_rank="residual"``).
    Returns the optimised states: for ``merge_scope="full"`` whole-model copies,
    for ``"local"`` the blocks (re-inserted by :func:`apply_merge`). With
    ``merge_rank="residual"`` only the best candidate (the first argmax) is
    optimised and the other entries are None: the residual ranks without the
    ``n_iter_merge`` sweeps, which only warm-start the merge taken. Its block is
    the same, bit for bit, as when every candidate is optimised (a block's fit
    does not depend on the blocks beside it: :mod:`.forked`).
    """
    if settings.merge_scope not in ("local", "full"):
        raise ValueError(f"merge_scope must be 'local' or 'full', got {settings.merge_scope!r}")
    if settings.merge_rank not in ("objective", "residual"):
        raise ValueError(f"merge_rank must be 'objective' or 'residual', got {settings.merge_rank!r}")
    by_residual = settings.merge_rank == "residual"
    if by_residual:
        _rank_by_residual(cands)
        todo = [int(np.argmax([c.score for c in cands]))] if cands else []
    else:
        todo = list(range(len(cands)))
        if base_st is None:
            base_st = baseline_state(st, obs, priors, settings)
    if settings.merge_scope == "full":
        base = None if by_residual else objective(base_st, obs, priors)
        outs: list[StickState | None] = [None] * len(cands)
        for idx in todo:
            c = cands[idx]
            m = merge_vertices(st, c, priors, settings.merge_init)
            if settings.merge_init == "joint" and settings.n_polish:
                polish_joints(m, obs, priors, [c.j1], [_cap(st, c)], settings.n_polish)
            m, val, _ = run_em(m, obs, priors, replace_tol(settings), settings.n_iter_merge, rng, resample=False)
            if not by_residual:
                c.score = val - base
            outs[idx] = m
        return outs
    if not by_residual:
        ps, pv = objective_terms(base_st, obs, priors)
    results: list[StickState | None] = [None] * len(cands)
    prepared = []
    for idx in todo:
        c = cands[idx]
        sticks = np.unique(c.ends // st.ends_per_stick)
        sub, sobs, maps = _block(st, obs, sticks)
        vm = {int(v): r for r, v in enumerate(maps["verts"])}
        em = {int(e): r for r, e in enumerate(maps["ends"])}
        local_c = Candidate(j1=vm[c.j1], j2=vm[c.j2], residual=c.residual,
                            ends=np.array([em[int(e)] for e in c.ends]), k=c.k)
        sub = merge_vertices(sub, local_c, priors, settings.merge_init)
        before = 0.0 if by_residual else float(ps[sticks].sum() + pv[maps["verts"]].sum())
        # After merge_vertices the merged vertex keeps index j1 (j1 < j2).
        prepared.append((idx, sub, sobs, maps, before, local_c.j1))

    def fit(items: list) -> list[tuple[float, StickState]]:
        """The blocks' EM runs, batched into disjoint unions of about ``batch_size`` entries
        (a block's fit does not depend on the blocks beside it); (objective after, block state)."""
        out: list[tuple[float, StickState]] = []
        for lo, hi in _chunks([it[2].w.size for it in items], settings.batch_size):
            batch = items[lo:hi]
            u, uobs, sb, vb = _union([(it[1], it[2]) for it in batch])
            if settings.merge_init == "joint" and settings.n_polish:
                offs = np.concatenate([[0], np.cumsum([it[1].n_vertices for it in batch])])
                polish_joints(u, uobs, priors, [int(offs[r] + it[5]) for r, it in enumerate(batch)],
                              [_cap(st, cands[it[0]]) for it in batch], settings.n_polish)
            for _ in range(settings.n_iter_merge):
                em_sweep(u, uobs, priors, precisions=False, local=True, n_procrustes=settings.n_procrustes)
            ups, upv = objective_terms(u, uobs, priors)
            after = np.bincount(sb, weights=ups, minlength=len(batch)) + np.bincount(vb, weights=upv,
                                                                                      minlength=len(batch))
            so = vo = po = 0
            for r, (idx, sub, sobs, maps, before, _) in enumerate(batch):
                ns, nv, npnt = sub.n_sticks, sub.n_vertices, sobs.n_points
                E = sub.ends_per_stick
                done = StickState(labels=sub.labels, vertex_of=sub.vertex_of, rot=u.rot[so:so + ns],
                                  trans=u.trans[so:so + ns], local=u.local[po:po + npnt],
                                  ends=u.ends[E * so:E * (so + ns)], mu_e=u.mu_e[E * so:E * (so + ns)],
                                  tau_e=u.tau_e[E * so:E * (so + ns)], mu_v=u.mu_v[vo:vo + nv],
                                  tau_v=u.tau_v[vo:vo + nv], alpha=u.alpha[vo:vo + nv], beta=u.beta[vo:vo + nv],
                                  tau_w=u.tau_w, tau_m=u.tau_m, tau_t=u.tau_t, ghosts=sub.ghosts)
                done._maps = maps  # type: ignore[attr-defined]
                out.append((float(after[r]), done))
                so, vo, po = so + ns, vo + nv, po + npnt
        return out

    # Half of the blocks in a forked child (n_jobs > 1): the same numbers, bit for bit.
    fitted = in_halves(fit, prepared, parallel=settings.n_jobs > 1, weights=[it[2].w.size for it in prepared])
    for (idx, _, _, _, before, _), (after, done) in zip(prepared, fitted):
        if not by_residual:
            cands[idx].score = after - before + _g_prior_change(st, cands[idx])
        results[idx] = done
    return results


def _rank_by_residual(cands: list[Candidate]) -> None:
    """A candidate's score under ``merge_rank="residual"``: minus its least-squares joint residual.

    The objective's change after 20 sweeps ranks a joint by how tight the EM can make
    it, which a stick whose motion its points barely fix (two markers, a flat band
    of four seen edge-on) can always do; the residual
    (:func:`joint_least_squares`, per stick and frame, from the current motions)
    asks whether one point fixed in both sticks' frames exists at all. Measured on
    the body's own segments given as the sticks (docs/em.md section 11): with
    mirror alignment the body's tree on 5 of 6 cameras of the placed CMU 41-marker
    set (1 of 6 by the objective) and 3 of 6 of the recorded CMU take (0 of 6).
    """
    for c in cands:
        c.score = -float(c.residual)


def _chunks(sizes: list[int], limit: int) -> list[tuple[int, int]]:
    """Consecutive (start, stop) ranges of ``sizes``, each closed once its total reaches ``limit``."""
    out, lo, tot = [], 0, 0
    for i, n in enumerate(sizes):
        tot += n
        if tot >= limit:
            out.append((lo, i + 1))
            lo, tot = i + 1, 0
    if lo < len(sizes):
        out.append((lo, len(sizes)))
    return out


def _score_into(st: StickState, obs: Observations, priors: Priors, settings: EMSettings,
                cands: list[Candidate], rng: np.random.Generator, blocks: dict[int, StickState | None],
                base: dict) -> None:
    """Score ``cands`` (fresh) and remember their optimised states by candidate id."""
    if not cands:
        return
    if "state" not in base and settings.merge_rank != "residual":
        base["state"] = baseline_state(st, obs, priors, settings)
    for c, b in zip(cands, score_candidates(st, obs, priors, settings, cands, rng, base.get("state"))):
        c.fresh = True
        blocks[id(c)] = b


def replace_tol(settings: EMSettings) -> EMSettings:
    from dataclasses import replace

    return replace(settings, tol=0.0)


def apply_merge(st: StickState, cand: Candidate, priors: Priors, settings: EMSettings,
                block: StickState | None) -> StickState:
    """The full model with ``cand`` merged, warm-started from its scored block (or copy)."""
    merged = merge_vertices(st, cand, priors, settings.merge_init)
    if block is None:
        return merged
    if settings.merge_scope == "full":
        return block
    maps = block._maps  # type: ignore[attr-defined]
    keep = np.ones(st.n_vertices, bool)
    keep[cand.j2] = False
    vnew = np.cumsum(keep) - 1
    vnew[cand.j2] = vnew[cand.j1]
    sticks, pts, ends = maps["sticks"], maps["points"], maps["ends"]
    bverts = np.unique(vnew[maps["verts"]])  # block vertices in the merged numbering, sorted as in the block
    merged.rot[sticks], merged.trans[sticks] = block.rot, block.trans
    merged.local[pts] = block.local
    merged.ends[ends], merged.mu_e[ends], merged.tau_e[ends] = block.ends, block.mu_e, block.tau_e
    merged.mu_v[bverts], merged.tau_v[bverts] = block.mu_v, block.tau_v
    merged.alpha[bverts], merged.beta[bverts] = block.alpha, block.beta
    merged._quat = None
    return merged


# ----------------------------------------------------------------------- the search
def n_parameters(st: StickState, obs: Observations, rotations: str = "all") -> int:
    """Free parameters of the articulated model with rigid joints (for BIC).

    Per stick and frame 3 rotation angles; per connected tree and frame D
    translation components (a joint fixes the child's translation); 3 local
    coordinates per point and per endpoint in a joint; the three precisions.

    With ``rotations="identified"`` a stick's rotation angles are those its
    *anchors* fix: its points and its endpoints in (rigid) joints, the places
    where the stick meets an observation or another stick. Turning a stick
    about the line through its only two anchors moves none of them: no
    observation and no joint changes, only endpoints on no joint, which explain
    nothing. So a stick with two anchors (a 1-point stick on one joint, a
    2-point stick on none) has 2 identified angles a frame, one with a single
    anchor (a 1-point stick on no joint) none, and one with three or more anchors
    (in general not on one line) all 3. ``"all"`` counts 3 for every stick.
    """
    F, D = st.n_frames, st.n_dims
    # A loose joint (rigid_joints) does not tie its sticks' translations: it counts as none.
    rigid = rigid_joints(st, obs)
    E = st.ends_per_stick
    trees = st.n_sticks
    parent = np.arange(st.n_sticks)

    def find(a: int) -> int:
        while parent[a] != a:
            a = parent[a]
        return a

    for j in np.flatnonzero(rigid & (st.vertex_counts() >= 2)):
        sticks = np.flatnonzero(st.vertex_of == j) // E
        for b in sticks[1:]:
            ra, rb = find(int(sticks[0])), find(int(b))
            if ra != rb:
                parent[rb] = ra
                trees -= 1
    in_joint = (st.vertex_counts() >= 2)[st.vertex_of] & rigid[st.vertex_of]
    if rotations == "all":
        angles = 3 * st.n_sticks
    elif rotations == "identified":
        anchors = st.stick_sizes() + in_joint.reshape(st.n_sticks, E).sum(axis=1)
        angles = int(np.sum(np.where(anchors >= 3, 3, np.where(anchors == 2, 2, 0))))
    else:
        raise ValueError(f"rotations must be 'all' or 'identified', got {rotations!r}")
    return int(angles * F + D * F * trees + 3 * obs.n_points + 3 * in_joint.sum() + 3)


def bic(st: StickState, obs: Observations, value: float, priors: Priors, free_ends: bool = True,
        rotations: str = "all") -> float:
    """The selection criterion ``value - n_parameters / 2 log N`` (N observed coordinates).

    With ``free_ends=False`` the terms of the endpoints on no joint
    (:func:`model.free_endpoint_terms`) are taken out of ``value`` first: they explain
    no observation but add about ``D/2 log(tau_t / 2pi)`` a frame each, so a model
    with more sticks or more endpoints gains by them alone (docs/em.md section 7).
    ``rotations``: which rotation angles count as parameters (:func:`n_parameters`).
    """
    if not free_ends:
        value = value - free_endpoint_terms(st, obs, priors)
    k = n_parameters(st, obs, rotations)
    return float(value - 0.5 * k * np.log(obs.mask.sum() * obs.n_dims))


def settings_bic(st: StickState, obs: Observations, value: float, priors: Priors, settings: EMSettings) -> float:
    """:func:`bic` as the fit counts it (``settings.bic_free_ends``, ``settings.bic_rotations``)."""
    return bic(st, obs, value, priors, settings.bic_free_ends, settings.bic_rotations)


LOOSE_FACTOR = 10.0


def rigid_joints(st: StickState, obs: Observations) -> np.ndarray:
    """Which vertices are joints the data support as rigid (J,) bool; True for unshared vertices too.

    A vertex shared by m sticks saves ``(m - 1) D F - 3 m`` parameters under the
    rigid-joint reading (the sticks' translations, less their endpoints), worth
    ``1/2 log N`` each in BIC. Making the sticks meet exactly costs about
    ``tau_w / 2 * m * res * sum_f H_f`` of the points' fit: ``res`` the mean squared
    distance of the sticks' least-squares joint predictions from their mean
    (:func:`joint_least_squares`), ``H_f`` the harmonic mean of the point counts the
    sticks show in frame f (closing a gap ``g`` between two sticks showing ``n_a`` and
    ``n_b`` points by moving both costs ``g^2 n_a n_b / (n_a + n_b)``; 0 where one shows
    none, since it then moves for free). On complete data ``sum_f H_f = F H`` with ``H``
    that of the sticks' sizes, as before session 34; with 75 % of the entries withheld the
    sizes overstated the cost about fourfold, and true joints of random figures measured
    up to 14 times their saving (now at most 3.5) and were read as loose, so the merge
    that completed the true tree lowered BIC and was not selected (docs/em.md section 11).
    A vertex whose cost exceeds its saving is a loose link (two independently moving
    bodies joined by a vertex of low precision): it is not counted as a joint in
    :func:`n_parameters`, so BIC prefers leaving the trees apart whenever the objective does. The cost closes
    the gap by translations alone, an upper bound (the rotations can absorb part
    of it), so a vertex is loose only when the cost exceeds ``LOOSE_FACTOR`` (10)
    times the saving. Measured cost/saving: true joints of random figures at
    most 0.35, a true joint between two sticks that each hold a point of the
    other (a clustering error) 2.5, two or three independent rigid bodies at
    least 320.
    """
    J = st.n_vertices
    out = np.ones(J, bool)
    cnt = st.vertex_counts()
    shared = np.flatnonzero(cnt >= 2)
    if shared.size == 0:
        return out
    E = st.ends_per_stick
    F, D = st.n_frames, st.n_dims
    logN = float(np.log(obs.mask.sum() * obs.n_dims))
    seen = st.design(obs).n
    for j in shared:
        ends = np.flatnonzero(st.vertex_of == j)
        sticks = ends // E
        m = ends.size
        _, res = joint_least_squares(st, list(sticks), list(st.ends[ends]), seen=seen)
        # Closing the gap in a frame costs the harmonic mean of the points each stick shows
        # *there*; a stick that shows none moves for free. Complete data: F times the sizes'.
        n_f = seen[sticks]  # (m, F)
        h_f = np.where(np.all(n_f > 0, axis=0), m / np.sum(1.0 / np.maximum(n_f, 1.0), axis=0), 0.0)
        cost = 0.5 * st.tau_w * m * res * float(h_f.sum())
        saving = 0.5 * logN * ((m - 1) * D * F - 3 * m)
        out[j] = cost < LOOSE_FACTOR * saving
    return out


@dataclass
class Stage:
    """What is kept of every merge stage (the selected stages keep their full state)."""

    objective: float
    bic: float
    labels: np.ndarray
    vertex_of: np.ndarray
    edges: list[tuple[int, int]]
    merged: tuple[int, int] | None
    n_sweeps: int
    ends_xy: np.ndarray  # (ES, D) endpoint means at the reference frame
    joints_xy: np.ndarray  # (J, D) vertex means at the reference frame
    state: StickState | None = None
    refinements: list = field(default_factory=list)
    dissolved: list = field(default_factory=list)  # point sets of sticks dissolved (refine.dissolve_small_sticks)
    moved: int = 0  # points moved by refine.resplit_pairs
    heldout: dict | None = None  # the held-out check's errors (refine.heldout_dissolve)
    split: list = field(default_factory=list)  # sticks split after it (refine.articulated_split_round)
    search_bic: float | None = None  # the search's best BIC, before the held-out check (compares starts)
    reattached: list = field(default_factory=list)  # sub-tree moves kept (tree.reattach_subtrees)
    joined: list = field(default_factory=list)  # stick pairs joined to reach max_trees (tree.join_trees)
    bridged: list = field(default_factory=list)  # points made sticks between two sticks (bridge.bridge_points)
    unpaired: list = field(default_factory=list)  # point pairs made two sticks (bridge.unpair_hubs)
    hubs: list = field(default_factory=list)  # sticks on joints only split in two (refine.split_hubs)


def _stage(st: StickState, obs: Observations, value: float, merged: tuple[int, int] | None, sweeps: int,
           ref: int, priors: Priors, settings: EMSettings) -> Stage:
    edges, _ = stick_edges(st)
    return Stage(objective=value, bic=settings_bic(st, obs, value, priors, settings), labels=st.labels.copy(),
                 vertex_of=st.vertex_of.copy(), edges=edges, merged=merged, n_sweeps=sweeps,
                 ends_xy=st.mu_e[:, ref].copy(), joints_xy=st.mu_v[:, ref].copy())


def greedy_merges(st: StickState, obs: Observations, priors: Priors, settings: EMSettings,
                  rng: np.random.Generator, ref: int, max_merges: int | None
                  ) -> Iterator[tuple[Stage, StickState]]:
    """The merge loop of Fig. 3: score every valid vertex-pair merge, take the best, re-optimise.

    Yields each stage and its state (the generator's own; copy it to keep it) after
    every merge, until one tree is left or ``max_merges`` merges are done.
    """
    k = 0
    cache: dict[tuple, tuple[float, frozenset]] = {}
    while max_merges is None or k < max_merges:
        cands = merge_candidates(st, settings, st.design(obs).n)
        if not cands:
            break
        todo = []
        for c in cands:
            hit = cache.get(c.key) if settings.reuse_scores else None
            if hit is None:
                todo.append(c)
            else:
                c.score, c.fresh = hit[0], False
        blocks: dict[int, StickState | None] = {}
        base: dict = {}
        _score_into(st, obs, priors, settings, todo, rng, blocks, base)
        while True:  # lazy greedy: a reused score must be confirmed before its merge is taken
            b = int(np.argmax([c.score for c in cands]))
            c = cands[b]
            if c.fresh:
                break
            c.fresh = True
            _score_into(st, obs, priors, settings, [c], rng, blocks, base)
        for x in cands:
            cache[x.key] = (x.score, frozenset((x.ends // st.ends_per_stick).tolist()))
        j1, j2 = c.j1, c.j2
        merged_sticks = set((np.flatnonzero((st.vertex_of == j1) | (st.vertex_of == j2))
                             // st.ends_per_stick).tolist())
        old_labels, old_S = st.labels, st.n_sticks
        st = apply_merge(st, c, priors, settings, blocks.get(id(c)))
        st, val, sweeps = run_em(st, obs, priors, settings, settings.n_iter, rng)
        # Scores of merges whose sticks the merge touched, or whose membership changed by more than
        # a quarter (a point or two flipping at a joint does not count), are stale.
        if st.n_sticks != old_S:
            cache.clear()
        else:
            size = np.bincount(old_labels, minlength=old_S)
            flux = np.bincount(old_labels[st.labels != old_labels], minlength=old_S) + np.bincount(
                st.labels[st.labels != old_labels], minlength=old_S)
            moved = set(np.flatnonzero(flux > np.maximum(1, 0.25 * size)).tolist())
            dirty = merged_sticks | moved
            cache = {key: v for key, v in cache.items() if not (v[1] & dirty)}
        k += 1
        yield _stage(st, obs, val, (j1, j2), sweeps, ref, priors, settings), st


def learn_structure(st: StickState, obs: Observations, priors: Priors, settings: EMSettings,
                    rng: np.random.Generator, *, selection: str = "bic",
                    progress: Callable[[int, int, float], None] | None = None) -> tuple[list[Stage], int]:
    """Fig. 3 of the paper from an initial state; returns every stage and the selected one.

    The states of the best stage under each criterion are kept in ``Stage.state``.
    With ``settings.n_jobs`` > 1 some of the work runs in forked children
    (:mod:`.forked`; the same result either way).
    """
    ref = int(np.argmax(obs.mask.sum(axis=0)))
    st, val, sweeps = run_em(st, obs, priors, settings, settings.n_iter, rng)
    refinements = []
    for _ in range(3 if settings.refine_sticks else 0):
        from .initialise import initial_state
        from .refine import refine_labels

        labels, what = refine_labels(st, obs, rng, min_points=settings.min_stick_points, priors=priors)
        if not what["splits"] and not what["joins"]:
            break
        refinements.append(what)
        st = initial_state(obs, labels, int(labels.max()) + 1, priors, rng, endpoint_init=settings.endpoint_init,
                           n_ends=settings.state_ends)
        st, val, more = run_em(st, obs, priors, settings, settings.n_iter, rng)
        sweeps += more
    for _ in range(settings.articulated_rounds if settings.refine_sticks else 0):
        from .refine import articulated_split_round

        new, v, more, split = articulated_split_round(st, obs, priors, settings, rng)
        if not split:
            break
        refinements.append({"articulated_splits": split})
        st, val = new, v
        sweeps += more
    stages = [_stage(st, obs, val, None, sweeps, ref, priors, settings)]
    stages[0].refinements = refinements
    best = {"objective": (stages[0].objective, 0, st.copy()), "bic": (stages[0].bic, 0, st.copy())}
    total = st.n_sticks - 1 if settings.max_merges is None else min(settings.max_merges, st.n_sticks - 1)
    if progress:
        progress(0, total, val)
    done = 0  # merges so far, the resumed search's included (progress: stage k of n)

    def report(k: int, state: StickState, value: float) -> None:
        # Stage k of (k + the merges still possible: trees left - 1).
        if progress:
            comp_s, _ = components(state)
            progress(k, k + int(comp_s.max()), value)

    for done, (stage, cur) in enumerate(greedy_merges(st, obs, priors, settings, rng, ref, settings.max_merges), 1):
        st = cur
        stages.append(stage)
        for crit in ("objective", "bic"):
            v = getattr(stage, crit)
            if v > best[crit][0]:
                best[crit] = (v, len(stages) - 1, st.copy())
        report(done, st, stage.objective)
    if selection not in ("objective", "bic"):
        raise ValueError(f"selection must be 'objective' or 'bic', got {selection!r}")

    def criterion(s: StickState, v: float) -> float:
        return settings_bic(s, obs, v, priors, settings) if selection == "bic" else v

    def keep_stage(state: StickState, value: float, sweeps: int, name: str, record: list) -> None:
        # A move after the search that changed something: its model is a stage of its own, selected
        # whatever its criterion (the moves keep only what improves it, or are wanted anyway).
        if record:
            stages.append(_stage(state, obs, value, None, sweeps, ref, priors, settings))
            setattr(stages[-1], name, record)
            best[selection] = (getattr(stages[-1], selection), len(stages) - 1, state.copy())

    if settings.dissolve_points or settings.resplit:
        # Hartigan-style moves of groups of points and of whole small sticks on the selected stage
        # (docs/em.md section 6).
        from .refine import dissolve_small_sticks, resplit_pairs

        _, at, cur = best[selection]
        cur, val = cur.copy(), stages[at].objective
        sweeps, gone, moved = 0, [], 0
        if settings.resplit:
            cur, val, sweeps, moved = resplit_pairs(cur, obs, priors, settings, rng, val, criterion)
        if settings.dissolve_points:
            cur, val, n, gone = dissolve_small_sticks(cur, obs, priors, settings, rng, val, criterion,
                                                      settings.dissolve_points, scope=settings.dissolve_scope)
            sweeps += n
            if gone and settings.resplit:  # the points of a dissolved stick may sit better elsewhere
                cur, val, n, m = resplit_pairs(cur, obs, priors, settings, rng, val, criterion)
                sweeps, moved = sweeps + n, moved + m
        if gone or moved:
            stages.append(_stage(cur, obs, val, None, sweeps, ref, priors, settings))
            stages[-1].dissolved = gone
            stages[-1].moved = moved
            for crit in ("objective", "bic"):
                v = getattr(stages[-1], crit)
                if v > best[crit][0]:
                    best[crit] = (v, len(stages) - 1, cur.copy())
    # The selected stage's BIC before the held-out check: what the two starts are compared by.
    search_bic = stages[best[selection][1]].bic
    if settings.holdout and settings.dissolve_points:
        # Small sticks judged by prediction (refine.heldout_dissolve): a 2-point stick fits any
        # two trajectories, so the likelihood cannot reject one that pairs markers across a body.
        # A dissolution kept here is selected whatever its BIC. Its own generator, so that the
        # check leaves the stream of rng (the refit on all frames) as it was.
        from .refine import heldout_dissolve

        _, at, cur = best[selection]
        hrng = child_rng(rng)
        cur, val, n, gone, hinfo = heldout_dissolve(cur.copy(), obs, priors, settings, hrng,
                                                    stages[at].objective,
                                                    settings.dissolve_points, settings.holdout,
                                                    n_masks=settings.holdout_masks,
                                                    scope=settings.dissolve_scope,
                                                    free_points=settings.holdout_points)
        split = []
        if gone and settings.split_dissolved:
            # A dissolved segment's points may have made a larger stick two parts (a thigh's
            # markers on the pelvis): split it before the search re-attaches what hung below.
            # Not judged by the check's prediction, which prefers the fewer sticks (docs/em.md
            # section 11).
            from .refine import articulated_split_round

            cur, v, more, split = articulated_split_round(cur, obs, priors, settings, hrng, settings.split_dissolved)
            val, n = (val if v is None else v), n + more
        if gone:
            stages.append(_stage(cur, obs, val, None, n, ref, priors, settings))
            stages[-1].dissolved = gone
            stages[-1].heldout = hinfo
            stages[-1].split = split
            best[selection] = (getattr(stages[-1], selection), len(stages) - 1, cur.copy())
            if settings.remerge:
                top = best[selection]
                for stage, s in greedy_merges(cur, obs, priors, settings, rng, ref, settings.max_merges):
                    stages.append(stage)
                    if getattr(stage, selection) > top[0]:
                        top = (getattr(stage, selection), len(stages) - 1, s.copy())
                    done += 1
                    report(done, s, stage.objective)
                best[selection] = top
    if settings.max_trees is not None:
        # A figure known to be one piece (max_trees=1): the forest's trees are joined by the
        # best merges between them, whatever the criterion says (tree.join_trees). Before the
        # sub-tree moves, which can re-place a join made at the wrong stick.
        from .tree import join_trees

        _, at, cur = best[selection]
        cur, val, n, joined = join_trees(cur.copy(), obs, priors, settings, rng, stages[at].objective,
                                         settings.max_trees)
        keep_stage(cur, val, n, "joined", joined)  # none when the forest has max_trees trees or fewer
    if settings.unpair:
        # A 2-point stick that three sticks hang from (two limbs' one-marker segments lumped
        # together, CMU's LTHI+RTHI) as two 1-point sticks (bridge.unpair_hubs).
        from .bridge import unpair_hubs

        _, at, cur = best[selection]
        cur, val, n, pairs = unpair_hubs(cur.copy(), obs, priors, settings, rng, stages[at].objective, criterion)
        keep_stage(cur, val, n, "unpaired", pairs)
    if settings.bridge_points:
        # A point that bends its stick (a thigh marker on the thorax) as a stick of its own between
        # two jointed sticks (bridge.py); before the sub-tree moves, which can re-place its joints.
        from .bridge import bridge_points

        _, at, cur = best[selection]
        cur, val, n, bridged = bridge_points(cur.copy(), obs, priors, settings, rng, stages[at].objective,
                                             criterion, settings.bridge_points)
        keep_stage(cur, val, n, "bridged", bridged)
    if settings.split_hubs:
        # A stick on joints only that is two parts (a torso of pelvis and thorax markers, which
        # twist against each other in a walk) split in two, each joint on its piece
        # (refine.split_hubs); before the sub-tree moves, which can then re-hang a part on the
        # piece that fits its joint.
        from .refine import split_hubs

        _, at, cur = best[selection]
        cur, val, n, hubs = split_hubs(cur.copy(), obs, priors, settings, rng, stages[at].objective, criterion)
        keep_stage(cur, val, n, "hubs", hubs)
    if settings.reattach:
        # Sub-tree moves (tree.py): the greedy search never undoes a merge, and a contracted
        # stick links its two neighbours whatever they are; a part hanging from the wrong stick
        # is cut off and re-attached where the objective puts it.
        from .tree import reattach_subtrees, with_spare_endpoint, without_spare_endpoints

        _, at, cur = best[selection]
        cur, val, n = cur.copy(), stages[at].objective, 0
        if settings.spare_end:
            # One more endpoint per stick for the moves, so that a stick on as many joints as it
            # has endpoints (a thorax with lumbar and shoulders) can still take a part hung
            # elsewhere (the head on the pelvis). Settled first: the moves are judged against it.
            cur, val, n = run_em(with_spare_endpoint(cur, priors), obs, priors, settings, settings.n_iter, rng)
        cur, val, more, moves = reattach_subtrees(cur, obs, priors, settings, rng, val, criterion)
        if moves and settings.spare_end:
            fewer = without_spare_endpoints(cur)  # None: a stick is on a joint at every endpoint
            if fewer is not None:
                cur, val = fewer, objective(fewer, obs, priors)
        keep_stage(cur, val, n + more, "reattached", moves)
    for crit in ("objective", "bic"):
        stages[best[crit][1]].state = best[crit][2]
    stages[best[selection][1]].search_bic = search_bic
    return stages, best[selection][1]


# ----------------------------------------------------------------- frame subsampling
def search_frames(mask: np.ndarray, max_frames: int | None) -> np.ndarray | None:
    """Frames for the structure search: ``max_frames`` evenly spaced ones (None: all frames).

    The reference frame (most points visible, the first such) is always included,
    so the stages' endpoint and joint positions are given in the same frame as
    the full model's; and every point keeps at least one frame where it is seen.
    """
    F = mask.shape[1]
    if max_frames is None or F <= max_frames:
        return None
    frames = set(np.unique(np.linspace(0, F - 1, max_frames).round().astype(int)).tolist())
    frames.add(int(np.argmax(mask.sum(axis=0))))
    for p in np.flatnonzero(~mask[:, sorted(frames)].any(axis=1)):
        seen = np.flatnonzero(mask[p])
        if seen.size:
            frames.add(int(seen[seen.size // 2]))
    return np.array(sorted(frames))


def extend_frames(st: StickState, obs: Observations, frames: np.ndarray, priors: Priors) -> StickState:
    """A model fitted on ``frames`` carried over to every frame of ``obs`` (a warm start for EM).

    L, K, G, R and the precisions of the vertices are kept; rotations are
    interpolated between the fitted frames (slerp), translations and vertex
    means linearly; endpoint posteriors follow. The vertex chain's precision
    ``tau_t`` is rescaled to the finer frame spacing (a random walk's step
    variance is proportional to the time step).
    """
    from .initialise import interpolate_rotations
    from .updates import update_endpoints

    F = obs.n_frames
    D = st.n_dims
    good = np.zeros(F, bool)
    good[frames] = True
    f = np.arange(F)
    out = st.copy()
    rot = np.zeros((st.n_sticks, F, D, 3))
    trans = np.zeros((st.n_sticks, F, D))
    for s in range(st.n_sticks):
        R = np.zeros((F, D, 3))
        R[frames] = st.rot[s]
        rot[s] = interpolate_rotations(R, good)
        for d in range(D):
            trans[s, :, d] = np.interp(f, frames, st.trans[s, :, d])
    mu_v = np.zeros((st.n_vertices, F, D))
    for j in range(st.n_vertices):
        for d in range(D):
            mu_v[j, :, d] = np.interp(f, frames, st.mu_v[j, :, d])
    out.rot, out.trans, out.mu_v = rot, trans, mu_v
    n = st.vertex_counts()
    a = st.alpha / st.beta
    step = (F - 1) / max(frames.size - 1, 1)
    out.tau_t = float(min(st.tau_t * step * step, priors.max_precision))
    out.alpha = priors.alpha0 + 0.5 * D * F * n
    out.beta = out.alpha / a
    out.tau_v = (a * n)[:, None] + out.tau_t * chain_degree(F)[None, :]
    out.mu_e = np.zeros((st.ends.shape[0], F, D))
    out.ghosts = None
    out._design = None
    out._quat = None
    update_endpoints(out)
    return out
