"""Initialisation of the stick model (section 4.1, last paragraph).

* Motions and local coordinates: structure from motion independently for each
  stick (:func:`stickfigure.geometry.affine_factorization` followed by
  :func:`~stickfigure.geometry.metric_upgrade`, which gives rotations with
  orthonormal rows; the per-frame scale, mean 1, is dropped because the model is
  orthographic).
* Vertices and endpoints, with the fully disconnected structure (J = 2S, one
  vertex per endpoint), in one of two ways (``endpoint_init``):

  ``"centroid"`` (the paper): every vertex of stick s starts at the average of
      the stick's observed points in each frame, the endpoints coincide with their
      vertices and ``k_i`` is the average back-projection
      ``1/F sum_f R^T (mu(e_i^f) - t)``. Both endpoints of a stick then start at
      the same place (its centroid).
  ``"axis"`` (default): the two endpoints start at the two ends of the stick,
      the extreme projections of its points onto the principal axis of its local
      shape; endpoints and vertices start at their predicted positions
      ``R k + t``. A joint usually lies near one end of a stick, so merges start
      closer to where they will settle; with the joint-aware merge
      initialisation (``merge_init="joint"``, structure.py) the choice matters
      little, with the paper's ``"mean"`` merge it matters more (docs/em.md).

* Precisions: tau_w from the SfM residual; tau_m and the prior mean of every
  phi_j equal to tau_w (endpoints are as reliable as observations); tau_t from
  the frame-to-frame motion of the initial vertices.
"""

from __future__ import annotations

import numpy as np

from ...geometry import affine_factorization, fill_gaps, metric_upgrade
from .model import Ghosts, Observations, Priors, StickState, chain_degree

__all__ = ["stick_sfm", "initial_state", "end_positions"]


