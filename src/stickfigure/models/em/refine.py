"""Checking the initial sticks: split non-rigid ones, join rigidly moving pairs (an extension).

The paper takes the number of sticks from Affinity Propagation and never
changes it (resampling only moves single points). When the clustering puts
two parts into one group, or one part into two, the merge search cannot
repair it. After the first EM run (no joints yet) every stick is therefore
checked by BIC with a common noise level ``sigma^2`` (the median per-stick
residual variance, robust to the sticks being tested):

* split: the stick's points are clustered in two
  (:func:`stickfigure.segmentation.affinity_propagation_segments` with
  ``n_segments=2``), each half fitted by structure from motion; the split is
  kept when ``(RSS_one - RSS_two) / (2 sigma^2) > k/2 log N`` with
  ``k = F (3 + D)`` the extra motion parameters and N the number of observed
  coordinates;
* join: two sticks are made one when one stick's motion explains the other's
  points (each point's local coordinates refitted) at a loss below ``k/2 log N``
  in the same units.

Both change only sticks without joints, before any merge, so the model is
re-initialised from the new assignments (docs/em.md).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..._validation import check_positive
from ...geometry import noise_level
from ...synthetic import occlude
from ...trajectories import Trajectories
from .initialise import initial_state
from .model import Observations, Priors, StickState
from .updates import MIN_ROTATION_POINTS, em_sweep

__all__ = ["motion_parameters", "fit_dof", "noise_variance", "misfit_ratios", "split_candidates", "join_candidates",
           "refine_labels", "dissolve_stick", "dissolve_small_sticks", "heldout_dissolve", "resplit_pairs"]


def _sfm_rss(obs: Observations, idx: np.ndarray, rng: np.random.Generator, n_iter: int = 60) -> float:
    """Residual sum of squares of one rigid orthographic body fitted to the points ``idx``.

    Structure from motion, refined by ``n_iter`` rotation/shape updates (the
    metric upgrade alone is poor for a handful of points: 4 points fit any
    affine motion exactly and leave the metric constraints to the noise).
    """
    sub = obs.take(idx)
    pri = Priors()
    st = initial_state(sub, np.zeros(idx.size, np.int64), 1, pri, rng, n_ends=2)
    for it in range(n_iter):
        em_sweep(st, sub, pri, global_rotations=it % 10 == 0, use_polar=it == 0)
    return float(st.design(sub).residual_sq(st.rot, st.trans, st.local)[0])


def motion_parameters(st: StickState, obs: Observations) -> np.ndarray:
    """Free motion parameters of every stick, shape (S,).

    D translations in every frame where the stick shows a point and 3 rotation angles
    where it shows at least ``min(MIN_ROTATION_POINTS, its size)``; elsewhere its
    rotation is interpolated (:func:`updates.update_motions`), not fitted. On complete
    data ``F (3 + D)``.
    """
    n = st.design(obs).n  # (S, F)
    size = st.stick_sizes()
    rot = n >= np.minimum(MIN_ROTATION_POINTS, size)[:, None]
    return np.sum(obs.n_dims * (n >= 1) + 3 * (rot & (n >= 1)), axis=1).astype(float)


def fit_dof(st: StickState, obs: Observations) -> np.ndarray:
    """Degrees of freedom left by every stick's fit, shape (S,): its observed coordinates less
    :func:`motion_parameters` and 3 local coordinates per point (a rigid stick's expected RSS is
    ``sigma^2`` times this)."""
    return (obs.n_dims * st.design(obs).n.sum(axis=1) - motion_parameters(st, obs)
            - 3 * st.stick_sizes())


def noise_variance(st: StickState, obs: Observations, priors: Priors) -> tuple[np.ndarray, float]:
    """Per-stick residual sums of squares (S,) and a robust noise variance per coordinate.

    Each stick's variance is corrected for the degrees of freedom its fit used
    (:func:`motion_parameters`: ``3 + D`` per frame it is seen in, or only ``D`` where
    its rotation is interpolated; 3 local coordinates per point), so sticks with few points do not look less noisy than they are; the
    noise variance is the lower quartile over sticks, so up to three quarters of
    the sticks may be bad without inflating it. It is at least ``1 / priors.max_precision``,
    the bound on tau_w: on noiseless data every stick's residual is what the EM's
    truncated optimisation left, and measured against the best-converged stick's
    residue that looks like articulation everywhere (docs/em.md, section 11).
    """
    des = st.design(obs)
    rss = des.residual_sq(st.rot, st.trans, st.local)
    n = des.n.sum(axis=1) * obs.n_dims
    dof = fit_dof(st, obs)
    ok = dof > 0
    var = float(np.quantile(rss[ok] / dof[ok], 0.25)) if ok.any() else float(rss.sum() / max(n.sum(), 1))
    return rss, max(var, 1.0 / priors.max_precision)


def split_candidates(st: StickState, obs: Observations, rng: np.random.Generator, priors: Priors, *,
                     min_points: int) -> list[tuple[int, np.ndarray]]:
    """Sticks worth splitting in two: [(stick, labels of its points 0/1)]."""
    from ...segmentation import affinity_propagation_segments

    rss, var = noise_variance(st, obs, priors)
    N = float(obs.mask.sum() * obs.n_dims)
    F, D = obs.n_frames, obs.n_dims
    penalty = 0.5 * F * (3 + D) * np.log(N)
    out = []
    for s in range(st.n_sticks):
        idx = np.flatnonzero(st.labels == s)
        if idx.size < 2 * max(min_points, 4):
            continue
        # Only sticks that fit clearly worse than the others can gain that much.
        if rss[s] / (2.0 * var) - obs.mask[idx].sum() * D / 2.0 < penalty:
            continue
        xy = np.where(obs.mask[idx][..., None] > 0, obs.w[idx], np.nan)
        halves = affinity_propagation_segments(xy, n_segments=2, random_state=rng)
        if np.bincount(halves, minlength=2).min() < min_points:
            continue
        two = sum(_sfm_rss(obs, idx[halves == h], rng) for h in (0, 1))
        if (rss[s] - two) / (2.0 * var) > penalty:
            out.append((s, halves))
    return out


def join_candidates(st: StickState, obs: Observations, priors: Priors) -> list[tuple[int, int]]:
    """Pairs of sticks that move as one rigid body, best first (each stick at most once).

    Joining b into a costs ``sum_{p in b} (|w_p - R_a l_pa - t_a|^2) - RSS_b`` with each
    point's coordinates refitted on a (:func:`assign.candidate_fits`, the same fit the
    resampling uses), i.e. a's motion has to explain b's points too; the pair is
    joined when the cheaper direction loses less than the BIC charge ``k_b / 2 log N``
    (in units of ``2 sigma^2``) of the motion parameters the join saves: D translations in
    every frame where b shows a point, and 3 rotation angles only where its rotation is
    fitted (:func:`motion_parameters`). On complete data that is the former
    ``F (3 + D)``; with 75% of the observations withheld the former charge exceeded all
    the evidence a stick has and joined articulated neighbours.
    """
    from .assign import candidate_fits

    S = st.n_sticks
    if S < 2:
        return []
    rss, var = noise_variance(st, obs, priors)
    D = obs.n_dims
    N = float(obs.mask.sum() * D)
    saved = 0.5 * np.log(N) * motion_parameters(st, obs)  # (S,)
    _, sq = candidate_fits(st, obs, priors)  # (P, S)
    moved = np.zeros((S, S))  # moved[b, a] = RSS of b's points on a
    np.add.at(moved, st.labels, sq)
    excess = (moved - rss[:, None]) / (2.0 * var) - saved[:, None]  # b into a, net of b's saved charge
    excess = np.minimum(excess, excess.T)
    np.fill_diagonal(excess, np.inf)
    found = [(float(excess[a, b]), (a, b)) for a in range(S) for b in range(a + 1, S) if excess[a, b] < 0]
    used: set[int] = set()
    out = []
    for _, (a, b) in sorted(found):
        if a not in used and b not in used:
            out.append((a, b))
            used |= {a, b}
    return out


def refine_labels(st: StickState, obs: Observations, rng: np.random.Generator, *, min_points: int,
                  priors: Priors | None = None) -> tuple[np.ndarray, dict]:
    """New assignments after the split and join checks (unchanged when none applies)."""
    labels = st.labels.copy()
    S = st.n_sticks
    priors = priors or Priors()
    splits = split_candidates(st, obs, rng, priors, min_points=min_points)
    joins = join_candidates(st, obs, priors)
    split_sticks = {s for s, _ in splits}
    for s, halves in splits:
        idx = np.flatnonzero(st.labels == s)
        labels[idx[halves == 1]] = S
        S += 1
    for a, b in joins:
        if a in split_sticks or b in split_sticks:
            continue
        labels[labels == b] = a
    _, labels = np.unique(labels, return_inverse=True)
    return labels, {"splits": [int(s) for s, _ in splits], "joins": [[int(a), int(b)] for a, b in joins]}


# ----------------------------------------------------------------- articulated splits
def _axis_bipartitions(local: np.ndarray, max_candidates: int = 24, n_axes: int = 3) -> list[np.ndarray]:
    """Candidate two-way splits of a stick's points: thresholds along principal axes of its shape.

    Two parts of a limb held in one stick lie on either side of their joint, so a
    plane normal to one of the shape's principal axes separates them. ``n_axes``:
    how many axes, the major one first (1: across the stick's length only).
    Returns boolean masks (True = second piece), each split once, both pieces
    non-empty.
    """
    n = local.shape[0]
    c = local - local.mean(axis=0)
    _, _, Vt = np.linalg.svd(c, full_matrices=False)
    out: list[np.ndarray] = []
    seen: set[tuple[int, ...]] = set()
    for axis in Vt[:n_axes]:
        order = np.argsort(c @ axis, kind="stable")
        for cut in range(1, n):
            mask = np.zeros(n, bool)
            mask[order[cut:]] = True
            key = tuple(np.flatnonzero(mask if mask[0] else ~mask))
            if key not in seen:
                seen.add(key)
                out.append(mask)
    # Balanced cuts first: they are the likelier ones when the list has to be cut short.
    out.sort(key=lambda m: abs(int(m.sum()) - n / 2))
    return out[:max_candidates]


def _split_block(st: StickState, obs: Observations, s: int, second: np.ndarray,
                 priors: Priors) -> tuple[StickState, Observations]:
    """Stick ``s`` as two sticks joined at one vertex, both starting at the stick's motion.

    Each piece has a single endpoint, the joint (free endpoints would only hold
    the pieces at their common starting motion); it starts midway between the
    closest pair of points across the split, in the stick's local frame.
    """
    from .model import Ghosts, chain_degree

    idx = np.flatnonzero(st.labels == s)
    a_idx, b_idx = idx[~second], idx[second]
    pts = np.concatenate([a_idx, b_idx])
    labels = np.concatenate([np.zeros(a_idx.size, np.int64), np.ones(b_idx.size, np.int64)])
    F, D = st.n_frames, st.n_dims
    la, lb = st.local[a_idx], st.local[b_idx]
    d = np.linalg.norm(la[:, None] - lb[None], axis=-1)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    ends = np.repeat((0.5 * (la[i] + lb[j]))[None], 2, axis=0)
    vertex_of = np.zeros(2, np.int64)
    rot = np.repeat(st.rot[s][None], 2, axis=0)
    trans = np.repeat(st.trans[s][None], 2, axis=0)
    blk = StickState(labels=labels, vertex_of=vertex_of, rot=rot, trans=trans, local=st.local[pts].copy(),
                     ends=ends, mu_e=np.zeros((2, F, D)), tau_e=np.ones(2), mu_v=np.zeros((1, F, D)),
                     tau_v=np.ones((1, F)), alpha=np.ones(1), beta=np.ones(1), tau_w=st.tau_w, tau_m=st.tau_m,
                     tau_t=st.tau_t, ghosts=Ghosts.empty(1, F, D))
    blk.mu_e = blk.end_predictions()
    blk.mu_v = blk.mu_e.mean(axis=0, keepdims=True)
    blk.alpha = priors.alpha0 + 0.5 * D * F * np.array([2.0])
    blk.beta = blk.alpha / st.tau_w
    a = blk.alpha / blk.beta
    blk.tau_e = blk.tau_m + a[vertex_of]
    blk.tau_v = (2.0 * a)[:, None] + blk.tau_t * chain_degree(F)[None, :]
    return blk, obs.take(pts)


def articulated_split_candidates(st: StickState, obs: Observations, priors: Priors, *, n_sweeps: int = 40,
                                 n_finalists: int = 5, max_frames: int = 240, skip: set[int] | None = None,
                                 var: float | None = None, return_gain: bool = False,
                                 n_axes: int = 1, n_jobs: int = 1, min_piece: int = 1) -> list[tuple]:
    """Sticks that are two parts joined by a joint: [(stick, 0/1 labels of its points)].

    The split check above needs two rigid halves of at least four points each
    (an affine body fits any four trajectories) and charges a free motion for
    the second one. Body segments carry one to three markers, so a limb often
    starts as one stick holding two or three segments. Here the second piece
    hangs from the first at a joint: a piece of one or two points plus the
    joint is a rigid body the orthographic metric model can test (its
    rotation is pinned by the joint and its points), and the extra parameters
    are the piece's rotations and the joint, ``k = 3 F + 6``. For every stick
    that fits clearly worse than the noise (as in :func:`split_candidates`), the
    splits by a plane normal to the major axis of its shape (``n_axes`` = 1; with
    3, to any principal axis; :func:`_axis_bipartitions`) are fitted as two
    sticks sharing a vertex, all candidates of all sticks at once (one batched
    EM run of ``n_sweeps`` sweeps on the disjoint union, precisions fixed, at
    most ``max_frames`` evenly spaced frames); the ``n_finalists`` best of each
    stick are fitted again for ``3 n_sweeps`` sweeps, and the best of those is kept when ``(RSS_one - RSS_two) / (2 sigma^2) > k/2 log N``.
    ``var``: the noise variance ``sigma^2`` (default: :func:`noise_variance` of ``st``).
    ``return_gain``: also return each split's gain ``(RSS_one - RSS_two) / (2 sigma^2)``.
    ``n_jobs`` > 1: half of the candidates are fitted in a forked child (:func:`.forked.in_halves`;
    the same numbers). ``min_piece``: only cuts whose two pieces hold at least this many points.
    """
    from .forked import in_halves
    from .structure import _union

    rss, var0 = noise_variance(st, obs, priors)
    var = var0 if var is None else var  # the noise level of a larger model this state is part of
    N = float(obs.mask.sum() * obs.n_dims)
    F, D = obs.n_frames, obs.n_dims
    frames = np.arange(F) if F <= max_frames else np.unique(np.linspace(0, F - 1, max_frames).round().astype(int))
    Fs = frames.size
    # BIC with each parameter charged log of the observations that determine it: a per-frame
    # rotation only sees the stick's points in that frame (D n_s coordinates), the joint sees all.
    def penalty_of(n_s: int) -> float:
        return 0.5 * 3 * F * np.log(D * n_s) + 0.5 * 6 * np.log(N)
    sub = _frames(st, frames)
    sobs = obs.take_frames(frames)
    res = (obs.w - st.point_predictions()) * obs.mask[..., None]
    point_rss = np.sum(res * res, axis=(1, 2))
    from .assign import candidate_fits

    _, sq = candidate_fits(st, obs, priors)
    own = sq[np.arange(obs.n_points), st.labels]
    other = np.where(np.arange(st.n_sticks)[None, :] == st.labels[:, None], np.inf, sq).min(axis=1)
    # The fit's expected RSS is sigma^2 times its degrees of freedom, not times the coordinates.
    dof = fit_dof(st, obs)
    blocks, owners = [], []
    for s in range(st.n_sticks):
        if skip and s in skip:
            continue
        idx = np.flatnonzero(st.labels == s)
        if idx.size < 3:
            continue
        # Non-rigid without its worst point too, where another stick explains that point: a
        # single misassigned point (which resampling moves) is not a joint. A point no other
        # stick explains may be a segment of its own (a thigh's one marker).
        worst = int(np.argmax(point_rss[idx]))
        rest = rss[s] - (point_rss[idx[worst]] if other[idx[worst]] < own[idx[worst]] else 0.0)
        if rest / (2.0 * var) - dof[s] / 2.0 < penalty_of(idx.size):
            continue
        for second in _axis_bipartitions(st.local[idx], n_axes=n_axes):
            if min(int(second.sum()), int((~second).sum())) < min_piece:
                continue
            blocks.append(_split_block(sub, sobs, s, second, priors))
            owners.append((s, second))
    if not blocks:
        return []
    one_rss = sub.design(sobs).residual_sq(sub.rot, sub.trans, sub.local)

    def split_rss(chosen: list[int], sweeps: int) -> list[float]:
        u, uobs, sb, _ = _union([blocks[c] for c in chosen])
        for it in range(sweeps):
            em_sweep(u, uobs, priors, precisions=False, global_rotations=it % 10 == 0, use_polar=False)
        per = u.design(uobs).residual_sq(u.rot, u.trans, u.local)
        return np.bincount(sb, weights=per, minlength=len(chosen)).tolist()

    def gains(chosen: list[int], sweeps: int) -> np.ndarray:
        # The blocks are independent: half of them in a forked child (the same numbers).
        rss2 = in_halves(lambda part: split_rss(part, sweeps), chosen, parallel=n_jobs > 1,
                         weights=[blocks[c][1].w.size for c in chosen])
        return np.array([(one_rss[owners[c][0]] - r) * (F / Fs) / (2.0 * var) for c, r in zip(chosen, rss2)])

    # Screen every candidate with n_sweeps sweeps; the best few of each stick are fitted for
    # three times as long before one is chosen (a right split can converge more slowly).
    g = gains(list(range(len(blocks))), n_sweeps)
    finalists = []
    for s in sorted({o[0] for o in owners}):
        mine = [c for c in range(len(blocks)) if owners[c][0] == s]
        finalists += sorted(mine, key=lambda c: -g[c])[:n_finalists]
    g2 = gains(finalists, 3 * n_sweeps)
    # A piece whose points another stick explains is a clustering error, not a joint: the
    # resampling's alternative (moving them there) is credited first.
    move = np.maximum(own - other, 0.0) / (2.0 * var)
    best: dict[int, tuple[float, np.ndarray]] = {}
    for c, gain in zip(finalists, g2):
        s, second = owners[c]
        idx = np.flatnonzero(st.labels == s)
        gain = gain - max(move[idx[second]].sum(), move[idx[~second]].sum())
        if gain > penalty_of(second.size) and (s not in best or gain > best[s][0]):
            best[s] = (gain, second.astype(np.int64))
    if return_gain:
        return [(s, halves, g) for s, (g, halves) in sorted(best.items())]
    return [(s, halves) for s, (_, halves) in sorted(best.items())]


def _frames(st: StickState, frames: np.ndarray) -> StickState:
    """The state restricted to some frames (motions and endpoint/vertex posteriors)."""
    out = st.copy()
    out.rot, out.trans = np.ascontiguousarray(st.rot[:, frames]), np.ascontiguousarray(st.trans[:, frames])
    out.mu_e, out.mu_v, out.tau_v = st.mu_e[:, frames], st.mu_v[:, frames], st.tau_v[:, frames]
    out.ghosts = None
    return out


def free_end_sticks(st: StickState) -> np.ndarray:
    """Which sticks have an endpoint on no joint (where a split can hang its new piece) and may
    take another joint (:meth:`StickState.open_sticks`), shape (S,)."""
    return st.open_sticks()


def _pieces(st: StickState, s: int, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The point indices of stick ``s``'s two pieces A and B (``second``: True for B, in label order)."""
    idx = np.flatnonzero(st.labels == s)
    return idx[~second.astype(bool)], idx[second.astype(bool)]


def _joints_to_second(st: StickState, s: int, local_a: np.ndarray, local_b: np.ndarray) -> list[int]:
    """Which of stick ``s``'s endpoints on a joint go with piece B when it is split (slots 0..E-1).

    Those nearer to B's points than to A's (local coordinates of the pieces'
    points, shapes (n_a, 3) and (n_b, 3)), in slot order, at most E - 1 of them:
    B keeps one endpoint for its joint with A.
    """
    E = st.ends_per_stick
    cnt = st.vertex_counts()
    out = []
    for e in range(E):
        if cnt[st.vertex_of[E * s + e]] > 1:
            k = st.ends[E * s + e]
            if np.min(np.linalg.norm(local_b - k, axis=1)) < np.min(np.linalg.norm(local_a - k, axis=1)):
                out.append(e)
    return out[:E - 1]


def apply_articulated_splits(st: StickState, obs: Observations, priors: Priors,
                             splits: list[tuple[int, np.ndarray]], *, n_sweeps: int = 40) -> StickState:
    """The model with every split stick replaced by two sticks joined at a new vertex.

    Each split is fitted on all frames as in :func:`articulated_split_candidates`
    (the two pieces and their joint, batched), then put into the model: piece A
    keeps the stick's index and endpoints, piece B becomes a new stick whose
    first endpoint shares the joint's vertex with a free endpoint of A. An
    endpoint of the old stick already in a joint moves to B when B's points are
    nearer to it than A's (and B has a free slot); A's endpoint left behind is
    free. A stick whose endpoints are all on joints is split only when one of
    them moves to B (:func:`split_hubs`); otherwise it is left as it was. The
    new stick's other endpoints start free, along its principal axis.
    Everything else is unchanged; the EM run that follows re-optimises the
    whole model.
    """
    from .initialise import end_positions
    from .structure import _union
    from .updates import update_endpoints

    S, E = st.n_sticks, st.ends_per_stick
    F, D = st.n_frames, st.n_dims
    cnt = st.vertex_counts()
    free = free_end_sticks(st)

    def placeable(s: int, h: np.ndarray) -> bool:
        # A stick with every endpoint on a joint can be split only if one of them moves to B.
        a, b = _pieces(st, s, h)
        return bool(free[s] or _joints_to_second(st, s, st.local[a], st.local[b]))

    ok = [(s, h) for s, h in splits if placeable(s, h)]
    if not ok:
        return st
    blocks = [_split_block(st, obs, s, h.astype(bool), priors) for s, h in ok]
    u, uobs, _, _ = _union(blocks)
    for it in range(n_sweeps):
        em_sweep(u, uobs, priors, precisions=False, global_rotations=it % 10 == 0, use_polar=False)
    out = st.copy()
    labels = st.labels.copy()
    rot, trans, local = list(st.rot), list(st.trans), st.local.copy()
    ends = [list(st.ends[E * s:E * (s + 1)]) for s in range(S)]
    verts = [list(st.vertex_of[E * s:E * (s + 1)]) for s in range(S)]
    mu_v, tau_v = list(st.mu_v), list(st.tau_v)
    alpha, beta = list(st.alpha), list(st.beta)
    po = 0
    for b, (s, h) in enumerate(ok):
        idx = np.flatnonzero(st.labels == s)
        second = h.astype(bool)
        pts = np.concatenate([idx[~second], idx[second]])
        n_pts = pts.size
        blk_local = u.local[po:po + n_pts]
        po += n_pts
        n_a = int((~second).sum())
        to_b = _joints_to_second(st, s, blk_local[:n_a], blk_local[n_a:])
        if not free[s] and not to_b:
            continue  # the fitted pieces moved no joint to B: A has no endpoint for their joint
        local[pts] = blk_local
        new = len(rot)
        labels[idx[second]] = new
        rot[s], trans[s] = u.rot[2 * b], u.trans[2 * b]
        rot.append(u.rot[2 * b + 1])
        trans.append(u.trans[2 * b + 1])
        lb = blk_local[n_a:]
        b_ends = list(end_positions(lb, np.zeros(lb.shape[0], np.int64), 1, E))
        b_verts: list[int] = [-1] * E
        # Joints the old stick already had: keep each on the piece whose points are nearer.
        for slot, e in enumerate(to_b, start=1):
            b_ends[slot], b_verts[slot] = ends[s][e], verts[s][e]
            # A gets a fresh free vertex in that endpoint's place.
            verts[s][e] = len(mu_v)
            mu_v.append(np.zeros((F, D)))
            tau_v.append(np.ones(F))
            alpha.append(1.0)
            beta.append(1.0)
        free_a = [e for e in range(E) if (cnt[verts[s][e]] if verts[s][e] < cnt.size else 1) == 1]
        ea = min(free_a, key=lambda e: verts[s][e] >= st.n_vertices)  # an original free vertex first
        j = verts[s][ea]
        ends[s][ea] = u.ends[2 * b]
        b_ends[0], b_verts[0] = u.ends[2 * b + 1], j
        mu_v[j], tau_v[j] = u.mu_v[b], u.tau_v[b]
        alpha[j], beta[j] = u.alpha[b], u.beta[b]
        for slot in range(1, E):
            if b_verts[slot] < 0:
                b_verts[slot] = len(mu_v)
                mu_v.append(np.zeros((F, D)))
                tau_v.append(np.ones(F))
                alpha.append(1.0)
                beta.append(1.0)
        ends.append(b_ends)
        verts.append(b_verts)
    out.labels = labels
    out.rot, out.trans, out.local = np.stack(rot), np.stack(trans), local
    out.ends = np.concatenate([np.asarray(e) for e in ends]).reshape(-1, 3)
    out.vertex_of = np.concatenate([np.asarray(v, np.int64) for v in verts])
    out.mu_v, out.tau_v = np.stack(mu_v), np.stack(tau_v)
    out.alpha, out.beta = np.asarray(alpha, float), np.asarray(beta, float)
    # Free vertices (and their endpoints) start at their endpoint's prediction under the new
    # motions, as in initial_state (old ones would sit where the old motion put them).
    pred = out.end_predictions()
    fresh = out.vertex_counts() == 1
    fresh[st.n_vertices:] = True
    start_vertices(out, np.flatnonzero(fresh), pred, priors)
    out.mu_e = pred.copy()
    out.tau_e = np.ones(out.ends.shape[0])
    out.ghosts = None
    out._design = None
    out._quat = None
    update_endpoints(out)
    return out


def start_vertices(st: StickState, vertices: np.ndarray, pred: np.ndarray, priors: Priors) -> None:
    """Start ``vertices`` (in place) at the mean of their endpoints' predictions ``pred`` (E, F, D),
    with the precision the prior and the noise level ``tau_w`` give, as in initial_state."""
    from .model import chain_degree

    F, D = st.n_frames, st.n_dims
    n = st.vertex_counts()
    for j in vertices:
        st.mu_v[j] = pred[st.vertex_of == j].mean(axis=0)
        st.alpha[j] = priors.alpha0 + 0.5 * D * F * n[j]
        st.beta[j] = st.alpha[j] / st.tau_w
        st.tau_v[j] = st.alpha[j] / st.beta[j] * n[j] + st.tau_t * chain_degree(F)


# A stick whose misfit ratio (misfit_ratios) exceeds this is suspect of holding points of more
# than one part (right sticks of random figures 0.95-1.34, mostly below 1.15).
SUSPECT_MISFIT = 1.25


# ------------------------------------------------------------- dissolving small sticks
def dissolve_stick(st: StickState, obs: Observations, priors: Priors, s: int) -> StickState:
    """The model without stick ``s``: its points moved, its joints contracted into one.

    Each point of ``s`` goes to the stick that explains its trajectory best with
    its local coordinates refitted (:func:`assign.candidate_fits`, the posterior
    mode of the resampling without ``s``). The vertices where ``s`` meets other
    sticks become one vertex (the stick shrinks to a point, so its neighbours
    now share a joint; contracting one stick of a tree leaves a tree). For a
    stick on two joints, a part may instead hang from the stick that took the
    point of ``s`` nearest its joint (:func:`_relink_vertices`; also a tree).
    That joint's endpoints start at the least-squares joint of their sticks
    (:func:`structure.joint_least_squares`) and its precision as in a merge.
    """
    from .assign import candidate_fits, remove_sticks
    from .model import chain_degree
    from .structure import joint_least_squares
    from .updates import update_endpoints

    S, E = st.n_sticks, st.ends_per_stick
    D, F = st.n_dims, st.n_frames
    loc, sq = candidate_fits(st, obs, priors)
    counts = st.stick_sizes().astype(float)
    logp = np.log(np.maximum(counts, 1.0) / obs.n_points)[None, :] - 0.5 * st.tau_w * sq
    logp[:, s] = -np.inf
    pts = np.flatnonzero(st.labels == s)
    new = np.argmax(logp[pts], axis=1)
    out = st.copy()
    out.labels[pts] = new
    out.local[pts] = loc[pts, new]
    cnt = st.vertex_counts()
    own = st.vertex_of[E * s:E * (s + 1)]
    joints = np.unique(own[cnt[own] >= 2])
    a_cap = float(np.max(st.alpha[joints] / st.beta[joints])) if joints.size else 0.0
    # The vertices made one: the two joints of a stick between two parts, unless a part is
    # better hung where the point nearest its joint went (_relink_vertices); all joints of a hub.
    unify = _relink_vertices(st, out, obs, s, pts, joints) if joints.size == 2 else joints
    if joints.size >= 2:
        out.vertex_of[np.isin(out.vertex_of, unify)] = unify[0]
    out = remove_sticks(out, np.array([s]))
    if joints.size >= 2:
        # The contracted joint, in the new vertex numbering (remove_sticks keeps the order of
        # the remaining endpoints).
        old_v = st.vertex_of[np.repeat(np.arange(S) != s, E)]
        jn = int(out.vertex_of[np.flatnonzero(np.isin(old_v, unify))[0]])
        ends = np.flatnonzero(out.vertex_of == jn)
        if ends.size >= 2:
            k, _ = joint_least_squares(out, list(ends // E), list(out.ends[ends]), seen=out.design(obs).n)
            out.ends[ends] = k
            pred = (out.rot[ends // E] @ k[:, None, :, None])[..., 0] + out.trans[ends // E]
            mu = pred.mean(axis=0)
            ss = float(np.sum((pred - mu) ** 2))
            n = float(ends.size)
            a = min(D * F * n / max(ss, 1e-300), a_cap)
            out.mu_v[jn] = mu
            out.alpha[jn] = priors.alpha0 + 0.5 * D * F * n
            out.beta[jn] = out.alpha[jn] / a
            out.tau_v[jn] = a * n + out.tau_t * chain_degree(F)
    out._design = None
    out._quat = None
    update_endpoints(out)
    return out


def _relink_vertices(st: StickState, moved: StickState, obs: Observations, s: int, pts: np.ndarray,
                     joints: np.ndarray) -> np.ndarray:
    """The two vertices made one when stick ``s``, on the two joints ``joints``, is dissolved.

    ``moved``: ``st`` with the points ``pts`` of ``s`` already on their new sticks.
    Contracting ``s`` (the two joints) links its two neighbours to each other. But
    where the point of ``s`` nearest one of its joints (RMS distance over the point's
    frames) went to a stick on the *other* side of ``s``, the part on that joint hangs
    from that stick instead, at its vertex nearest the joint: the shoulder marker of a
    stick that also held a head marker goes back to the torso, which hangs on the
    head's side, and the arm that was on the shoulder joint goes with it, not onto the
    head (CMU 85_02, docs/em.md section 11, session 14). When both joints qualify, the
    nearer vertex is taken; when neither does, the contraction.
    """
    from .assign import remove_sticks
    from .bridge import vertex_distances
    from .structure import components

    E = st.ends_per_stick
    without = remove_sticks(moved, np.array([s]))
    comp_s, comp_v = components(without)
    new_stick = np.cumsum(np.arange(st.n_sticks) != s) - 1  # numbering without s
    old_v = st.vertex_of[np.repeat(np.arange(st.n_sticks) != s, E)]  # without's endpoints, st's vertices
    side = {int(j): int(comp_v[without.vertex_of[np.flatnonzero(old_v == j)[0]]]) for j in joints}
    best: tuple[float, int, int] | None = None
    for k, j in enumerate(joints):
        d = [float(vertex_distances(st, obs, np.array([j]), int(p))[0]) for p in pts]
        t = int(moved.labels[pts[int(np.argmin(d))]])
        if comp_s[new_stick[t]] != side[int(joints[1 - k])]:
            continue  # it went to this joint's own side: that part stays where it is
        verts = np.unique(st.vertex_of[E * t:E * (t + 1)])
        dv = np.sum((st.mu_v[verts] - st.mu_v[j][None]) ** 2, axis=(1, 2))
        i = int(np.argmin(dv))
        if best is None or dv[i] < best[0]:
            best = (float(dv[i]), int(j), int(verts[i]))
    return joints if best is None else np.array([best[1], best[2]])


def _next_small_stick(st: StickState, order: np.ndarray, max_points: int, tried: set, scope: str = "all"
                      ) -> tuple[int, tuple[int, ...]] | None:
    """The first stick in ``order`` with at most ``max_points`` points whose point set is not in
    ``tried`` (which it joins), as (stick, point set); None when there is none. With
    ``scope="leaves"`` only sticks with at most one joint count."""
    if scope not in ("all", "leaves"):
        raise ValueError(f"scope must be 'all' or 'leaves', got {scope!r}")
    sizes = st.stick_sizes()
    if scope == "leaves":
        order = np.asarray(order)
        order = order[st.joints_per_stick()[order] <= 1]
    for s in order:
        key = tuple(np.flatnonzero(st.labels == s).tolist())
        if sizes[s] <= max_points and key not in tried:
            tried.add(key)
            return int(s), key
    return None


def _dissolve_loss(st: StickState, obs: Observations, priors: Priors, s: int) -> float:
    """Loss of fit, in units of the noise (``RSS / (2 sigma^2)``), when the points of stick ``s``
    move to their best other sticks with all motions fixed."""
    from .assign import candidate_fits

    rss, var = noise_variance(st, obs, priors)
    _, sq = candidate_fits(st, obs, priors)
    pts = np.flatnonzero(st.labels == s)
    other = np.delete(sq[pts], s, axis=1)
    return float((other.min(axis=1).sum() - rss[s]) / (2.0 * var))


def dissolve_small_sticks(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
                          value: float, criterion: Callable[[StickState, float], float], max_points: int,
                          trial_iter: int | None = None, scope: str = "all"
                          ) -> tuple[StickState, float, int, list[list[int]]]:
    """Hartigan-style moves of whole small sticks: keep a dissolution when the criterion improves.

    Every stick with at most ``max_points`` points (smallest first) is tried once,
    unless moving its points with the motions fixed already loses more than
    ``LOOSE_FACTOR`` (10) times the BIC charge of its rotations (``3F/2 log N``): a
    real body segment's markers fit the other sticks far worse than that, and
    the trial would cost an EM run. Then :func:`dissolve_stick`, then an EM run (``trial_iter`` sweeps, default
    ``settings.n_iter``, resampling, early stop) re-fits the model, and the result replaces the current one when
    ``criterion(state, objective)`` (the selection's BIC or objective) is higher.
    A 1-3 point stick made of points from the two parts beside a joint (a
    clustering error that an articulated split or the resampling turned into a
    stick of its own) fits its points almost exactly, so the objective alone
    favours it; BIC charges its per-frame rotations.
    With ``scope="leaves"`` only sticks with at most one joint are tried: a stick
    between two joints (a thigh, between the pelvis and the shin) is kept, because
    once it is gone no link of the part below it is right (docs/em.md section 11).
    The trials are greedy (:func:`.trials.greedy_trials`: each draws from its own
    generator spawned from ``rng``; with ``settings.n_jobs`` > 1 the trial that
    follows a loss runs beside the current one).

    Returns the state, its objective, the EM sweeps run, and the point sets of the
    dissolved sticks.
    """
    from .structure import LOOSE_FACTOR, out_of_reach, run_em
    from .trials import greedy_trials

    cur = {"st": st, "value": value, "best": criterion(st, value)}
    trial_iter = settings.n_iter if trial_iter is None else trial_iter
    logN = float(np.log(obs.mask.sum() * obs.n_dims))
    done: list[list[int]] = []
    sweeps = 0

    def propose(tried: set) -> tuple[int, tuple[int, ...]] | None:
        now = cur["st"]
        while now.n_sticks > 1:
            nxt = _next_small_stick(now, np.argsort(now.stick_sizes(), kind="stable"), max_points, tried, scope)
            # Cheap test first: the points' fit on their best other sticks (motions fixed, local
            # coordinates refitted) may lose at most LOOSE_FACTOR times the parameters saved
            # (a real segment's points fit the other sticks far worse).
            if nxt is None or _dissolve_loss(now, obs, priors, nxt[0]) <= LOOSE_FACTOR * 0.5 * 3 * obs.n_frames * logN:
                return nxt
        return None

    def run(nxt: tuple[int, tuple[int, ...]], r: np.random.Generator) -> tuple[StickState, float, int]:
        trial = dissolve_stick(cur["st"], obs, priors, nxt[0])
        return run_em(trial, obs, priors, settings, trial_iter, r, stop=out_of_reach(cur["best"], criterion))

    def judge(nxt: tuple[int, tuple[int, ...]], result: tuple[StickState, float, int]) -> bool:
        nonlocal sweeps
        trial, val, n = result
        sweeps += n
        score = criterion(trial, val)
        if score <= cur["best"]:
            return False
        cur.update(st=trial, value=val, best=score)
        done.append([int(p) for p in nxt[1]])
        return True

    greedy_trials(propose, run, judge, rng, parallel=settings.n_jobs > 1)
    return cur["st"], cur["value"], sweeps, done


def heldout_dissolve(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
                     value: float, max_points: int, fraction: float, trial_iter: int | None = None,
                     margin: float = 0.1, n_masks: int = 1, scope: str = "all", free_points: int | None = None,
                     suspect_ratio: float = SUSPECT_MISFIT) -> tuple[StickState, float, int, list[list[int]], dict]:
    """Dissolutions of small sticks judged by how well the model predicts entries it does not see.

    A 2-point stick in 2D fits any two trajectories whose distance stays below its
    3D length (the depth takes up the rest), so no criterion made of the fit's
    likelihood can reject one that pairs markers across a body: on CMU 85_02 the
    model scores such a structure 20 000-30 000 BIC units above the body's own
    segments. Hide one of its points, though, and the other point and its joints
    (which a cross-body stick has no reason to keep) do not place it: that point is
    predicted hundreds of millimetres off
    (docs/em.md section 11). So each stick of at most ``max_points`` points
    (the worst predicted first, each point set once) is dissolved (:func:`dissolve_stick`, then an
    EM run of ``trial_iter`` sweeps) and the result kept when it predicts better, by
    more than ``margin`` (relative squared error), both the points concerned (the
    stick's and those of the sticks that take them) and the stick's own points. The
    other points' errors move with the EM re-run only, and on a scene with a few
    badly predicted points that noise would decide; and the near set alone can
    improve through that re-run while the stick's own points get worse (on CMU
    85_02, isometric view, a pelvis and a shin stick: 1.07 -> 2.03 and 0.97 -> 1.21
    on their own points, docs/em.md section 6), which is no evidence against the
    stick. The held-out error (:func:`impute.heldout_error`) hides the same
    ``fraction`` of the observed entries in every comparison, as occlusions hide them
    (:func:`stickfigure.synthetic.occlude`: a sweeping bar, then random drop-outs, half
    each), and predicts them from the rest with the structure fixed, as imputation does.
    With ``n_masks`` > 1 it is summed over that many independent masks, drawn from
    ``rng`` in turn: with one, which dissolutions are kept depends on where its bar
    falls (on the whole CMU take, seeds 0-3 of one camera gave four different skeletons
    from the same search), at ``n_masks`` times the cost of the predictions.
    With ``scope="leaves"`` only sticks with at most one joint are tried (as in
    :func:`dissolve_small_sticks`).
    With ``free_points`` (< ``max_points``) a stick of more than ``free_points`` points
    is tried only while its fit is suspect (:func:`misfit_ratios` above
    ``suspect_ratio``, as in :func:`resplit_pairs`): a 2-point stick fits any two
    2D trajectories, so only prediction can judge it, but three points give 6
    coordinates a frame for 5 pose parameters, and a 3-point stick that fits them at
    the noise level is left to the likelihood (:func:`dissolve_small_sticks`).
    Prediction is biased against such sticks (a shin, a foot, the pelvis): all three
    points hidden by the bar, a larger neighbour predicts them better than the
    stick's interpolated rotation. The ratio is no test of rigidity for 3 points
    (true rigid 3-point parts of random figures measured 0.5-7.7), only a sign of
    it: the sticks that fit well are spared, the rest offered (docs/em.md sections 6
    and 11).
    The masks are drawn from ``rng``; the trials are greedy
    (:func:`.trials.greedy_trials`: each draws from its own generator spawned from
    ``rng``; with ``settings.n_jobs`` > 1 the trial that follows a loss runs beside
    the current one).

    Returns the state, its objective, the EM sweeps run, the point sets of the
    dissolved sticks, and ``{"fraction", "error_before", "error_after"}`` (RMS per
    hidden coordinate, normalised units; None when no stick is small enough to try).
    """
    from .impute import heldout_error
    from .structure import run_em
    from .trials import greedy_trials

    n_masks = check_positive(n_masks, "n_masks", integer=True)
    if not np.any(st.stick_sizes() <= max_points):  # nothing to try
        return st, value, 0, [], {"fraction": float(fraction), "error_before": None, "error_after": None}
    # Hidden as occlusions are (synthetic.occlude: a sweeping bar, then random drop-outs, half
    # the fraction each): with entries hidden one at a time, a stick's rotation is interpolated
    # across one-frame gaps, which predicts well whatever the structure; a bar hides runs of
    # frames and neighbouring points together, where only the structure can predict them.
    xy = np.where(obs.mask[..., None] > 0, obs.w, np.nan)
    masks = [occlude(Trajectories(xy), seed=rng, bar_fraction=0.5 * fraction, random_fraction=0.5 * fraction)[1]
             for _ in range(n_masks)]
    n_hid = sum(h.sum(axis=1) for h in masks)  # (P,) hidden entries per point, all masks
    n_hidden = max(int(n_hid.sum()) * obs.n_dims, 1)
    trial_iter = settings.n_iter if trial_iter is None else trial_iter

    def errors(state: StickState) -> np.ndarray:  # (P,) summed over the masks
        return sum(heldout_error(state, obs, priors, settings, h) for h in masks)

    err = first = errors(st)
    cur = {"st": st, "value": value, "err": err}
    done: list[list[int]] = []
    sweeps = 0

    def propose(tried: set) -> tuple[int, tuple[int, ...]] | None:
        now, err = cur["st"], cur["err"]
        if now.n_sticks <= 1:
            return None
        # The worst-predicted stick first: a stick that pairs markers across the body also
        # spoils the prediction of the sticks jointed to it, which may be right.
        worst = np.bincount(now.labels, weights=err, minlength=now.n_sticks) / np.maximum(
            np.bincount(now.labels, weights=n_hid, minlength=now.n_sticks), 1)
        order = np.argsort(-worst, kind="stable")
        if free_points is not None and free_points < max_points:
            fits = (now.stick_sizes() <= free_points) | (misfit_ratios(now, obs, priors) > suspect_ratio)
            order = order[fits[order]]
        return _next_small_stick(now, order, max_points, tried, scope)

    def run(nxt: tuple[int, tuple[int, ...]], r: np.random.Generator) -> tuple[StickState, float, int, np.ndarray]:
        trial = dissolve_stick(cur["st"], obs, priors, nxt[0])
        trial, val, n = run_em(trial, obs, priors, settings, trial_iter, r)
        return trial, val, n, errors(trial)

    def judge(nxt: tuple[int, tuple[int, ...]], result: tuple[StickState, float, int, np.ndarray]) -> bool:
        nonlocal sweeps
        trial, val, n, e = result
        sweeps += n
        err = cur["err"]
        pts = np.array(nxt[1])
        near = np.isin(trial.labels, trial.labels[pts]) | np.isin(np.arange(obs.n_points), pts)
        # Both the stick's own points and the near set must be predicted better: a small
        # true segment (a shin, the pelvis) whose own points its dissolution predicts worse
        # can still lower the near set's error through the EM re-run of the sticks taking
        # them, and that is no evidence against the stick. (A stick none of whose entries the
        # masks hid is therefore kept: nothing measures it.)
        if not (e[near].sum() < (1.0 - margin) * err[near].sum()
                and e[pts].sum() < (1.0 - margin) * err[pts].sum()):
            return False
        cur.update(st=trial, value=val, err=e)
        done.append([int(p) for p in nxt[1]])
        return True

    greedy_trials(propose, run, judge, rng, parallel=settings.n_jobs > 1)
    st, value, err = cur["st"], cur["value"], cur["err"]
    info = {"fraction": float(fraction), "error_before": float(np.sqrt(first.sum() / n_hidden)),
            "error_after": float(np.sqrt(err.sum() / n_hidden))}
    return st, value, sweeps, done, info


def articulated_split_round(st: StickState, obs: Observations, priors: Priors, settings,
                            rng: np.random.Generator, min_points: int = 0
                            ) -> tuple[StickState, float | None, int, list[int]]:
    """One round of articulated splits: candidates, the splits put in, an EM run.

    The rounds after the first EM run (``articulated_rounds``) and the round after
    the held-out check's dissolutions (``split_dissolved``) are this step. Only
    sticks of at least ``min_points`` points with a free endpoint are tested
    (:func:`articulated_split_candidates` with the others skipped):
    :func:`apply_articulated_splits` has nowhere to hang the new piece of a stick
    whose endpoints are all on joints (on the CMU side view, the thorax stick
    holding RTHI, jointed to the pelvis, the head and the right arm).

    After a dissolution (``min_points`` = ``split_dissolved``): a dissolved stick's
    points go to the sticks that explain them best with the motions fixed, and a
    limb segment of two markers (a thigh: LTHI and LKNE on the CMU set) can end up
    on a larger stick it is jointed to (the pelvis, the thorax). That stick is then
    two parts, and the segment below the dissolved one (the shin) has no stick it
    can hinge on: the resumed search (``remerge``) and ``join_trees`` re-attach it
    by its best-scoring merge, which on CMU 85_02 was the left upper arm or a foot
    (docs/em.md section 11). The split test re-creates the segment where the fit
    asks for it. Smaller sticks are left alone there, and there is one round only:
    splitting them re-creates the 1-2 point sticks the check has just removed (with
    every stick and all rounds, the CMU isometric view went from 12 to 19 sticks).

    Returns the state, its objective after an EM run of ``settings.n_iter``
    sweeps (None when nothing was split), the sweeps run and the split sticks.
    """
    from .structure import run_em

    sizes = st.stick_sizes()
    skip = set(np.flatnonzero((sizes < min_points) | ~free_end_sticks(st)).tolist())
    splits = articulated_split_candidates(st, obs, priors, n_axes=settings.split_axes, skip=skip,
                                          n_jobs=settings.n_jobs)
    if not splits:
        return st, None, 0, []
    new = apply_articulated_splits(st, obs, priors, splits)
    new, val, sweeps = run_em(new, obs, priors, settings, settings.n_iter, rng)
    return new, val, sweeps, [int(s) for s, _ in splits]


def split_hubs(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
               value: float, criterion: Callable[[StickState, float], float]
               ) -> tuple[StickState, float, int, list[int]]:
    """Articulated splits of sticks whose endpoints are all on joints, each kept when ``criterion`` improves.

    :func:`articulated_split_round` leaves such a stick alone: its new piece has no
    free endpoint to hang on. On CMU walks the torso is often one stick of pelvis and
    thorax markers (they move nearly as one) holding both hips and the shoulders. The
    pelvis turns against the thorax in every stride, so the stick's frame is a
    compromise, and a shoulder joint fixed in it fits worse than one fixed in the
    head, which follows the thorax: the arm ends up on the head (CMU 85_02 from
    32000/6: the joint residual of the upper-arm marker with the torso stick is 640
    times that with the head; docs/em.md section 11).

    Here such a stick is tested as the other sticks are
    (:func:`articulated_split_candidates`), with both pieces of at least
    ``settings.min_stick_points`` points: a piece that takes over joints must be a
    rigid body of its own (a single marker that bends a stick is a bridge's business,
    :mod:`.bridge`). A passing split is put in with each old joint on the piece whose
    points are nearer to it (:func:`apply_articulated_splits`), which is possible
    when at least one joint goes to the new piece; the model is refitted by EM and
    kept when the criterion improves. Candidates are tried once, best gain first.

    Returns the state, its objective, the EM sweeps run and the sticks split
    (numbers of the state each was split in).
    """
    from .structure import out_of_reach, run_em

    m = int(settings.min_stick_points)
    sizes = st.stick_sizes()
    skip = set(np.flatnonzero((sizes < 2 * m) | free_end_sticks(st)).tolist())
    if len(skip) == st.n_sticks:
        return st, value, 0, []
    found = articulated_split_candidates(st, obs, priors, n_axes=settings.split_axes, skip=skip,
                                         n_jobs=settings.n_jobs, min_piece=m, return_gain=True)
    best = criterion(st, value)
    sweeps, done = 0, []
    members = {s: np.flatnonzero(st.labels == s) for s, _, _ in found}
    for s, halves, _ in sorted(found, key=lambda x: -x[2]):
        if not np.array_equal(np.flatnonzero(st.labels == s), members[s]):
            continue  # a kept split's EM run moved points of this stick: its cut is of another stick
        trial = apply_articulated_splits(st, obs, priors, [(s, halves)])
        if trial.n_sticks == st.n_sticks:
            continue  # no joint went to the new piece
        trial, val, n = run_em(trial, obs, priors, settings, settings.n_iter, rng, stop=out_of_reach(best, criterion))
        sweeps += n
        score = criterion(trial, val)
        if score > best:
            st, value, best = trial, val, score
            done.append(int(s))
    return st, value, sweeps, done


# ----------------------------------------------------------------- moving groups of points
def local_noise_variance(obs: Observations, priors: Priors) -> float | None:
    """The data's local noise variance per coordinate, independent of any sticks.

    :func:`geometry.noise_level` squared (the residual of the most rigid small sets
    of neighbouring trajectories), floored as :func:`noise_variance`'s is. None where
    fewer than 5 distinct trajectories admit no rigidity test.
    """
    try:
        sigma = noise_level(np.where(obs.mask[..., None] > 0, obs.w, np.nan))
    except ValueError:  # fewer than rank + 2 distinct trajectories
        return None
    return max(sigma * sigma, 1.0 / priors.max_precision)


def misfit_ratios(st: StickState, obs: Observations, priors: Priors, var: float | None = None) -> np.ndarray:
    """Each stick's residual variance over the robust noise variance, shape (S,).

    The residual variance is corrected for the degrees of freedom of the stick's
    fit (:func:`fit_dof`, as the noise variance is: D translations per frame it is
    seen in, 3 rotation angles where its rotation is fitted rather than
    interpolated, 3 local coordinates per point), the noise variance is
    :func:`noise_variance`'s lower quartile over sticks. A rigid stick fits at
    about 1 (measured on random figures: 0.95-1.34, mostly below 1.15); a stick
    holding points of two parts beside a joint 1.4-3.5, two body segments joined
    in one stick far more. ``var``: another noise variance to compare with (the
    data's local one, :func:`geometry.noise_level` squared).
    """
    rss, var0 = noise_variance(st, obs, priors)
    var = var0 if var is None else var
    dof = fit_dof(st, obs)
    return np.where(dof > 0, rss / (var * np.maximum(dof, 1)), 0.0)


def resplit_pairs(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
                  value: float, criterion: Callable[[StickState, float], float], *,
                  suspect_ratio: float = SUSPECT_MISFIT, max_trials: int | None = None, trial_iter: int | None = None
                  ) -> tuple[StickState, float, int, int]:
    """Moves of groups of points between two jointed sticks: the pair re-split as one stick.

    Two sticks beside a joint that each hold a few of the other's points (the
    clustering's error, kept by the resampling because each motion is a
    compromise fitted to its wrong points too, and by single-point moves for
    the same reason) are undone together: the union of their points is fitted
    as one rigid body (SfM and EM), its best split into two pieces sharing a
    joint is found by :func:`articulated_split_candidates` (planar cuts across
    the major axis of its shape, ``settings.split_axes``; the scene's noise
    level), and when that split differs from the
    current one its points are given to the two sticks (the piece holding more
    of a's points to a), EM re-runs and the change is kept when ``criterion``
    improves. Only pairs with a *suspect* stick are tried (its residual variance,
    corrected for the degrees of freedom of its fit, above ``suspect_ratio``
    times the robust noise variance of :func:`noise_variance`; measured on
    random figures: sticks holding points of two parts 1.4-3.5, clean sticks
    0.95-1.34, mostly below 1.15), the most suspect first, each once per point
    sets, and at most ``max_trials`` (default: the number of sticks) in all.
    The trials are greedy (:func:`.trials.greedy_trials`: each draws from its own
    generator spawned from ``rng``; with ``settings.n_jobs`` > 1 the trial that
    follows a loss runs beside the current one).
    Returns the state, its objective, the EM sweeps run and the points moved.
    """
    from .assign import candidate_fits
    from .structure import out_of_reach, run_em, stick_edges
    from .trials import greedy_trials

    max_trials = st.n_sticks if max_trials is None else max_trials
    trial_iter = settings.n_iter if trial_iter is None else trial_iter
    cur = {"st": st, "value": value, "best": criterion(st, value)}
    sweeps = moved = 0

    def propose(tried: set) -> tuple[int, int] | None:
        now = cur["st"]
        edges, _ = stick_edges(now)
        ratio = misfit_ratios(now, obs, priors)
        # The most suspect pairs first; at most max_trials fits in all (each costs an EM run).
        for a, b in sorted(edges, key=lambda e: -max(ratio[e[0]], ratio[e[1]])):
            if max(ratio[a], ratio[b]) <= suspect_ratio or len(tried) >= max_trials:
                return None
            key = (tuple(np.flatnonzero(now.labels == a)), tuple(np.flatnonzero(now.labels == b)))
            if key not in tried:
                tried.add(key)
                return int(a), int(b)
        return None

    def run(pair: tuple[int, int], r: np.random.Generator) -> tuple[StickState, float, int, int] | None:
        now = cur["st"]
        a, b = pair
        rss, var = noise_variance(now, obs, priors)
        ia, ib = np.flatnonzero(now.labels == a), np.flatnonzero(now.labels == b)
        U = np.concatenate([ia, ib])
        sub = obs.take(U)
        one = initial_state(sub, np.zeros(U.size, np.int64), 1, priors, r, n_ends=2)
        for it in range(60):
            em_sweep(one, sub, priors, global_rotations=it % 10 == 0, use_polar=it == 0)
        splits = articulated_split_candidates(one, sub, priors, var=var, return_gain=True,
                                              n_axes=settings.split_axes)
        if not splits:
            return None
        second = splits[0][1].astype(bool)
        # The cut must fit the pair's points better than the two sticks do now (cheap test
        # before the EM run): the union's one-body residual less the split's gain.
        one_rss = float(one.design(sub).residual_sq(one.rot, one.trans, one.local)[0])
        if one_rss - 2.0 * var * splits[0][2] >= rss[a] + rss[b]:
            return None
        in_a = np.isin(U, ia)
        if (second & in_a).sum() > (~second & in_a).sum():
            second = ~second
        if set(U[second].tolist()) == set(ib.tolist()):
            return None
        trial = now.copy()
        trial.labels[U[~second]] = a
        trial.labels[U[second]] = b
        pts = U[trial.labels[U] != now.labels[U]]
        loc, _ = candidate_fits(now, obs, priors)
        trial.local[pts] = loc[pts, trial.labels[pts]]
        # The motions and joints first settle to the new point sets (a resampling right away
        # would hand the points back to the old compromise motions) and are compared with the
        # current model after as many sweeps; only a promising cut gets the usual run.
        trial, _, n0 = run_em(trial, obs, priors, settings, 2 * settings.n_iter_merge, r, resample=False)
        trial, val, n = run_em(trial, obs, priors, settings, trial_iter, r, stop=out_of_reach(cur["best"], criterion))
        return trial, val, n0 + n, int(pts.size)

    def judge(pair: tuple[int, int], result: tuple[StickState, float, int, int] | None) -> bool:
        nonlocal sweeps, moved
        if result is None:
            return False
        trial, val, n, n_moved = result
        sweeps += n
        U = np.flatnonzero(np.isin(cur["st"].labels, pair))
        score = criterion(trial, val)
        # Kept only when points really moved (not for the objective's slow creep alone).
        if score <= cur["best"] or not np.any(trial.labels[U] != cur["st"].labels[U]):
            return False
        cur.update(st=trial, value=val, best=score)
        moved += n_moved
        return True

    greedy_trials(propose, run, judge, rng, parallel=settings.n_jobs > 1)
    return cur["st"], cur["value"], sweeps, moved
