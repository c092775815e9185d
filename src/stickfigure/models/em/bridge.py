"""Bridges: a point that bends its stick becomes a stick of its own, inserted into a joint.

A body segment can carry one marker away from its joints: CMU's thigh is THI + KNE,
and the knee marker, on the joint, usually goes with the shin. The thigh marker left
over fits no stick rigidly, and a stick of its own, one point with a free rotation in
every frame, has more parameters than observations while it hangs free, so neither the
resampling of assignments (which dissolves free sticks of fewer than
``min_stick_points``) nor any split keeps it. It lands on some stick, often the thorax,
and that stick bends to follow it: a point far from a stick's other markers is a lever,
and small 3D turns of the stick move it far in the image, at the cost of the stick's
own markers (docs/em.md section 11: on the CMU side view RTHI fits its thorax stick to
15.7 mm while the thorax's own STRN is at 15.1 mm, against 5-7 mm for other sticks).

Placed between two sticks, the same single point is well determined: its stick's two
endpoints share vertices with its neighbours, so per frame its 3 rotation angles and
D translations meet D coordinates of its point and 2 D of its joints. The greedy
search cannot get there, because it never undoes a merge and never has the 1-point
stick to join. :func:`bridge_points` makes the move directly:

1. *Screen* (:func:`lever_points`). For every stick ``c`` and point ``p`` on it, ``c``
   without ``p`` is refitted alone (all such blocks batched in one EM run, precisions
   fixed, at most ``max_frames`` evenly spaced frames). The *excess*
   ``(RSS_c - rss_p - RSS_{c-p}) / (2 sigma^2)`` is what the stick's *other* points
   gain without ``p`` (``rss_p``: ``p``'s own residual on ``c``). A point of a rigid
   stick gains them about nothing (at most 2.5 per frame on the human-sized random
   figure seed 0, 1.6 per frame on CMU 85_02 from 62.1/13.8 degrees, a body tree; the
   block refit is free of the joints, which alone gains a little); the thigh marker
   on the thorax stick of CMU 85_02 seen from 303.5/13.4 degrees gains them 26 per
   frame (the next point 6.9). A point is a candidate when its excess exceeds half
   the BIC charge of a new stick, ``(3 F + 9) log(N) / 4``; the other half is left to
   the joints the bridge makes rigid, which the screen does not see.
2. *Trials.* For the best candidate ``p``, each endpoint ``e`` of another stick ``b``
   on one of the two joints nearest to ``p`` (the vertex trajectory closest to
   ``p``'s, RMS over its observed frames) gives a trial: ``p`` goes into that joint
   between ``b`` and the sticks still on it. ``e`` is detached from the joint
   (:func:`.tree.detach_endpoint`), a new stick holding ``p`` starts at ``b``'s motion
   with one endpoint on ``e``'s new vertex and its other endpoints free, and the merges
   of a free endpoint of the new stick with the endpoints still on that joint are scored
   as in the search (:func:`.structure.score_candidates`); the best is performed and EM
   re-run. The number of sticks grows by one and of trees stays the same. Linking the
   new stick anywhere in the part ``b`` was cut from (the first version) put it where
   a loose joint fitted worst: on CMU 85_02 from 128.4/24.6 degrees RUPA, bridged at the
   right forearm's joint, was linked to the hip stick RFWT+RTHI (a body tree lost; with
   the link into the joint, a body tree). Linking it to a free endpoint of a stick on
   that joint (the second version) made a new joint elsewhere: on CMU 85_02 from 131/6
   degrees RUPA, bridged at the right forearm's joint, was hung on a free end of the
   head, a stick on that joint (a body tree lost; into the joint, a body tree).
3. The best trial is kept when the selection criterion (BIC or the objective)
   improves; then the screen runs again on the new model, up to ``max_points``
   kept bridges. A candidate whose trials all lose is not proposed again.

Measured on that view (an outside prototype of the first version on the final model,
all 810 frames): every one of five trials (two joints, both ends) raised BIC, by 20548
to 35969, and each gave a body tree; the best bridged LTHI between the pelvis and the
left shin.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from .model import Ghosts, Observations, Priors, StickState
from .updates import em_sweep, update_endpoints

__all__ = ["bridge_points", "bridge_threshold", "insert_bridge", "lever_points", "split_pair", "unpair_hubs",
           "vertex_distances"]


def lever_points(st: StickState, obs: Observations, priors: Priors, *, min_points: int = 3,
                 n_sweeps: int = 40, max_frames: int = 240) -> list[tuple[float, int, int]]:
    """Points whose removal lets the rest of their stick fit much better.

    Parameters
    ----------
    st : StickState
    obs : Observations, shape (P, F, D)
    priors : Priors
    min_points : int
        A stick left free (no joint) must keep at least this many points, else the
        resampling would dissolve it.
    n_sweeps, max_frames : int
        The refit of every stick without one of its points: EM sweeps, and at most
        this many evenly spaced frames.

    Returns
    -------
    list of (excess, stick, point)
        Every candidate (stick, point) with its excess in units of ``2 sigma^2``
        over all frames (module docstring), largest first. Only those above the
        screen's threshold (:func:`bridge_threshold`) are worth a trial.
    """
    from .initialise import end_positions
    from .refine import _frames, noise_variance
    from .structure import _union

    _, var = noise_variance(st, obs, priors)
    F, D = obs.n_frames, obs.n_dims
    E = st.ends_per_stick
    frames = np.arange(F) if F <= max_frames else np.unique(np.linspace(0, F - 1, max_frames).round().astype(int))
    Fs = frames.size
    sub = _frames(st, frames)
    sobs = obs.take_frames(frames)
    stick_rss = sub.design(sobs).residual_sq(sub.rot, sub.trans, sub.local)
    res = (sobs.w - sub.point_predictions()) * sobs.mask[..., None]
    point_rss = np.sum(res * res, axis=(1, 2))
    jointed = st.joints_per_stick() > 0
    blocks, who = [], []
    for c in range(st.n_sticks):
        idx = np.flatnonzero(st.labels == c)
        if idx.size < 2 or (not jointed[c] and idx.size - 1 < min_points):
            continue
        for p in idx:
            keep = idx[idx != p]
            # The rest as one free stick from the stick's own motion and shape.
            ends = np.asarray(end_positions(st.local[keep], np.zeros(keep.size, np.int64), 1, E), float)
            blk = StickState(labels=np.zeros(keep.size, np.int64), vertex_of=np.arange(E),
                             rot=sub.rot[c:c + 1].copy(), trans=sub.trans[c:c + 1].copy(),
                             local=st.local[keep].copy(), ends=ends, mu_e=np.zeros((E, Fs, D)), tau_e=np.ones(E),
                             mu_v=np.zeros((E, Fs, D)), tau_v=np.ones((E, Fs)), alpha=np.ones(E),
                             beta=np.ones(E), tau_w=st.tau_w, tau_m=st.tau_m, tau_t=st.tau_t,
                             ghosts=Ghosts.empty(E, Fs, D))
            blk.mu_e = blk.end_predictions()
            blk.mu_v = blk.mu_e.copy()
            blocks.append((blk, sobs.take(keep)))
            who.append((c, int(p)))
    if not blocks:
        return []
    u, uobs, _, _ = _union(blocks)
    for it in range(n_sweeps):
        em_sweep(u, uobs, priors, precisions=False, global_rotations=it % 10 == 0, use_polar=False)
    rest = u.design(uobs).residual_sq(u.rot, u.trans, u.local)
    out = [(float((stick_rss[c] - point_rss[p] - r) * (F / Fs) / (2.0 * var)), c, p)
           for (c, p), r in zip(who, rest)]
    out.sort(key=lambda x: (-x[0], x[2]))
    return out


def bridge_threshold(obs: Observations) -> float:
    """The screen's threshold: half the BIC charge of a 1-point stick in two joints,
    ``(3 F + 9) log(N) / 4`` (3 rotation angles a frame, 3 local coordinates of its
    point and of each of its two jointed endpoints; ``N`` observed coordinates)."""
    N = float(obs.mask.sum() * obs.n_dims)
    return 0.25 * (3.0 * obs.n_frames + 9.0) * np.log(max(N, 2.0))


def vertex_distances(st: StickState, obs: Observations, vertices: np.ndarray, p: int) -> np.ndarray:
    """Mean squared distance of each vertex's trajectory from point ``p``'s over ``p``'s observed
    frames, shape (len(vertices),)."""
    m = obs.mask[p]
    d = np.sum(m[None, :] * np.sum((st.mu_v[vertices] - obs.w[p][None]) ** 2, axis=2), axis=1)
    return d / max(m.sum(), 1.0)


def _nearest_joints(st: StickState, obs: Observations, p: int, n: int) -> np.ndarray:
    """The ``n`` joints (vertices of two or more endpoints) whose trajectories are nearest point ``p``'s."""
    joints = np.flatnonzero(st.vertex_counts() >= 2)
    return joints[np.argsort(vertex_distances(st, obs, joints, p), kind="stable")[:n]]


