"""Compiled sums over the observed (point, frame) entries, per stick and frame.

Every EM sweep needs, for each (stick, frame), sums over that stick's visible
points: of ``l``, ``l l^T`` and ``w l^T`` (the Procrustes statistics), of the
squared residuals ``|w - R l - t|^2`` (tau_w and the objective), and per point
the normal equations of its local coordinates. These loops make one pass over
the P x F entries each, where the sparse-incidence products they replace
(scipy.sparse, one product per statistic) made several, plus their reshapes;
the residual is summed directly instead of expanded into moments, so it has no
cancellation. See :class:`.model.Design`.

Inputs: ``labels`` (P,) int64 stick of each point, ``mask`` (P, F) float64 (an
entry counts where > 0), ``w`` (P, F, D), ``local`` (P, 3), ``rot`` (S, F, D, 3),
``trans`` (S, F, D), all C-contiguous; outputs are zeroed here and written in place.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_L = nb.types.Array(nb.int64, 1, "C", readonly=True)
_I1 = nb.types.Array(nb.float64, 1, "C", readonly=True)
_I2 = nb.types.Array(nb.float64, 2, "C", readonly=True)
_I3 = nb.types.Array(nb.float64, 3, "C", readonly=True)
_I4 = nb.types.Array(nb.float64, 4, "C", readonly=True)


@nb.njit(nb.void(_L, _I2, _I3, _I2, nb.float64[:, :, ::1], nb.float64[:, :, :, ::1], nb.float64[:, :, :, ::1]),
         **_JIT)
def point_moments(labels: np.ndarray, mask: np.ndarray, w: np.ndarray, local: np.ndarray,
                  s_l: np.ndarray, s_ll: np.ndarray, s_wl: np.ndarray) -> None:
    """s_l (S, F, 3), s_ll (S, F, 3, 3), s_wl (S, F, D, 3): sums of l, l l^T, w l^T over visible points."""
    P, F, D = w.shape
    s_l[:] = 0.0
    s_ll[:] = 0.0
    s_wl[:] = 0.0
    for p in range(P):
        s = labels[p]
        l0, l1, l2 = local[p, 0], local[p, 1], local[p, 2]
        for f in range(F):
            if mask[p, f] > 0:
                s_l[s, f, 0] += l0
                s_l[s, f, 1] += l1
                s_l[s, f, 2] += l2
                for j in range(3):
                    lj = local[p, j]
                    s_ll[s, f, j, 0] += lj * l0
                    s_ll[s, f, j, 1] += lj * l1
                    s_ll[s, f, j, 2] += lj * l2
                for d in range(D):
                    wd = w[p, f, d]
                    s_wl[s, f, d, 0] += wd * l0
                    s_wl[s, f, d, 1] += wd * l1
                    s_wl[s, f, d, 2] += wd * l2


@nb.njit(nb.void(_L, _I2, _I3, _I4, _I3, _I2, nb.float64[::1]), **_JIT)
def residual_sq(labels: np.ndarray, mask: np.ndarray, w: np.ndarray, rot: np.ndarray, trans: np.ndarray,
                local: np.ndarray, out: np.ndarray) -> None:
    """out (S,): sum over the visible entries of each stick of |w - R l - t|^2."""
    P, F, D = w.shape
    out[:] = 0.0
    for p in range(P):
        s = labels[p]
        l0, l1, l2 = local[p, 0], local[p, 1], local[p, 2]
        acc = 0.0
        for f in range(F):
            if mask[p, f] > 0:
                for d in range(D):
                    r = w[p, f, d] - rot[s, f, d, 0] * l0 - rot[s, f, d, 1] * l1 - rot[s, f, d, 2] * l2 \
                        - trans[s, f, d]
                    acc += r * r
        out[s] += acc


@nb.njit(nb.void(_L, _I2, _I3, _I4, _I3, nb.float64[:, :, ::1], nb.float64[:, ::1]), **_JIT)
def local_normal_equations(labels: np.ndarray, mask: np.ndarray, w: np.ndarray, rot: np.ndarray,
                           trans: np.ndarray, H: np.ndarray, b: np.ndarray) -> None:
    """H (P, 3, 3) = sum_f o R^T R and b (P, 3) = sum_f o R^T (w - t), R, t of the point's stick."""
    P, F, D = w.shape
    H[:] = 0.0
    b[:] = 0.0
    for p in range(P):
        s = labels[p]
        for f in range(F):
            if mask[p, f] > 0:
                for d in range(D):
                    r = w[p, f, d] - trans[s, f, d]
                    for j in range(3):
                        rj = rot[s, f, d, j]
                        b[p, j] += rj * r
                        for k in range(3):
                            H[p, j, k] += rj * rot[s, f, d, k]


