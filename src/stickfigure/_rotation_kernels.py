"""Compiled per-matrix loops behind :mod:`stickfigure.geometry`'s rotation energy,
Newton step and quaternion Procrustes step.

EM evaluates these on every (stick, frame) pair in every sweep: thousands of 2x3
and 3x3 problems at a time, each a few dozen flops. In numpy every operation on
the batch makes a full pass over memory for an intermediate (N, 4, 4) or (N, 3, 3)
array, so those few flops cost a memory pass each: measured on the human-sized
figure (53 points, 11 sticks, 400 frames), these three functions took 45 % of
the whole fit, and the loops here run them 5-10x faster (docs/em.md section 11).
Each loop body is the arithmetic of the numpy version it replaces, in the same
closed forms (the derivations stay with the public functions in geometry.py),
on one matrix at a time. No fast-math, so the IEEE results are reproducible;
single-threaded (the EM forks its own workers).

Inputs are C-contiguous float64 arrays flattened over the batch: ``R`` (N, D, 3)
with orthonormal rows, ``C_ab`` (N, D, 3), ``C_bb`` (N, 3, 3) symmetric, quaternions
(N, 4) as (w, x, y, z). Outputs are written into the arrays passed last. The
signatures are explicit, so the loops compile (or load from numba's on-disk
cache) when this module is imported, not inside a forked worker.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

# Inputs may be read-only (views from np.broadcast_to); writable arrays convert to these.
_I3 = nb.types.Array(nb.float64, 3, "C", readonly=True)
_I2 = nb.types.Array(nb.float64, 2, "C", readonly=True)
_I1 = nb.types.Array(nb.float64, 1, "C", readonly=True)
_A3 = nb.float64[:, :, ::1]
_A2 = nb.float64[:, ::1]
_A1 = nb.float64[::1]
_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


@nb.njit([nb.float64(_I2, _I2, _I2), nb.float64(_A2, _I2, _I2)], **_JIT)
def _energy1(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray) -> float:
    # -2 tr(R C_ab^T) + tr(R C_bb R^T)
    e = 0.0
    for a in range(R.shape[0]):
        for j in range(3):
            rc = R[a, 0] * C_bb[0, j] + R[a, 1] * C_bb[1, j] + R[a, 2] * C_bb[2, j]
            e += (rc - 2.0 * C_ab[a, j]) * R[a, j]
    return e


@nb.njit(nb.void(_I3, _I3, _I3, _A1), **_JIT)
def rotation_energy(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, out: np.ndarray) -> None:
    """out[i] = -2 tr(R_i C_ab,i^T) + tr(R_i C_bb,i R_i^T)."""
    for i in range(R.shape[0]):
        out[i] = _energy1(R[i], C_ab[i], C_bb[i])


@nb.njit(nb.float64(nb.float64[:, ::1]), **_JIT)
def _min_eig_sym3(H: np.ndarray) -> float:
    # The trigonometric closed form of geometry.min_eig_sym3.
    p1 = H[0, 1] ** 2 + H[0, 2] ** 2 + H[1, 2] ** 2
    q = (H[0, 0] + H[1, 1] + H[2, 2]) / 3.0
    p2 = (H[0, 0] - q) ** 2 + (H[1, 1] - q) ** 2 + (H[2, 2] - q) ** 2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    s = p if p > 0 else 1.0
    b00, b11, b22 = (H[0, 0] - q) / s, (H[1, 1] - q) / s, (H[2, 2] - q) / s
    b01, b02, b12 = H[0, 1] / s, H[0, 2] / s, H[1, 2] / s
    b10, b20, b21 = H[1, 0] / s, H[2, 0] / s, H[2, 1] / s
    r = 0.5 * (b00 * (b11 * b22 - b12 * b21) - b01 * (b10 * b22 - b12 * b20) + b02 * (b10 * b21 - b11 * b20))
    r = min(max(r, -1.0), 1.0)
    return q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)


@nb.njit(nb.void(_I3, _I3, _I3, _I1, _A3, _A1), **_JIT)
def rotation_newton_step(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, e_old: np.ndarray,
                         R_out: np.ndarray, e_out: np.ndarray) -> None:
    """One damped Newton step on every rotation (geometry.rotation_newton_step), kept where it lowers the energy."""
    D = R.shape[1]
    P = np.empty((3, 3))
    N = np.empty((3, 3))
    CP = np.empty((3, 3))
    H = np.empty((3, 3))
    K = np.empty((3, 3))
    Q = np.empty((3, 3))
    Rn = np.empty((D, 3))
    g = np.empty(3)
    for i in range(R.shape[0]):
        Ri, Ca, Cb = R[i], C_ab[i], C_bb[i]
        for j in range(3):
            for k in range(3):
                pj = 0.0
                nj = 0.0
                for a in range(D):
                    pj += Ri[a, j] * Ri[a, k]
                    nj += Ca[a, j] * Ri[a, k]
                P[j, k] = pj
                N[j, k] = nj
        for j in range(3):
            for k in range(3):
                CP[j, k] = Cb[j, 0] * P[0, k] + Cb[j, 1] * P[1, k] + Cb[j, 2] * P[2, k]
        # g = vee(CP - PC) - 2 vee(N), with PC = CP^T and vee(M) = (M12 - M21, M20 - M02, M01 - M10)
        g[0] = 2.0 * (CP[1, 2] - CP[2, 1]) - 2.0 * (N[1, 2] - N[2, 1])
        g[1] = 2.0 * (CP[2, 0] - CP[0, 2]) - 2.0 * (N[2, 0] - N[0, 2])
        g[2] = 2.0 * (CP[0, 1] - CP[1, 0]) - 2.0 * (N[0, 1] - N[1, 0])
        trC = Cb[0, 0] + Cb[1, 1] + Cb[2, 2]
        trN = N[0, 0] + N[1, 1] + N[2, 2]
        trCP = CP[0, 0] + CP[1, 1] + CP[2, 2]
        diag = 2.0 * trN + 2.0 * D * trC - 4.0 * trCP
        hmax = 0.0
        for j in range(3):
            for k in range(3):
                h = (3.0 * (CP[j, k] + CP[k, j]) - (2.0 * D) * Cb[j, k] - 2.0 * trC * P[j, k]
                     - (N[j, k] + N[k, j]))
                if j == k:
                    h += diag
                H[j, k] = h
                hmax = max(hmax, abs(h))
        mu = max(0.0, -_min_eig_sym3(H)) + 1e-6 * hmax + 1e-300
        for j in range(3):
            H[j, j] += mu
        # w = H^-1 (-g) by cofactors
        a, b, c = H[0, 0], H[0, 1], H[0, 2]
        d, e, f = H[1, 0], H[1, 1], H[1, 2]
        gg, h, k9 = H[2, 0], H[2, 1], H[2, 2]
        A, B, C = e * k9 - f * h, f * gg - d * k9, d * h - e * gg
        det = a * A + b * B + c * C
        safe = det if det != 0 else 1.0
        x0 = (A * -g[0] + (c * h - b * k9) * -g[1] + (b * f - c * e) * -g[2]) / safe
        x1 = (B * -g[0] + (a * k9 - c * gg) * -g[1] + (c * d - a * f) * -g[2]) / safe
        x2 = (C * -g[0] + (b * gg - a * h) * -g[1] + (a * e - b * d) * -g[2]) / safe
        if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
            x0 = x1 = x2 = 0.0
        # Long steps leave the region where the quadratic model holds: at most 0.5 rad.
        th = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        cap = min(1.0, 0.5 / max(th, 1e-300))
        x0, x1, x2, th = x0 * cap, x1 * cap, x2 * cap, th * cap
        # exp([w]_x) by Rodrigues' formula (series where theta is tiny)
        if th < 1e-6:
            s1, s2 = 1.0 - th * th / 6.0, 0.5 - th * th / 24.0
        else:
            s1, s2 = math.sin(th) / th, (1.0 - math.cos(th)) / (th * th)
        K[0, 0], K[0, 1], K[0, 2] = 0.0, -x2, x1
        K[1, 0], K[1, 1], K[1, 2] = x2, 0.0, -x0
        K[2, 0], K[2, 1], K[2, 2] = -x1, x0, 0.0
        for j in range(3):
            for k in range(3):
                kk = K[j, 0] * K[0, k] + K[j, 1] * K[1, k] + K[j, 2] * K[2, k]
                Q[j, k] = (1.0 if j == k else 0.0) + s1 * K[j, k] + s2 * kk
        for r in range(D):
            for k in range(3):
                Rn[r, k] = Ri[r, 0] * Q[0, k] + Ri[r, 1] * Q[1, k] + Ri[r, 2] * Q[2, k]
        e_new = _energy1(Rn, Ca, Cb)
        if e_new < e_old[i]:
            R_out[i] = Rn
            e_out[i] = e_new
        else:
            R_out[i] = Ri
            e_out[i] = e_old[i]


@nb.njit(nb.void(nb.float64[::1], nb.float64[:, ::1]), **_JIT)
def _quat_to_rot(q: np.ndarray, Q: np.ndarray) -> None:
    w, x, y, z = q[0], q[1], q[2], q[3]
    Q[0, 0], Q[0, 1], Q[0, 2] = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)
    Q[1, 0], Q[1, 1], Q[1, 2] = 2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)
    Q[2, 0], Q[2, 1], Q[2, 2] = 2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)


@nb.njit(nb.void(_I2, _I3, _I3, nb.int64, nb.int64, _A3, _A2), **_JIT)
def procrustes_step(quat: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, n_outer: int, n_square: int,
                    R_out: np.ndarray, q_out: np.ndarray) -> None:
    """Green-Gower completion steps by Horn's quaternion power iteration (models/em/updates.procrustes_step)."""
    D = C_ab.shape[1]
    Q = np.empty((3, 3))
    C = np.empty((3, 3))
    M = np.empty((4, 4))
    T = np.empty((4, 4))
    q = np.empty(4)
    qn = np.empty(4)
    for i in range(quat.shape[0]):
        for k in range(4):
            q[k] = quat[i, k]
        _quat_to_rot(q, Q)
        for _ in range(n_outer if D == 2 else 1):
            for a in range(D):
                for b in range(3):
                    C[a, b] = C_ab[i, a, b]
            if D == 2:  # the completed third row: r3^T C_bb
                for b in range(3):
                    C[2, b] = Q[2, 0] * C_bb[i, 0, b] + Q[2, 1] * C_bb[i, 1, b] + Q[2, 2] * C_bb[i, 2, b]
            s2 = 0.0
            for a in range(3):
                for b in range(3):
                    s2 += C[a, b] * C[a, b]
            sig = math.sqrt(3.0 * s2)
            # Horn's N(C) + sigma I (positive semi-definite)
            M[0, 0] = C[0, 0] + C[1, 1] + C[2, 2] + sig
            M[1, 1] = C[0, 0] - C[1, 1] - C[2, 2] + sig
            M[2, 2] = -C[0, 0] + C[1, 1] - C[2, 2] + sig
            M[3, 3] = -C[0, 0] - C[1, 1] + C[2, 2] + sig
            M[0, 1] = M[1, 0] = C[2, 1] - C[1, 2]
            M[0, 2] = M[2, 0] = C[0, 2] - C[2, 0]
            M[0, 3] = M[3, 0] = C[1, 0] - C[0, 1]
            M[1, 2] = M[2, 1] = C[0, 1] + C[1, 0]
            M[1, 3] = M[3, 1] = C[0, 2] + C[2, 0]
            M[2, 3] = M[3, 2] = C[1, 2] + C[2, 1]
            for _ in range(n_square):
                for a in range(4):
                    for b in range(4):
                        T[a, b] = M[a, 0] * M[0, b] + M[a, 1] * M[1, b] + M[a, 2] * M[2, b] + M[a, 3] * M[3, b]
                tr = max(T[0, 0] + T[1, 1] + T[2, 2] + T[3, 3], 1e-300)
                for a in range(4):
                    for b in range(4):
                        M[a, b] = T[a, b] / tr
            nrm = 0.0
            for a in range(4):
                qn[a] = M[a, 0] * q[0] + M[a, 1] * q[1] + M[a, 2] * q[2] + M[a, 3] * q[3]
                nrm += qn[a] * qn[a]
            nrm = math.sqrt(nrm)
            if nrm > 1e-300:
                for a in range(4):
                    q[a] = qn[a] / nrm
            _quat_to_rot(q, Q)
        for k in range(4):
            q_out[i, k] = q[k]
        for a in range(D):
            for b in range(3):
                R_out[i, a, b] = Q[a, b]


