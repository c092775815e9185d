"""Putting trajectories on the scale the priors assume, and starting states.

Why and how the data are normalised
-----------------------------------
The paper's Gamma priors fix the size of a stick: ``s_yh ~ Gamma(100, 1)`` gives a
spread of the points along a stick of about ``1 / sqrt(100) = 0.1`` and a length
``L = 6 / sqrt(s_yh)`` of about 0.6, with little room to move (a Gamma with shape
100 is worth 200 observations); ``s_yv ~ Gamma(400, 1)`` a spread across the stick
of 0.05; ``s_T ~ Gamma(100, 1)`` joints within about 0.1 of the parent's end. So
the data's units decide how finely the figure is cut into sticks, and they have
to be set from the data.

We estimate the size of a rigid part directly (:func:`rigid_part_size`): every
point grows the largest group of nearby points that moves rigidly (2D
Procrustes residual at the noise level); its *rigid reach* is the largest
distance to a member, and the figure's part size is the median reach. The data are
centred on their mean position (one translation for the whole sequence) and
divided by ``scale = part_size / TARGET_REACH`` so that a typical part spans what
the prior expects (``TARGET_REACH`` = 0.33: points filling a stick end to end have a median
reach of about 0.75 of its length, so sticks come out about 0.45 long; the value was set on
synthetic arms and random planar figures). Results are mapped back to
the original coordinates. The scale can also be given explicitly (data units per
model unit). Children of the root have their translations tied to the origin
with a precision ``1 / R^2``, ``R`` the largest distance of a point from the centre,
so that it constrains nothing within the scene.
"""

from __future__ import annotations

import numpy as np

from .kernels import fit_node
from .model import Hyper, translation_conditional
from .state import Data, State

__all__ = ["TARGET_REACH", "rigid_part_size", "normalise", "initial_imputation", "rigid_imputation", "initial_state"]

#: Median rigid reach of the points, in model units, after normalisation.
TARGET_REACH = 0.33


def _group_rms(Z: np.ndarray, W: np.ndarray) -> np.ndarray:
    """RMS residual of a 2D rigid (Procrustes) fit of each weighted point group.

    Z : complex (G, n, F); W : (G, n) 0/1 membership. Returns (G,).
    """
    ws = W.sum(1)
    Wf = W[:, :, None]
    cen = (Z * Wf).sum(1) / ws[:, None]
    Xc = Z - cen[:, None, :]
    f0 = np.argmax(((np.abs(Xc) ** 2) * Wf).sum(1), axis=1)
    ref = Xc[np.arange(Z.shape[0]), :, f0] * W
    for _ in range(2):
        psi = np.angle((np.conj(ref)[:, :, None] * Xc * Wf).sum(1))
        ref = (Xc * np.exp(-1j * psi)[:, None, :]).mean(2) * W
    res = (Xc - ref[:, :, None] * np.exp(1j * psi)[:, None, :]) * Wf
    return np.sqrt((np.abs(res) ** 2).sum((1, 2)) / (ws * Z.shape[2]))


def rigid_part_size(xy: np.ndarray, max_neighbors: int = 30, max_frames: int = 30, tol: float = 2.5,
                    return_noise: bool = False) -> float | tuple[float, float]:
    """Typical size of a rigid part: the median over points of their rigid reach.

    Each point grows a rigid group greedily: its neighbours are visited in order
    of mean distance and kept when the group's Procrustes residual stays below
    ``tol`` times the typical residual of a point with its two nearest
    neighbours (the noise level). Points across a joint are skipped, so the
    group covers the point's part; its reach is the largest mean distance to a
    member. (Distances alone cannot tell a part from two parts joined at a
    nearly straight angle, whose distances change only to second order.)

    Parameters
    ----------
    xy : ndarray, shape (P, F, 2)
        Positions, NaN where missing (filled by interpolation for this estimate).
    max_neighbors, max_frames : int
        Bound the cost: O(P max_neighbors^2 max_frames).
    tol : float

    return_noise : bool
        Also return the noise level: the median residual (per coordinate) of a
        point and its two nearest neighbours, which is the noise standard
        deviation for rigid triples (2n - 3 residual degrees of freedom per frame
        over 2n coordinates, n = 3).

    Returns
    -------
    float, or (float, float) with ``return_noise``
        NaN with fewer than 3 points.
    """
    P, F, _ = xy.shape
    if P < 3:
        return (float("nan"), float("nan")) if return_noise else float("nan")
    fsel = np.unique(np.linspace(0, F - 1, min(F, max_frames)).round().astype(int))
    z = initial_imputation(xy[:, fsel, 0] + 1j * xy[:, fsel, 1])
    m = np.abs(z[:, None, :] - z[None, :, :]).mean(-1)
    R = min(P - 1, max_neighbors)
    order = np.argsort(m, axis=1, kind="stable")[:, : R + 1]  # the point itself first
    Z = z[order]
    W = np.zeros((P, R + 1))
    W[:, :3] = 1.0
    base = float(np.median(_group_rms(Z, W)))
    thr = tol * base
    W[:, 2:] = 0.0
    for r in range(2, R + 1):
        W[:, r] = 1.0
        W[_group_rms(Z, W) > thr, r] = 0.0
    reach = (m[np.arange(P)[:, None], order] * W).max(1)
    part = float(np.median(reach))
    return (part, base) if return_noise else part