def interpolate_rotations(R: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Rotations (F, D, 3) kept where ``good``, spherically interpolated in between (held at the ends).

    (Frames after the last good one take its rotation; the copy this replaces gave
    them the rotation of the last but one.)
    """
    from .updates import complete_rotation, quat_to_rot, rot_to_quat, slerp_fill

    F, D, _ = R.shape
    if good.all() or not good.any():
        return R
    # Only the good frames' rotations are read (the others may be unset, all zero).
    q = np.zeros((F, 4))
    q[good] = rot_to_quat(complete_rotation(R[good]))
    return quat_to_rot(slerp_fill(q, good))[:, :D, :]


def _translations(w: np.ndarray, m: np.ndarray, R: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Least-squares t_f = mean over visible points of (w - R l); interpolated where none is visible.

    w (n, F, D) with 0 where missing, m (n, F), R (F, D, 3), local (n, 3) -> (F, D).
    """
    D = R.shape[1]
    cnt = m.sum(axis=0)
    resid = w - np.einsum("fdk,nk->nfd", R, local)
    t = np.einsum("nfd,nf->fd", resid, m) / np.maximum(cnt, 1)[:, None]
    seen = cnt > 0
    if seen.any() and not seen.all():
        si = np.flatnonzero(seen)
        for d in range(D):
            t[~seen, d] = np.interp(np.flatnonzero(~seen), si, t[si, d])
    return t


def _fit_local(w: np.ndarray, m: np.ndarray, R: np.ndarray, t: np.ndarray, ridge: float = 1e-6) -> np.ndarray:
    """Least-squares local coordinates of each point from its *observed* entries, shape (n, 3).

    ``(sum_f o R^T R + ridge I) l = sum_f o R^T (w - t)``: the L update with the
    observations alone (a tiny ridge keeps unobservable directions at 0).
    """
    RtR = np.swapaxes(R, -1, -2) @ R  # (F, 3, 3)
    H = np.einsum("nf,fab->nab", m, RtR) + ridge * np.eye(3)
    rhs = np.einsum("nf,fdk,nfd->nk", m, R, w - t[None])
    return np.linalg.solve(H, rhs[..., None])[..., 0]


def _rigid_sfm(pts: np.ndarray, rng: np.random.Generator, filled: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Metric SfM of one rigid group (n >= 4 points) with NaN gaps: R (F, D, 3), t (F, D), local (n, 3).

    Missing entries stay out of every fit. Frames where the group shows at least 4
    points determine their affine motion; when such frames are most of them and
    every point is seen in one of them, the factorisation (Wiberg, the gaps left
    out) runs on those frames alone, and the others get rotations interpolated
    between them and translations fitted to their visible points (a frame with
    fewer than 4 points leaves its affine motion undetermined, and a garbage one
    would corrupt the metric upgrade of all frames). Otherwise (sparse data:
    frames rarely show 4 points) the factorisation runs on the trajectories
    with their gaps filled, and the local coordinates and translations are then
    re-fitted to the observed entries only. The gaps are interpolated in time
    (:func:`fill_gaps`); where ``filled`` (n, F, D; the whole scene's completion,
    :attr:`Observations.filled`) is given, both fills are factorised and the start
    with the lower residual on the observed entries is kept.
    """
    n, F, D = pts.shape
    obs = ~np.isnan(pts[..., 0])
    m = obs.astype(float)
    w = np.where(obs[..., None], pts, 0.0)
    cnt = obs.sum(axis=0)
    good = cnt >= 4
    if obs.all():
        fac = affine_factorization(pts, rank=3, random_state=rng)
        R, _, t, shape = metric_upgrade(fac.motions, fac.shape)
        return R, t, shape
    interpolated = fill_gaps(pts)
    if good.sum() >= max(3, 0.5 * F) and obs[:, good].any(axis=1).all():
        fac = affine_factorization(pts[:, good], rank=3, random_state=rng)
        Rg, _, _, local = metric_upgrade(fac.motions, fac.shape)
        R = np.zeros((F, D, 3))
        R[good] = Rg
        R = interpolate_rotations(R, good)
        local = _bound_spread(local, interpolated if filled is None else filled)
        return R, _translations(w, m, R, local), local
    # With the scene's completion given, the stick's own interpolated trajectories are a
    # second start, and the one that fits the observed entries better is kept: the
    # completion's smoothness is chosen for the whole scene, and for one stick it can be
    # wrong (a 5-point stick started 50 times worse from one held-out draw's choice than
    # from the others'; after 200 EM sweeps alone still 5 times). The start's fit predicts
    # the fit EM reaches from it (docs/em.md section 5).
    best: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None
    for fill in [interpolated] if filled is None else [filled, interpolated]:
        fac = affine_factorization(fill, rank=3, random_state=rng)
        R, _, t, _ = metric_upgrade(fac.motions, fac.shape)
        local = _bound_spread(_fit_local(w, m, R, t), fill)
        t = _translations(w, m, R, local)
        rss = float(np.sum(m[..., None] * (w - np.einsum("fdk,nk->nfd", R, local) - t[None]) ** 2))
        if best is None or rss < best[0]:
            best = (rss, R, t, local)
    assert best is not None
    return best[1], best[2], best[3]


#: A group's 3D principal spreads are capped at this multiple of its largest 2D spread over frames.
MAX_DEPTH_RATIO = 2.0


def _bound_spread(local: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Local shape (n, 3) with every principal spread at most ``MAX_DEPTH_RATIO`` times the
    largest RMS radius the group shows in any frame of ``xy`` (n, F, D), complete.

    A rigid body's spread along an axis is at most its 2D RMS radius in a frame where that
    axis lies in the image plane; a spread far beyond every frame's radius is one the
    motion never revealed. With sparse data the metric upgrade can return such axes
    hundreds of scene sizes long (a near-singular metric matrix), and a stick that long
    fits its projections by foreshortening, so EM keeps it: the cap keeps the start in
    the region of real shapes (applied to groups with missing entries only).
    """
    c = local.mean(axis=0)
    X = local - c
    lam, V = np.linalg.eigh(X.T @ X / max(local.shape[0], 1))
    spread = np.sqrt(np.maximum(lam, 0.0))
    r2 = np.sqrt(np.max(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=-1), axis=0)))
    cap = MAX_DEPTH_RATIO * r2
    if not np.isfinite(cap) or np.all(spread <= cap):
        return local
    f = np.where(spread > cap, cap / np.maximum(spread, 1e-300), 1.0)
    return c + X @ V @ np.diag(f) @ V.T