@nb.njit(nb.void(_I3, _A3, nb.bool_[::1]), **_JIT)
def polar_rows2(C: np.ndarray, out: np.ndarray, ok: np.ndarray) -> None:
    """out[i] = (C C^T)^(-1/2) C for 2x3 C[i]: the polar factor U V^T of its thin SVD.

    With A = C C^T (2x2, positive definite), s = sqrt(det A) and t = sqrt(tr A + 2 s),
    sqrt(A) = (A + s I) / t, so A^(-1/2) = t (A + s I)^(-1). ``ok[i]`` is False where C
    is near rank 1 (det A below 1e-20 tr(A)^2), where the factor is not unique.
    """
    for i in range(C.shape[0]):
        a = C[i, 0, 0] * C[i, 0, 0] + C[i, 0, 1] * C[i, 0, 1] + C[i, 0, 2] * C[i, 0, 2]
        b = C[i, 0, 0] * C[i, 1, 0] + C[i, 0, 1] * C[i, 1, 1] + C[i, 0, 2] * C[i, 1, 2]
        d = C[i, 1, 0] * C[i, 1, 0] + C[i, 1, 1] * C[i, 1, 1] + C[i, 1, 2] * C[i, 1, 2]
        det = a * d - b * b
        tr = a + d
        if not (det > 1e-20 * tr * tr):
            ok[i] = False
            continue
        ok[i] = True
        s = math.sqrt(det)
        t = math.sqrt(tr + 2.0 * s)
        # (A + s I)^-1 = [[d + s, -b], [-b, a + s]] / det(A + s I)
        m = t / ((a + s) * (d + s) - b * b)
        i00, i01, i11 = m * (d + s), -m * b, m * (a + s)
        for k in range(3):
            c0, c1 = C[i, 0, k], C[i, 1, k]
            out[i, 0, k] = i00 * c0 + i01 * c1
            out[i, 1, k] = i01 * c0 + i11 * c1