def normalise(xy: np.ndarray, scale: float | str = "auto") -> tuple[np.ndarray, np.ndarray, float, float]:
    """Centre and scale 2D trajectories for the model.

    Parameters
    ----------
    xy : ndarray, shape (P, F, 2)
    scale : "auto" or float
        Data units per model unit.

    Returns
    -------
    z : complex ndarray, shape (P, F)
        Model coordinates, NaN where missing.
    centre : ndarray, shape (2,)
    scale : float
    noise : float
        Estimated noise standard deviation per coordinate, in model units (NaN if unknown).
    """
    centre = np.nanmean(xy.reshape(-1, 2), axis=0)
    part, noise = rigid_part_size(xy, return_noise=True)
    if isinstance(scale, str):
        if scale != "auto":
            raise ValueError(f"scale must be 'auto' or a positive number, got {scale!r}")
        if not np.isfinite(part) or part <= 0:
            # No rigid group at all: fall back on the overall spread.
            part = float(np.sqrt(np.nanmean(((xy - centre) ** 2).sum(-1)))) / 3.0
        if not np.isfinite(part) or part <= 0:
            raise ValueError("traj has no spatial extent (all observed positions coincide); cannot scale it")
        scale_f = part / TARGET_REACH
    else:
        scale_f = float(scale)
    if not np.isfinite(scale_f) or scale_f <= 0:
        raise ValueError(f"scale must be a positive number, got {scale_f!r}")
    q = (xy - centre) / scale_f
    return q[..., 0] + 1j * q[..., 1], centre, scale_f, noise / scale_f


def initial_imputation(z: np.ndarray) -> np.ndarray:
    """Fill missing entries by linear interpolation in time (constant beyond the ends)."""
    out = z.copy()
    F = z.shape[1]
    t = np.arange(F)
    for i in np.flatnonzero(np.isnan(z).any(1)):
        ok = ~np.isnan(z[i])
        out[i] = np.interp(t, t[ok], z[i, ok].real) + 1j * np.interp(t, t[ok], z[i, ok].imag)
    return out