def _with_new_stick(cut: StickState, priors: Priors, point: int, like: int, ends: list,
                    joined: list[int], local: np.ndarray | None = None) -> StickState:
    """``cut`` plus a new stick (the last) holding ``point``, at stick ``like``'s motion.

    ``ends``: the new stick's E endpoints in its local frame; the first ``len(joined)`` go
    on the vertices ``joined``, the others on new free vertices, which start at their
    endpoint's prediction (as in initial_state). ``local``: ``point``'s local
    coordinates in the new stick (default: those it has).
    """
    from .refine import start_vertices

    E = cut.ends_per_stick
    F, D = cut.n_frames, cut.n_dims
    S, J = cut.n_sticks, cut.n_vertices
    n_free = E - len(joined)
    out = cut.copy()
    out.labels = cut.labels.copy()
    out.labels[point] = S
    out.local = cut.local.copy()
    if local is not None:
        out.local[point] = local
    out.rot = np.concatenate([cut.rot, cut.rot[like:like + 1]])
    out.trans = np.concatenate([cut.trans, cut.trans[like:like + 1]])
    out.ends = np.concatenate([cut.ends, np.stack(ends)])
    out.vertex_of = np.concatenate([cut.vertex_of, np.asarray(list(joined), np.int64), J + np.arange(n_free)])
    out.mu_v = np.concatenate([cut.mu_v, np.zeros((n_free, F, D))])
    out.tau_v = np.concatenate([cut.tau_v, np.ones((n_free, F))])
    out.alpha = np.concatenate([cut.alpha, np.ones(n_free)])
    out.beta = np.concatenate([cut.beta, np.ones(n_free)])
    if cut.ghosts is not None:
        out.ghosts = cut.ghosts.grown(n_free)
    out._design = None
    out._quat = None
    pred = out.end_predictions()
    out.mu_e = np.concatenate([cut.mu_e, pred[-E:]])
    out.tau_e = np.concatenate([cut.tau_e, np.ones(E)])
    start_vertices(out, np.arange(J, J + n_free), pred, priors)  # the free ones, at their endpoint's prediction
    update_endpoints(out)
    return out