def stick_sfm(obs: Observations, labels: np.ndarray, n_sticks: int, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-stick orthographic structure from motion (missing entries left out, see :func:`_rigid_sfm`).

    Returns
    -------
    rot : (S, F, D, 3), trans : (S, F, D), local : (P, 3)
    """
    P, F, D = obs.w.shape
    rot = np.zeros((n_sticks, F, D, 3))
    rot[:, :, :, :D] = np.eye(D)
    trans = np.zeros((n_sticks, F, D))
    local = np.zeros((P, 3))
    xy = np.where(obs.mask[..., None] > 0, obs.w, np.nan)
    for s in range(n_sticks):  # one factorisation per stick (frames are vectorised inside)
        idx = np.flatnonzero(labels == s)
        if idx.size == 0:
            continue
        pts = xy[idx]
        m = obs.mask[idx]
        if idx.size >= 4:
            rot[s], trans[s], local[idx] = _rigid_sfm(pts, rng, None if obs.filled is None else obs.filled[idx])
            continue
        # Too few points for a rank-3 factorisation: a flat shape seen face-on, translations
        # from the visible centroid (held over frames where none is visible); EM refines it.
        # Offsets and translations jointly (w_pf = off_p + t_f by alternating least squares on
        # the visible entries): the centroid of whichever points a frame shows is not the
        # group's centroid when some are missing.
        w = np.where(m[..., None] > 0, pts, 0.0)
        off = np.zeros((idx.size, D))
        R0 = np.zeros((F, D, 3))
        R0[:, :, :D] = np.eye(D)
        for _ in range(1 if m.all() else 20):
            t = _translations(w, m, R0, np.pad(off, ((0, 0), (0, 3 - D))))
            off = np.einsum("nfd,nf->nd", w - t[None], m) / np.maximum(m.sum(axis=1), 1)[:, None]
        trans[s] = _translations(w, m, R0, np.pad(off, ((0, 0), (0, 3 - D))))
        local[idx, :D] = off
    return rot, trans, local


def end_positions(local: np.ndarray, labels: np.ndarray, n_sticks: int, n_ends: int = 2) -> np.ndarray:
    """Endpoints spread evenly along the principal axis of each stick's local shape, shape (E S, 3).

    The first two sit at the extreme projections of the stick's points (its two
    ends); further ones (``n_ends > 2``) at evenly spaced interior positions.
    """
    E = n_ends
    ends = np.zeros((E * n_sticks, 3))
    frac = np.concatenate([[0.0, 1.0], np.arange(1, E - 1) / (E - 1)])[:E]
    for s in range(n_sticks):
        L = local[labels == s]
        if L.shape[0] == 0:
            continue
        c = L.mean(axis=0)
        if L.shape[0] == 1:
            ends[E * s:E * (s + 1)] = c
            continue
        _, _, Vt = np.linalg.svd(L - c, full_matrices=False)
        u = Vt[0]
        proj = (L - c) @ u
        lo, hi = proj.min(), proj.max()
        ends[E * s:E * (s + 1)] = c + (lo + frac[:, None] * (hi - lo)) * u
    return ends


def initial_state(obs: Observations, labels: np.ndarray, n_sticks: int, priors: Priors,
                  rng: np.random.Generator, *, endpoint_init: str = "axis", n_ends: int = 2) -> StickState:
    """The fully disconnected model (J = 2S) started from per-stick SfM.

    Parameters
    ----------
    obs : Observations
    labels : ndarray of int, shape (P,)
        Initial stick of every point (no empty sticks).
    n_sticks : int
    priors : Priors
    rng : numpy Generator
    endpoint_init : {"axis", "centroid"}
    n_ends : int
        Endpoints per stick (2 in the paper).
    """
    P, F, D = obs.w.shape
    S, E = n_sticks, int(n_ends)
    if E < 2:
        raise ValueError(f"n_ends must be >= 2, got {n_ends}")
    rot, trans, local = stick_sfm(obs, labels, S, rng)
    J = E * S
    st = StickState(labels=labels.copy(), vertex_of=np.arange(J), rot=rot, trans=trans, local=local,
                    ends=np.zeros((J, 3)), mu_e=np.zeros((J, F, D)), tau_e=np.ones(J),
                    mu_v=np.zeros((J, F, D)), tau_v=np.ones((J, F)), alpha=np.ones(J),
                    beta=np.ones(J), tau_w=1.0, tau_m=1.0, tau_t=1.0)
    res = (obs.w - st.point_predictions()) * obs.mask[..., None]
    st.tau_w = float(min(D * obs.mask.sum() / max(np.sum(res * res), 1e-300), priors.max_precision))
    st.tau_m = st.tau_w
    if endpoint_init == "axis":
        st.ends = end_positions(local, labels, S, E)
        st.mu_e = st.end_predictions()
    elif endpoint_init == "centroid":
        sums = st.design(obs).s_w  # (S, F, D)
        cnt = st.design(obs).n  # (S, F)
        cen_local = st.design(obs).stick_sum(local) / np.maximum(np.bincount(labels, minlength=S), 1)[:, None]
        pred = np.einsum("sfdk,sk->sfd", rot, cen_local) + trans
        # The average of the observations where the stick shows all its points; where some are
        # missing, the average of the visible ones is not the stick's centroid: its prediction is.
        full = cnt >= np.bincount(labels, minlength=S)[:, None]
        avg = np.where(full[..., None], sums / np.maximum(cnt, 1)[..., None], pred)
        st.mu_e = np.repeat(avg, E, axis=0)
        k = np.einsum("sfdk,sfd->sk", rot, avg - trans) / F
        st.ends = np.repeat(k, E, axis=0)
    else:
        raise ValueError(f"endpoint_init must be 'axis' or 'centroid', got {endpoint_init!r}")
    st.mu_v = st.mu_e.copy()
    if F > 1:
        dmu = np.diff(st.mu_v, axis=1)
        st.tau_t = float(min(D * J * (F - 1) / max(np.sum(dmu * dmu), 1e-300), priors.max_precision))
    st.alpha = priors.alpha0 + 0.5 * D * F * np.ones(J)
    st.beta = st.alpha / st.tau_w
    a = st.alpha / st.beta
    st.tau_e = st.tau_m + a[st.vertex_of]
    st.tau_v = a[:, None] + st.tau_t * chain_degree(F)[None, :]
    st.ghosts = None
    return st


def empty_ghosts(st: StickState) -> Ghosts:
    return Ghosts.empty(st.n_vertices, st.n_frames, st.n_dims)