def rigid_imputation(z: np.ndarray, n_neighbours: int = 4, n_ref: int = 3) -> np.ndarray:
    """Fill missing entries from the points that move rigidly with each one, else by interpolation.

    A fixed function of the observed entries (the sampler builds its structure
    proposals from it, see :attr:`.state.Data.x_proposal`). For a hidden entry
    ``(i, f)`` the points that keep the steadiest distance to ``i`` over the frames
    both are seen in (distance standard deviation at most three times the typical
    one of a point's steadiest partner: the same rigid part) and are seen in frame
    ``f`` carry ``i`` along: with at least two of them (up to ``n_neighbours``), a 2D
    rotation and translation mapping them from each of the ``n_ref`` nearest frames
    where ``i`` and they are all seen onto frame ``f`` is applied to ``i``, and the
    predictions are averaged. Entries without such partners (their whole part hidden)
    are interpolated linearly in time (:func:`initial_imputation`).

    Linear interpolation of a turning stick shortens it and bends its path; a rigid
    fit to such a completion then sees residuals tens of times the noise (measured on
    the occluded arm: a stick hidden in 19% of its entries got a noise precision 60
    times too small), and proposals built on it are far from anything the chain holds.
    """
    out = initial_imputation(z)
    obs = ~np.isnan(z)
    if obs.all():
        return out
    I, F = z.shape
    zf = np.where(obs, z, 0)
    sd = np.empty((I, I))
    m1 = np.empty((I, I))
    for i in range(I):  # row by row: memory O(I F)
        co = obs[i][None] & obs
        ncol = co.sum(-1)
        d = np.abs(zf[i][None] - zf)
        m1[i] = (d * co).sum(-1) / np.maximum(ncol, 1)
        m2 = (d * d * co).sum(-1) / np.maximum(ncol, 1)
        sd[i] = np.sqrt(np.maximum(m2 - m1[i] ** 2, 0.0))
        sd[i, ncol < 3] = np.inf
    np.fill_diagonal(sd, np.inf)
    best = sd.min(1)
    finite = np.isfinite(best)
    if not finite.any():
        return out
    limit = 3.0 * float(np.median(best[finite])) + 1e-9 * float(np.median(m1[np.isfinite(sd)]))  # round-off
    for i in np.flatnonzero(~obs.all(1)):
        partners = np.argsort(sd[i])
        partners = partners[sd[i, partners] <= limit]
        if partners.size < 2:
            continue
        for f in np.flatnonzero(~obs[i]):
            V = partners[obs[partners, f]][:n_neighbours]
            if V.size < 2:
                continue
            ref = np.flatnonzero(obs[i] & obs[V].all(0))
            if ref.size == 0:
                continue
            ref = ref[np.argsort(np.abs(ref - f), kind="stable")][:n_ref]
            preds = []
            for g in ref.tolist():
                a = z[V, g]
                b = z[V, f]
                ca, cb = a.mean(), b.mean()
                rot = np.exp(1j * np.angle(np.sum(np.conj(a - ca) * (b - cb))))
                preds.append(cb + rot * (z[i, g] - ca))
            out[i, f] = np.mean(preds)
    return out


def root_precision(z: np.ndarray) -> float:
    """1 / R^2 with R the largest distance of an observation from the origin (at least 1)."""
    R = float(np.nanmax(np.abs(z)))
    return 1.0 / max(R, 1.0) ** 2


def initial_state(data: Data, hyper: Hyper, rng: np.random.Generator, n_clusters: int) -> State:
    """A starting state: k-means on whole trajectories, every cluster a child of the root.

    Each node's angles come from a rigid fit of its points (:func:`.kernels.fit_node`),
    either way round at random; translations are their conditional mean.
    """
    from sklearn.cluster import KMeans

    x = data.x
    I, F = x.shape
    K0 = int(min(max(n_clusters, 1), I))
    if K0 > 1:
        feats = np.concatenate([x.real, x.imag], axis=1)
        km = KMeans(n_clusters=K0, n_init=1, random_state=int(rng.integers(2**31 - 1)))
        c = km.fit_predict(feats).astype(np.int64)
        c = np.unique(c, return_inverse=True)[1].astype(np.int64)
    else:
        c = np.zeros(I, np.int64)
    K = int(c.max()) + 1
    theta = np.zeros((K, F))
    T = np.zeros((K, F), complex)
    s_x = np.zeros(K)
    s_yh = np.full(K, hyper.a_syh / hyper.b_syh)
    s_yv = np.full(K, hyper.a_syv / hyper.b_syv)
    s_T = np.full(K, hyper.a_sT / hyper.b_sT)
    for k in range(K):
        xk = x[c == k]
        fit = fit_node(xk, None, hyper.root_precision, hyper)
        theta[k] = fit.theta + np.pi * (rng.random() < 0.5)
        s_x[k] = fit.sx_shape / fit.sx_rate
        T[k], _, _ = translation_conditional(theta[k], s_x[k], s_yh[k], s_yv[k], xk.shape[0], xk.sum(0),
                                             np.zeros(F, complex), hyper.root_precision, 0, 0j, s_T[k])
    return State(c=c, parent=-np.ones(K, np.int64), theta=theta, T=T, s_x=s_x, s_yh=s_yh, s_yv=s_yv, s_T=s_T,
                 lam=float(hyper.lam))