@nb.njit(nb.void(nb.float64, _I3, _I2, _I3, _I4, _I4, _I1, _I3, _I2, _I4, _I3,
                 nb.float64[:, :, ::1], nb.float64[:, :, ::1], nb.float64[:, :, :, ::1], nb.float64[:, :, :, ::1]),
         **_JIT)
def procrustes_moments(tw: float, s_w: np.ndarray, n: np.ndarray, s_l: np.ndarray, s_ll: np.ndarray,
                       s_wl: np.ndarray, w_end: np.ndarray, t_end: np.ndarray, k_end: np.ndarray,
                       c_end: np.ndarray, kk_end: np.ndarray, a_bar: np.ndarray, b_bar: np.ndarray,
                       C_ab: np.ndarray, C_bb: np.ndarray) -> None:
    """Weighted centroids and centred moments of every (stick, frame) Procrustes problem.

    The points (weight tw; sums s_w, n, s_l, s_ll, s_wl per (stick, frame)) and the
    endpoints (per stick: total weight w_end (S,), weighted target sum t_end (S, F, D),
    source sum k_end (S, 3), cross moment c_end (S, F, D, 3), second moment kk_end
    (S, 3, 3)) pooled: W = tw n + w_end, a_bar = (tw s_w + t_end) / W,
    b_bar = (tw s_l + k_end) / W, C_ab = tw s_wl + c_end - W a_bar b_bar^T,
    C_bb = tw s_ll + kk_end - W b_bar b_bar^T (symmetrised).
    """
    S, F, D = s_w.shape
    for s in range(S):
        for f in range(F):
            W = tw * n[s, f] + w_end[s]
            for j in range(3):
                b_bar[s, f, j] = (tw * s_l[s, f, j] + k_end[s, j]) / W
            for d in range(D):
                a = (tw * s_w[s, f, d] + t_end[s, f, d]) / W
                a_bar[s, f, d] = a
                for j in range(3):
                    C_ab[s, f, d, j] = tw * s_wl[s, f, d, j] + c_end[s, f, d, j] - W * a * b_bar[s, f, j]
            for j in range(3):
                for k in range(j, 3):
                    v = 0.5 * (tw * (s_ll[s, f, j, k] + s_ll[s, f, k, j]) + kk_end[s, j, k] + kk_end[s, k, j]) \
                        - W * b_bar[s, f, j] * b_bar[s, f, k]
                    C_bb[s, f, j, k] = v
                    C_bb[s, f, k, j] = v


@nb.njit(nb.void(_L, _I2, nb.float64[:, ::1]), **_JIT)
def row_sums(index: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """out (J, K) = the rows of x (E, K) summed by ``index`` (E,), in the order of E.

    ``np.add.at(out, index, x)`` on a zeroed ``out``, with the same order of additions
    (so the same bits), without its per-element dispatch. Every index must lie in [0, J):
    the loop does not check (a vertex index of the model always does).
    """
    out[:] = 0.0
    E, K = x.shape
    for e in range(E):
        j = index[e]
        for k in range(K):
            out[j, k] += x[e, k]


@nb.njit(nb.void(_L, _I2, nb.float64[:, :, ::1]), **_JIT)
def stick_scatter(labels: np.ndarray, local: np.ndarray, cov: np.ndarray) -> None:
    """cov (S, 3, 3): each stick's scatter of its points' local coordinates about their mean.

    Sums in point order, as the bincount / ``np.add.at`` version it replaces (the same bits).
    """
    S = cov.shape[0]
    P = local.shape[0]
    mean = np.zeros((S, 3))
    cnt = np.zeros(S)
    for p in range(P):
        cnt[labels[p]] += 1.0
        for k in range(3):
            mean[labels[p], k] += local[p, k]
    for s in range(S):
        c = max(cnt[s], 1.0)
        for k in range(3):
            mean[s, k] = mean[s, k] / c
    cov[:] = 0.0
    for p in range(P):
        s = labels[p]
        x0 = local[p, 0] - mean[s, 0]
        x1 = local[p, 1] - mean[s, 1]
        x2 = local[p, 2] - mean[s, 2]
        cov[s, 0, 0] += x0 * x0
        cov[s, 0, 1] += x0 * x1
        cov[s, 0, 2] += x0 * x2
        cov[s, 1, 0] += x1 * x0
        cov[s, 1, 1] += x1 * x1
        cov[s, 1, 2] += x1 * x2
        cov[s, 2, 0] += x2 * x0
        cov[s, 2, 1] += x2 * x1
        cov[s, 2, 2] += x2 * x2
