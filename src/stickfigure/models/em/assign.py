"""Resampling the point-to-stick assignments R, and changes of the stick set.

Section 4.2: every ``resample_every`` EM iterations each point draws its stick
from ``P(r_ps) ~ c_s exp(-tau_w/2 sum_f o_pf |w_pf - R_sf l_ps - t_sf|^2)``. A point
has local coordinates only on its own stick, so for every candidate stick the
coordinates ``l_ps`` are fitted first, by the same regularised least squares as
the L update (``(tau_w sum_f o R^T R + tau_p I) l = tau_w sum_f o R^T (w - t)``),
all (point, stick) pairs at once; ``c_s`` is the ML weight ``n_s / P``.
"""

from __future__ import annotations

import numpy as np

from .model import Observations, Priors, StickState

__all__ = ["candidate_fits", "resample_assignments", "remove_sticks", "stick_is_free"]


def candidate_fits(st: StickState, obs: Observations, priors: Priors) -> tuple[np.ndarray, np.ndarray]:
    """Best local coordinates of every point on every stick, and the residual.

    Returns
    -------
    local : ndarray, shape (P, S, 3)
    sq : ndarray, shape (P, S)
        ``sum_f o_pf |w_pf - R_sf l_ps - t_sf|^2``.
    """
    S, F, D = st.trans.shape
    P = obs.n_points
    m = obs.mask  # (P, F)
    RtR = np.einsum("sfdi,sfdj->fsij", st.rot, st.rot).reshape(F, S * 9)
    H0 = (m @ RtR).reshape(P, S, 3, 3)
    Rt_t = np.einsum("sfdk,sfd->fsk", st.rot, st.trans).reshape(F, S * 3)
    Rw = obs.w.reshape(P, F * D) @ st.rot.transpose(1, 2, 0, 3).reshape(F * D, S * 3)
    b = (Rw - m @ Rt_t).reshape(P, S, 3)  # sum_f o R^T (w - t)
    H = st.tau_w * H0 + priors.tau_p * np.eye(3)
    loc = np.linalg.solve(H, st.tau_w * b[..., None])[..., 0]
    ww = np.sum(obs.w * obs.w, axis=(1, 2))  # (P,)
    wt = obs.w.reshape(P, F * D) @ st.trans.transpose(1, 2, 0).reshape(F * D, S)  # (P, S)
    tt = m @ np.sum(st.trans * st.trans, axis=2).T  # (P, S)
    sq = ww[:, None] - 2.0 * wt + tt - 2.0 * np.einsum("psk,psk->ps", loc, b) + np.einsum(
        "psi,psij,psj->ps", loc, H0, loc)
    return loc, np.maximum(sq, 0.0)


def stick_is_free(st: StickState) -> np.ndarray:
    """Sticks none of whose endpoints share a vertex (safe to delete), shape (S,) bool."""
    cnt = st.vertex_counts()
    if st.ghosts is not None:
        cnt = cnt + st.ghosts.n
    alone = cnt[st.vertex_of] == 1
    return alone.reshape(st.n_sticks, -1).all(axis=1)


def remove_sticks(st: StickState, drop: np.ndarray) -> StickState:
    """A copy without the sticks in ``drop`` (free sticks only), their endpoints and vertices.

    The points of dropped sticks must already be reassigned.
    """
    S = st.n_sticks
    keep = np.ones(S, bool)
    keep[drop] = False
    if np.isin(st.labels, np.flatnonzero(~keep)).any():
        raise RuntimeError("remove_sticks: some points are still on a dropped stick")
    new_id = -np.ones(S, np.int64)
    new_id[keep] = np.arange(keep.sum())
    ekeep = np.repeat(keep, st.ends_per_stick)
    vkeep = np.zeros(st.n_vertices, bool)
    vkeep[st.vertex_of[ekeep]] = True
    vnew = -np.ones(st.n_vertices, np.int64)
    vnew[vkeep] = np.arange(vkeep.sum())
    out = st.copy()
    out.labels = new_id[st.labels]
    out.vertex_of = vnew[st.vertex_of[ekeep]]
    out.rot, out.trans = st.rot[keep], st.trans[keep]
    out.ends, out.mu_e, out.tau_e = st.ends[ekeep], st.mu_e[ekeep], st.tau_e[ekeep]
    out.mu_v, out.tau_v = st.mu_v[vkeep], st.tau_v[vkeep]
    out.alpha, out.beta = st.alpha[vkeep], st.beta[vkeep]
    if st.ghosts is not None:
        out.ghosts = st.ghosts.take(vkeep)
    return out


def resample_assignments(st: StickState, obs: Observations, priors: Priors, rng: np.random.Generator, *,
                         mode: str = "sample", min_points: int = 3) -> tuple[StickState, int]:
    """Redraw every point's stick; refit local coordinates; drop sticks that fall apart.

    Parameters
    ----------
    mode : {"sample", "map"}
        Draw from the posterior (the paper) or take its mode.
    min_points : int
        A *free* stick (no joint) left with fewer points is dissolved: its points go
        to their best other stick and the stick, its endpoints and vertices are
        removed. A stick in a joint keeps at least its most probable point.

    Returns
    -------
    state : StickState
        The updated state (a new object when sticks were removed).
    changed : int
        How many points changed stick (0 when none).
    """
    S = st.n_sticks
    P = obs.n_points
    loc, sq = candidate_fits(st, obs, priors)
    counts = st.stick_sizes().astype(float)
    logc = np.log(np.maximum(counts, 1.0) / P)
    logp = logc[None, :] - 0.5 * st.tau_w * sq  # (P, S)
    if mode == "sample":
        new = np.argmax(logp + rng.gumbel(size=logp.shape), axis=1)
    elif mode == "map":
        new = np.argmax(logp, axis=1)
    else:
        raise ValueError(f"resample must be 'sample' or 'map', got {mode!r}")
    # Sticks in a joint must not vanish: give each its most probable former point back.
    free = stick_is_free(st)
    for s in np.flatnonzero(~free & (np.bincount(new, minlength=S) == 0)):
        mine = np.flatnonzero(st.labels == s)
        if mine.size:
            new[mine[np.argmax(logp[mine, s])]] = s
    # Free sticks left too small are dissolved into their points' next best sticks.
    cnt = np.bincount(new, minlength=S)
    drop = np.flatnonzero(free & (cnt < min_points))
    if drop.size and drop.size < S:
        lp = logp.copy()
        lp[:, drop] = -np.inf
        moving = np.isin(new, drop)
        new[moving] = np.argmax(lp[moving], axis=1)
    else:
        drop = np.zeros(0, np.int64)
    changed = int(np.sum(new != st.labels))
    out = st
    if changed:
        out = st.copy()
        out.labels = new
        out.local = loc[np.arange(P), new]
    if drop.size:
        out = remove_sticks(out, drop)
    return out, changed
