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

from ...geometry import affine_factorization, metric_upgrade
from .model import Ghosts, Observations, Priors, StickState, chain_degree

__all__ = ["stick_sfm", "initial_state", "end_positions"]


def stick_sfm(obs: Observations, labels: np.ndarray, n_sticks: int, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-stick orthographic structure from motion.

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
        cnt = m.sum(axis=0)
        if idx.size >= 4 and np.all(cnt >= 1):
            fac = affine_factorization(pts, rank=3, random_state=rng)
            R, _, t, shape = metric_upgrade(fac.motions, fac.shape)
            rot[s], trans[s], local[idx] = R, t, shape
            continue
        # Too few points for a rank-3 factorisation: a flat shape seen face-on, translations
        # from the visible centroid (held over frames where none is visible); EM refines it.
        cen = np.nansum(pts, axis=0) / np.maximum(cnt, 1)[:, None]  # (F, D)
        seen = np.flatnonzero(cnt > 0)
        nearest = seen[np.clip(np.searchsorted(seen, np.arange(F)), 0, seen.size - 1)]
        trans[s] = cen[nearest]
        off = np.nanmean(pts - trans[s][None], axis=1)  # (n, D)
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
        avg = np.where(cnt[..., None] > 0, sums / np.maximum(cnt, 1)[..., None], pred)
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