def insert_bridge(st: StickState, obs: Observations, priors: Priors, settings, p: int, e: int,
                  rng: np.random.Generator, stop: Callable | None = None
                  ) -> tuple[StickState, float, int, dict] | None:
    """Point ``p`` as a new stick in endpoint ``e``'s joint, between ``e``'s stick and the others on it.

    Step 2 of the module docstring. Returns the state after EM, its objective, the
    sweeps run and a record ``{"point", "detached", "linked"}`` (stick numbers of
    the new state; the new stick is the last), or None when ``e``'s stick holds one
    point or no merge links the new stick to the joint's other sticks.
    """
    from .assign import candidate_fits
    from .structure import (
        apply_merge,
        merge_candidates,
        run_em,
        score_candidates,
    )
    from .tree import detach_endpoint

    E = st.ends_per_stick
    b = int(e // E)
    if np.count_nonzero(st.labels == b) == 1:
        # e's new vertex would join b and the new stick, both of one point: a joint that ties
        # nothing (StickState.only_one_point_sticks); known before any state is built.
        return None
    loc, _ = candidate_fits(st, obs, priors)
    cut = detach_endpoint(st, e, priors)
    ve = int(cut.vertex_of[e])
    S = cut.n_sticks
    lp = loc[p, b]  # p's best place in b's frame; the new stick starts at b's motion
    k0 = cut.ends[e]
    # One endpoint where b was jointed, the others beyond p from it (free, to be joined).
    # (Any number of endpoints: n_ends has no upper bound.)
    far = [lp + (lp - k0) / (i + 1) for i in range(min(E - 1, 2))]
    far += [lp + np.array([0.0, 0.0, 0.1 * i]) for i in range(1, E - 2)]
    out = _with_new_stick(cut, priors, p, b, [k0] + far, [ve], local=lp)
    # The new stick goes into the joint b left: merges of a free endpoint of it with the
    # endpoints still on that joint (a 1-point stick's two joints constrain each other little,
    # so a link scored anywhere in the tree would go wherever a loose joint fits worst; and a
    # link to another endpoint of a stick on that joint makes a new joint, docs/em.md section 11).
    into = [int(x) for x in np.flatnonzero(st.vertex_of == st.vertex_of[e]) if x != e]
    partners = {x // E for x in into}
    cands = []
    for c in merge_candidates(out, replace(settings, max_candidates=None), out.design(obs).n):
        sticks = {int(x) for x in np.unique(c.ends // E)}
        if S in sticks and sticks - {S} and sticks - {S} <= partners and np.isin(c.ends, into).any():
            cands.append(c)
    if not cands:
        return None
    cands = sorted(cands, key=lambda c: c.residual)[:8]
    blocks = score_candidates(out, obs, priors, settings, cands, rng)
    i = int(np.argmax([c.score for c in cands]))
    linked = sorted({int(x) for x in cands[i].ends // E})
    out = apply_merge(out, cands[i], priors, settings, blocks[i])
    out, val, sweeps = run_em(out, obs, priors, settings, settings.n_iter, rng, stop=stop)
    return out, val, sweeps, {"point": int(p), "detached": b, "linked": linked}


def bridge_points(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
                  value: float, criterion: Callable[[StickState, float], float], max_points: int, *,
                  n_joints: int = 2, max_trials: int = 4) -> tuple[StickState, float, int, list[dict]]:
    """Greedy bridges (module docstring) until no candidate's best trial improves ``criterion``.

    Returns the state, its objective, the EM sweeps run and one record per kept
    bridge (:func:`insert_bridge`). Each trial draws from its own generator
    spawned from ``rng`` in order; with ``settings.n_jobs`` > 1 half of a
    candidate's trials run in a forked child (the same result).
    """
    from .forked import in_halves
    from .structure import child_rng, out_of_reach

    E = st.ends_per_stick
    cur = {"st": st, "value": value, "best": criterion(st, value)}
    kept: list[dict] = []
    tried: set[tuple[int, ...]] = set()
    sweeps = 0
    limit = bridge_threshold(obs)
    screened: tuple[StickState, list[tuple[int, int]]] | None = None
    while len(kept) < max_points:
        now = cur["st"]
        if screened is None or screened[0] is not now:
            # The screen once per model: a candidate whose trials all lost leaves the model as it
            # was, and the screen (a batched EM run, no generator) would give the same list again.
            screened = (now, [(c, p) for x, c, p in lever_points(now, obs, priors,
                                                                  min_points=settings.min_stick_points)
                              if x > limit])
        # A candidate named by its stick's points, so that one whose trials lost is not retried.
        cands = [(c, p) for c, p in screened[1] if (p,) + tuple(np.flatnonzero(now.labels == c)) not in tried]
        if not cands:
            break
        c, p = cands[0]
        tried.add((p,) + tuple(np.flatnonzero(now.labels == c)))
        ends = [int(e) for j in _nearest_joints(now, obs, p, n_joints)
                for e in np.flatnonzero(now.vertex_of == j) if e // E != c][:max_trials]
        gens = [child_rng(rng) for _ in ends]

        def run(items: list, now: StickState = now, p: int = p, best: float = cur["best"]) -> list:
            # A stop of its own per trial: it keeps the history of the run it watches.
            return [insert_bridge(now, obs, priors, settings, p, e, g, out_of_reach(best, criterion))
                    for e, g in items]

        results = in_halves(run, list(zip(ends, gens)), parallel=settings.n_jobs > 1)
        best = None
        for r in results:
            if r is None:
                continue
            sweeps += r[2]
            score = criterion(r[0], r[1])
            if score > cur["best"] and (best is None or score > best[0]):
                best = (score, r)
        if best is None:
            continue
        score, (new, val, _, record) = best
        kept.append(record)
        cur.update(st=new, value=val, best=score)
    return cur["st"], cur["value"], sweeps, kept


# ----------------------------------------------------------------- 2-point hubs
#: A 2-point stick on at least this many joints is tried as two 1-point sticks (:func:`unpair_hubs`).
UNPAIR_MIN_JOINTS = 3


def split_pair(st: StickState, obs: Observations, priors: Priors, c: int) -> StickState | None:
    """Stick ``c`` of two points as two 1-point sticks, each on the joints nearer its point.

    The second point ``q`` moves to a new stick (the last) that starts at ``c``'s
    motion and local coordinates. Each joint of ``c`` goes with the point its vertex
    trajectory is nearer (RMS over the point's observed frames); one that goes with
    ``q`` leaves ``c``'s endpoint (:func:`.tree.detach_endpoint`) for the new
    stick's, at the same local coordinates. The new stick's other endpoints start
    free, beyond ``q`` from its first joint. The tree falls into two parts, which
    the caller joins again. None when one point is nearer every joint.
    """
    from .tree import detach_endpoint

    E = st.ends_per_stick
    idx = np.flatnonzero(st.labels == c)
    if idx.size != 2:
        raise ValueError(f"stick {c} holds {idx.size} points; split_pair takes a stick of two")
    p, q = (int(x) for x in idx)
    cnt = st.vertex_counts()
    jointed = [e for e in range(E * c, E * (c + 1)) if cnt[st.vertex_of[e]] >= 2]
    to_p, to_q = (vertex_distances(st, obs, st.vertex_of[jointed], x) for x in (p, q))
    moved = [e for e, dp, dq in zip(jointed, to_p, to_q) if dq < dp]
    if not moved or len(moved) == len(jointed):
        return None
    cut = st
    for e in moved:
        cut = detach_endpoint(cut, e, priors)
    lq = cut.local[q]
    k0 = cut.ends[moved[0]]
    ends = [cut.ends[e] for e in moved] + [lq + (lq - k0) / (i + 1) for i in range(E - len(moved))]
    out = _with_new_stick(cut, priors, q, c, ends, [int(st.vertex_of[e]) for e in moved])
    return out


def unpair_hubs(st: StickState, obs: Observations, priors: Priors, settings, rng: np.random.Generator,
                value: float, criterion: Callable[[StickState, float], float]
                ) -> tuple[StickState, float, int, list[list[int]]]:
    """Every 2-point stick on ``UNPAIR_MIN_JOINTS`` or more joints tried as two 1-point sticks.

    A body's hubs (pelvis, thorax) carry several markers. Two markers alone on a
    stick that three others hang from are, in every case seen, the one-marker
    segments of two limbs lumped together: CMU's two thigh markers LTHI+RTHI on a
    stick joined to the pelvis and both shins, left over by the first clustering
    and cut off as one piece by the articulated split (its plane cuts keep the two
    together). Such a stick fits its two points exactly (a 2-point stick fits any
    two trajectories), so no screen of point residuals flags it, and the held-out
    check has no better place for either marker. Each such stick is split by
    :func:`split_pair`; the two parts of the tree are joined again by the best
    merge between them, as ``join_trees`` joins a forest (scored as the search
    scores merges), EM is re-run, and the result is kept when ``criterion``
    improves. A 2-point stick on two joints is a segment of a chain (an upper
    arm's LUPA+LELB) and is left alone: splitting those raised BIC too (by
    350-4100 on CMU 85_02, the vertex terms' bias of docs/em.md section 11) and
    only fragmented the segments.
    The trials are greedy (:func:`.trials.greedy_trials`: each draws from its own
    generator spawned from ``rng``; with ``settings.n_jobs`` > 1 the trial that
    follows a loss runs beside the current one).

    Returns the state, its objective, the EM sweeps run and the point pairs split.
    """
    from .structure import components, run_em
    from .tree import join_trees
    from .trials import greedy_trials

    cur = {"st": st, "value": value, "best": criterion(st, value)}
    kept: list[list[int]] = []
    sweeps = 0

    def propose(tried: set) -> tuple[int, tuple[int, ...]] | None:
        now = cur["st"]
        hubs = now.joints_per_stick() >= UNPAIR_MIN_JOINTS
        sizes = now.stick_sizes()
        for c in np.flatnonzero((sizes == 2) & hubs):
            pts = tuple(np.flatnonzero(now.labels == c).tolist())
            if pts not in tried:  # a pair is named by its points, so that one that lost is not retried
                tried.add(pts)
                return int(c), pts
        return None

    def run(key: tuple[int, tuple[int, ...]], r: np.random.Generator) -> tuple[StickState, float, int] | None:
        now = cur["st"]
        new = split_pair(now, obs, priors, key[0])
        if new is None or any(new.only_one_point_sticks(j) for j in np.flatnonzero(new.vertex_counts() >= 2)):
            return None  # (a joint of 1-point sticks ties nothing: StickState.only_one_point_sticks)
        trees = int(components(now)[0].max()) + 1
        new, val, n = run_em(new, obs, priors, settings, settings.n_iter, r)
        new, val, m, _ = join_trees(new, obs, priors, settings, r, val, trees)
        return new, val, n + m

    def judge(key: tuple[int, tuple[int, ...]], result: tuple[StickState, float, int] | None) -> bool:
        nonlocal sweeps
        if result is None:
            return False
        new, val, n = result
        sweeps += n
        score = criterion(new, val)
        if score <= cur["best"]:
            return False
        cur.update(st=new, value=val, best=score)
        kept.append(list(key[1]))
        return True

    greedy_trials(propose, run, judge, rng, parallel=settings.n_jobs > 1)
    return cur["st"], cur["value"], sweeps, kept
