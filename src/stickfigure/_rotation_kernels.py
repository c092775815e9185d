"""Compiled per-matrix loops behind :mod:`stickfigure.geometry`'s rotation energy,
Newton step and quaternion Procrustes step, and of the EM's rotation-to-quaternion
conversion and mirror alignment.

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


@nb.njit(inline="always", **_JIT)  # inlined into its callers: a call per matrix costs 2x here
def _energy_at(R: np.ndarray, r: int, C_ab: np.ndarray, C_bb: np.ndarray, i: int) -> float:
    # -2 tr(R[r] C_ab[i]^T) + tr(R[r] C_bb[i] R[r]^T). The loops here index the batch arrays
    # directly: taking ``R[i]`` as a view costs more than this arithmetic (3x in rotation_energy).
    e = 0.0
    for a in range(R.shape[1]):
        for j in range(3):
            rc = R[r, a, 0] * C_bb[i, 0, j] + R[r, a, 1] * C_bb[i, 1, j] + R[r, a, 2] * C_bb[i, 2, j]
            e += (rc - 2.0 * C_ab[i, a, j]) * R[r, a, j]
    return e


@nb.njit(nb.void(_I3, _I3, _I3, _A1), **_JIT)
def rotation_energy(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, out: np.ndarray) -> None:
    """out[i] = -2 tr(R_i C_ab,i^T) + tr(R_i C_bb,i R_i^T)."""
    for i in range(R.shape[0]):
        out[i] = _energy_at(R, i, C_ab, C_bb, i)


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


@nb.njit(inline="always", **_JIT)
def _newton_at(R: np.ndarray, r: int, C_ab: np.ndarray, C_bb: np.ndarray, i: int, e_old: float,
               R_out: np.ndarray, o: int, P: np.ndarray, N: np.ndarray, CP: np.ndarray, H: np.ndarray,
               K: np.ndarray, Q: np.ndarray, Rn: np.ndarray, g: np.ndarray) -> float:
    # One damped Newton step on R[r] against problem i (C_ab[i], C_bb[i]) from its energy e_old:
    # writes the step, or R[r] where the step does not lower the energy, to R_out[o] and returns
    # that rotation's energy. P ... g are scratch (3x3, Rn (1, D, 3), g (3,)).
    D = R.shape[1]
    for j in range(3):
        for k in range(3):
            pj = 0.0
            nj = 0.0
            for row in range(D):
                pj += R[r, row, j] * R[r, row, k]
                nj += C_ab[i, row, j] * R[r, row, k]
            P[j, k] = pj
            N[j, k] = nj
    for j in range(3):
        for k in range(3):
            CP[j, k] = C_bb[i, j, 0] * P[0, k] + C_bb[i, j, 1] * P[1, k] + C_bb[i, j, 2] * P[2, k]
    # g = vee(CP - PC) - 2 vee(N), with PC = CP^T and vee(M) = (M12 - M21, M20 - M02, M01 - M10)
    g[0] = 2.0 * (CP[1, 2] - CP[2, 1]) - 2.0 * (N[1, 2] - N[2, 1])
    g[1] = 2.0 * (CP[2, 0] - CP[0, 2]) - 2.0 * (N[2, 0] - N[0, 2])
    g[2] = 2.0 * (CP[0, 1] - CP[1, 0]) - 2.0 * (N[0, 1] - N[1, 0])
    trC = C_bb[i, 0, 0] + C_bb[i, 1, 1] + C_bb[i, 2, 2]
    trN = N[0, 0] + N[1, 1] + N[2, 2]
    trCP = CP[0, 0] + CP[1, 1] + CP[2, 2]
    diag = 2.0 * trN + 2.0 * D * trC - 4.0 * trCP
    hmax = 0.0
    for j in range(3):
        for k in range(3):
            h = (3.0 * (CP[j, k] + CP[k, j]) - (2.0 * D) * C_bb[i, j, k] - 2.0 * trC * P[j, k]
                 - (N[j, k] + N[k, j]))
            if j == k:
                h += diag
            H[j, k] = h
            hmax = max(hmax, abs(h))
    # The shift needs the smallest eigenvalue only where H may not be positive definite:
    # where the leading minors are positive and lambda_min >= det / tr^2 (lambda_max <= tr)
    # exceeds 1e-8 tr, far above the closed form's rounding, max(0, -lambda_min) is 0 as
    # the closed form would give it, without its acos and cos.
    m1 = H[0, 0]
    m2 = H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]
    m3 = (H[0, 0] * (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]) - H[0, 1] * (H[1, 0] * H[2, 2] - H[1, 2] * H[2, 0])
          + H[0, 2] * (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]))
    trH = H[0, 0] + H[1, 1] + H[2, 2]
    if m1 > 0.0 and m2 > 0.0 and m3 > 1e-8 * trH * trH * trH:
        mu = 0.0 + 1e-6 * hmax + 1e-300
    else:
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
    for row in range(D):
        for k in range(3):
            Rn[0, row, k] = R[r, row, 0] * Q[0, k] + R[r, row, 1] * Q[1, k] + R[r, row, 2] * Q[2, k]
    e_new = _energy_at(Rn, 0, C_ab, C_bb, i)
    take = e_new < e_old
    for row in range(D):
        for k in range(3):
            R_out[o, row, k] = Rn[0, row, k] if take else R[r, row, k]
    return e_new if take else e_old


@nb.njit(inline="always", **_JIT)
def _newton_scratch(D: int) -> tuple:
    # The scratch arrays of _newton_at, once per kernel call: six 3x3 (P, N, CP, H, K, Q), the
    # trial rotation Rn (1, D, 3) (a batch of one for _energy_at) and the gradient g (3,).
    return (np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
            np.empty((3, 3)), np.empty((1, D, 3)), np.empty(3))


@nb.njit(nb.void(_I3, _I3, _I3, _I1, _A3, _A1), **_JIT)
def rotation_newton_step(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, e_old: np.ndarray,
                         R_out: np.ndarray, e_out: np.ndarray) -> None:
    """One damped Newton step on every rotation (geometry.rotation_newton_step), kept where it lowers the energy."""
    P, N, CP, H, K, Q, Rn, g = _newton_scratch(R.shape[1])
    for i in range(R.shape[0]):
        e_out[i] = _newton_at(R, i, C_ab, C_bb, i, e_old[i], R_out, i, P, N, CP, H, K, Q, Rn, g)


@nb.njit(nb.void(_I2, _I3, _I3, nb.int64, nb.int64, _A3, _A2), **_JIT)
def procrustes_step(quat: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, n_outer: int, n_square: int,
                    R_out: np.ndarray, q_out: np.ndarray) -> None:
    """Green-Gower completion steps by Horn's quaternion power iteration (models/em/updates.procrustes_step).

    Written in scalars (the 4x4 matrices as 16 locals), which the compiler keeps in
    registers: 1.4x faster than the same arithmetic on small scratch arrays, whose
    stores it cannot elide; the operations and their order are those of the array
    form it replaces, so the results are the same bits.
    """
    D = C_ab.shape[1]
    for i in range(quat.shape[0]):
        w, x, y, z = quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3]
        # the third row of R(q), the only one the completion step reads
        q20, q21, q22 = 2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)
        for _ in range(n_outer if D == 2 else 1):
            c00, c01, c02 = C_ab[i, 0, 0], C_ab[i, 0, 1], C_ab[i, 0, 2]
            c10, c11, c12 = C_ab[i, 1, 0], C_ab[i, 1, 1], C_ab[i, 1, 2]
            if D == 2:  # the completed third row: r3^T C_bb
                c20 = q20 * C_bb[i, 0, 0] + q21 * C_bb[i, 1, 0] + q22 * C_bb[i, 2, 0]
                c21 = q20 * C_bb[i, 0, 1] + q21 * C_bb[i, 1, 1] + q22 * C_bb[i, 2, 1]
                c22 = q20 * C_bb[i, 0, 2] + q21 * C_bb[i, 1, 2] + q22 * C_bb[i, 2, 2]
            else:
                c20, c21, c22 = C_ab[i, 2, 0], C_ab[i, 2, 1], C_ab[i, 2, 2]
            s2 = 0.0
            s2 += c00 * c00
            s2 += c01 * c01
            s2 += c02 * c02
            s2 += c10 * c10
            s2 += c11 * c11
            s2 += c12 * c12
            s2 += c20 * c20
            s2 += c21 * c21
            s2 += c22 * c22
            sig = math.sqrt(3.0 * s2)
            # Horn's N(C) + sigma I (positive semi-definite)
            m00 = c00 + c11 + c22 + sig
            m11 = c00 - c11 - c22 + sig
            m22 = -c00 + c11 - c22 + sig
            m33 = -c00 - c11 + c22 + sig
            m01 = m10 = c21 - c12
            m02 = m20 = c02 - c20
            m03 = m30 = c10 - c01
            m12 = m21 = c01 + c10
            m13 = m31 = c02 + c20
            m23 = m32 = c12 + c21
            for _ in range(n_square):
                t00 = m00 * m00 + m01 * m10 + m02 * m20 + m03 * m30
                t01 = m00 * m01 + m01 * m11 + m02 * m21 + m03 * m31
                t02 = m00 * m02 + m01 * m12 + m02 * m22 + m03 * m32
                t03 = m00 * m03 + m01 * m13 + m02 * m23 + m03 * m33
                t10 = m10 * m00 + m11 * m10 + m12 * m20 + m13 * m30
                t11 = m10 * m01 + m11 * m11 + m12 * m21 + m13 * m31
                t12 = m10 * m02 + m11 * m12 + m12 * m22 + m13 * m32
                t13 = m10 * m03 + m11 * m13 + m12 * m23 + m13 * m33
                t20 = m20 * m00 + m21 * m10 + m22 * m20 + m23 * m30
                t21 = m20 * m01 + m21 * m11 + m22 * m21 + m23 * m31
                t22 = m20 * m02 + m21 * m12 + m22 * m22 + m23 * m32
                t23 = m20 * m03 + m21 * m13 + m22 * m23 + m23 * m33
                t30 = m30 * m00 + m31 * m10 + m32 * m20 + m33 * m30
                t31 = m30 * m01 + m31 * m11 + m32 * m21 + m33 * m31
                t32 = m30 * m02 + m31 * m12 + m32 * m22 + m33 * m32
                t33 = m30 * m03 + m31 * m13 + m32 * m23 + m33 * m33
                tr = max(t00 + t11 + t22 + t33, 1e-300)
                m00, m01, m02, m03 = t00 / tr, t01 / tr, t02 / tr, t03 / tr
                m10, m11, m12, m13 = t10 / tr, t11 / tr, t12 / tr, t13 / tr
                m20, m21, m22, m23 = t20 / tr, t21 / tr, t22 / tr, t23 / tr
                m30, m31, m32, m33 = t30 / tr, t31 / tr, t32 / tr, t33 / tr
            n0 = m00 * w + m01 * x + m02 * y + m03 * z
            n1 = m10 * w + m11 * x + m12 * y + m13 * z
            n2 = m20 * w + m21 * x + m22 * y + m23 * z
            n3 = m30 * w + m31 * x + m32 * y + m33 * z
            nrm = 0.0
            nrm += n0 * n0
            nrm += n1 * n1
            nrm += n2 * n2
            nrm += n3 * n3
            nrm = math.sqrt(nrm)
            if nrm > 1e-300:
                w, x, y, z = n0 / nrm, n1 / nrm, n2 / nrm, n3 / nrm
            q20, q21, q22 = 2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)
        q_out[i, 0], q_out[i, 1], q_out[i, 2], q_out[i, 3] = w, x, y, z
        R_out[i, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
        R_out[i, 0, 1] = 2.0 * (x * y - z * w)
        R_out[i, 0, 2] = 2.0 * (x * z + y * w)
        R_out[i, 1, 0] = 2.0 * (x * y + z * w)
        R_out[i, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
        R_out[i, 1, 2] = 2.0 * (y * z - x * w)
        if D == 3:
            R_out[i, 2, 0], R_out[i, 2, 1], R_out[i, 2, 2] = q20, q21, q22


@nb.njit(nb.void(_I3, _A2, nb.bool_[::1]), **_JIT)
def rot_to_quat(R: np.ndarray, out: np.ndarray, ok: np.ndarray) -> None:
    """Unit quaternions (w, x, y, z) of proper rotations R (N, 3, 3) by Shepperd's method.

    The branch (the largest of the diagonal and the trace), the formulas, the
    normalisation and their order are scipy's ``Rotation.from_matrix`` for
    orthonormal input, so the results are the same bits (tested) at a twentieth of
    the time. ``ok[i]`` is False where R[i] is not orthonormal by scipy's test
    (``R R^T`` within 1e-12 + 1e-5 |I| of I) or not proper: there scipy first
    orthogonalises (or refuses), and the caller hands those matrices to it.
    """
    for n in range(R.shape[0]):
        m = R[n]
        good = True
        for a in range(3):
            for b in range(3):
                g = m[a, 0] * m[b, 0] + m[a, 1] * m[b, 1] + m[a, 2] * m[b, 2]
                ref = 1.0 if a == b else 0.0
                if not abs(g - ref) <= 1e-12 + 1e-5 * ref:
                    good = False
        det = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
               + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))
        ok[n] = good and det > 0.0
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        choice = 0
        best = m[0, 0]
        if m[1, 1] > best:
            choice, best = 1, m[1, 1]
        if m[2, 2] > best:
            choice, best = 2, m[2, 2]
        if tr > best:
            choice = 3
        # v = (x, y, z, w), scipy's order
        if choice != 3:
            i = choice
            j = (i + 1) % 3
            k = (j + 1) % 3
            vi = 1.0 - tr + 2.0 * m[i, i]
            vj = m[j, i] + m[i, j]
            vk = m[k, i] + m[i, k]
            v3 = m[k, j] - m[j, k]
            v = (vi, vj, vk) if i == 0 else ((vk, vi, vj) if i == 1 else (vj, vk, vi))
            v0, v1, v2 = v
        else:
            v0 = m[2, 1] - m[1, 2]
            v1 = m[0, 2] - m[2, 0]
            v2 = m[1, 0] - m[0, 1]
            v3 = 1.0 + tr
        nrm = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3)
        out[n, 0] = v3 / nrm
        out[n, 1] = v0 / nrm
        out[n, 2] = v1 / nrm
        out[n, 3] = v2 / nrm


@nb.njit(inline="always", **_JIT)
def _plane_normal_at(C: np.ndarray, i: int, normal: np.ndarray, M: np.ndarray, Cp: np.ndarray, Cn: np.ndarray,
                     cand: np.ndarray) -> float:
    # Writes into normal (3,) the unit eigenvector of C[i]'s smallest eigenvalue and returns
    # lambda_min / lambda_max; M ... cand are 3x3 scratch.
    for a in range(3):
        for b in range(3):
            Cp[a, b] = C[i, a, b]
            Cn[a, b] = -C[i, a, b]
    lam_min = _min_eig_sym3(Cp)
    lam_max = -_min_eig_sym3(Cn)
    for a in range(3):
        for b in range(3):
            M[a, b] = C[i, a, b] - lam_min * (1.0 if a == b else 0.0)
    for r, (u, v) in enumerate(((0, 1), (0, 2), (1, 2))):
        cand[r, 0] = M[u, 1] * M[v, 2] - M[u, 2] * M[v, 1]
        cand[r, 1] = M[u, 2] * M[v, 0] - M[u, 0] * M[v, 2]
        cand[r, 2] = M[u, 0] * M[v, 1] - M[u, 1] * M[v, 0]
    best = -1.0
    k = 0
    for r in range(3):
        nr = math.sqrt(cand[r, 0] * cand[r, 0] + cand[r, 1] * cand[r, 1] + cand[r, 2] * cand[r, 2])
        if nr > best:
            best, k = nr, r
    d = max(best, 1e-300)
    for b in range(3):
        normal[b] = cand[k, b] / d
    return lam_min / max(lam_max, 1e-300)


@nb.njit(nb.void(_I3, _A2, _A1), **_JIT)
def plane_normals(C: np.ndarray, normal: np.ndarray, ratio: np.ndarray) -> None:
    """Unit eigenvector of the smallest eigenvalue of symmetric C[i] (3, 3), and lambda_min / lambda_max.

    The arithmetic of ``models/em/updates._plane_normal`` (the longest cross
    product of two rows of ``C - lambda_min I``) one matrix at a time, the same bits.
    """
    M = np.empty((3, 3))
    Cp = np.empty((3, 3))
    Cn = np.empty((3, 3))
    cand = np.empty((3, 3))
    for i in range(C.shape[0]):
        ratio[i] = _plane_normal_at(C, i, normal[i], M, Cp, Cn, cand)


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


@nb.njit(nb.void(_I3, _I3, _I3, nb.int64, nb.types.Array(nb.int64, 1, "C", readonly=True), _I2, nb.float64,
                 _A3, nb.bool_[:, ::1]), **_JIT)
def mirror_runs(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, F: int, idx: np.ndarray, normal: np.ndarray,
                tie: float, R_mirror: np.ndarray, odd: np.ndarray) -> None:
    """The frames where each flat stick's mirror image continues its tied runs (``updates.align_mirrors``).

    ``R``, ``C_ab`` (S F, D, 3) and ``C_bb`` (S F, 3, 3) hold every stick's frames in
    order; ``idx`` (k,) the flat sticks, ``normal`` (k, 3) their planes' unit normals.
    Writes ``R_mirror`` (k F, D, 3), each rotation times ``I - 2 n n^T``, and ``odd``
    (k, F), where the mirror is to be taken. The rules and the arithmetic are those
    of the numpy version this replaces, one stick at a time and one pass over its
    frames (a run's choice once the run ends): the energies, products and sums in
    the same order, so the same bits.
    """
    D = R.shape[1]
    H = np.empty((3, 3))
    e0 = np.empty(F)
    e1 = np.empty(F)
    rn = np.empty((F, D))
    long = np.empty(F, dtype=np.bool_)
    for kk in range(idx.shape[0]):
        s = idx[kk]
        for a in range(3):
            for b in range(3):
                H[a, b] = (1.0 if a == b else 0.0) - 2.0 * normal[kk, a] * normal[kk, b]
        for f in range(F):
            i = s * F + f
            m = kk * F + f
            for d in range(D):
                for c in range(3):
                    R_mirror[m, d, c] = R[i, d, 0] * H[0, c] + R[i, d, 1] * H[1, c] + R[i, d, 2] * H[2, c]
            e0[f] = _energy_at(R, i, C_ab, C_bb, i)
            e1[f] = _energy_at(R_mirror, m, C_ab, C_bb, i)
            sq = 0.0
            for d in range(D):
                r = R[i, d, 0] * normal[kk, 0] + R[i, d, 1] * normal[kk, 1] + R[i, d, 2] * normal[kk, 2]
                rn[f, d] = r
                sq += r * r
            long[f] = math.sqrt(sq) >= 0.3
        # the parity of the projected normal's flips since the last untied frame; each run of tied
        # frames then keeps it, or its complement where that has the lower total energy
        parity = False
        start = 0
        sum_keep = 0.0
        sum_other = 0.0
        n_odd = 0
        n_tied = 0
        for f in range(F):
            tied = abs(e1[f] - e0[f]) <= tie
            if not tied:
                parity = False
                odd[kk, f] = False
                start = f + 1
                sum_keep = 0.0
                sum_other = 0.0
                n_odd = 0
                n_tied = 0
                continue
            if f > 0 and long[f] and long[f - 1]:
                dot = 0.0
                for d in range(D):
                    dot += rn[f, d] * rn[f - 1, d]
                if dot < 0:
                    parity = not parity
            odd[kk, f] = parity
            if parity:
                sum_keep += e1[f]
                sum_other += e0[f]
                n_odd += 1
            else:
                sum_keep += e0[f]
                sum_other += e1[f]
            n_tied += 1
            if f == F - 1 or not abs(e1[f + 1] - e0[f + 1]) <= tie:  # the run ends here
                if sum_other < sum_keep or (sum_other == sum_keep and n_tied - n_odd < n_odd):
                    for g in range(start, f + 1):
                        odd[kk, g] = not odd[kk, g]


@nb.njit(nb.void(_I3, _I3, _I3, nb.types.Array(nb.float64, 4, "C", readonly=True),
                 nb.types.Array(nb.bool_, 2, "C", readonly=True), nb.int64, nb.bool_, _A3), **_JIT)
def best_rotations(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, starts: np.ndarray, has: np.ndarray,
                   n_newton: int, polish_current: bool, R_out: np.ndarray) -> None:
    """The multi-start rotation search of ``models/em/updates.best_rotations``, one problem at a time.

    Per problem i: ``R[i]``, polished by ``n_newton`` Newton steps where
    ``polish_current``; then each start ``starts[k, i]`` (K, N, D, 3) where ``has[k, i]``,
    in order of k, polished by ``n_newton`` steps and taken where its energy is
    strictly lower than the best so far. The starts are made by the caller (the
    same bits as the numpy form); what this loop saves is the batch's passes over
    memory and its gathers and scatters per start.
    """
    D = R.shape[1]
    P, N, CP, H, K, Q, Rn, g = _newton_scratch(D)
    X = np.empty((1, D, 3))
    for i in range(R.shape[0]):
        for row in range(D):
            for c in range(3):
                R_out[i, row, c] = R[i, row, c]
        best_e = _energy_at(R_out, i, C_ab, C_bb, i)
        if polish_current:
            for _ in range(n_newton):
                best_e = _newton_at(R_out, i, C_ab, C_bb, i, best_e, R_out, i, P, N, CP, H, K, Q, Rn, g)
        for k in range(starts.shape[0]):
            if not has[k, i]:
                continue
            for row in range(D):
                for c in range(3):
                    X[0, row, c] = starts[k, i, row, c]
            e = _energy_at(X, 0, C_ab, C_bb, i)
            for _ in range(n_newton):
                e = _newton_at(X, 0, C_ab, C_bb, i, e, X, 0, P, N, CP, H, K, Q, Rn, g)
            if e < best_e:
                best_e = e
                for row in range(D):
                    for c in range(3):
                        R_out[i, row, c] = X[0, row, c]


@nb.njit(nb.void(_I3, _I2, _I3, _I2, _I3, _I3, _A3, _A2, _A1), **_JIT)
def keep_lower(R_old: np.ndarray, q_old: np.ndarray, R_new: np.ndarray, q_new: np.ndarray, C_ab: np.ndarray,
               C_bb: np.ndarray, R_out: np.ndarray, q_out: np.ndarray, e_old: np.ndarray) -> None:
    """R_out, q_out: the new rotation and quaternion where its energy is not above the old one's, else the old.

    ``e_old`` gets the old rotations' energies (``models/em/updates.update_motions`` uses them
    again); the comparison is numpy's ``new <= old`` (False with a NaN: the old is kept).
    """
    D = R_old.shape[1]
    for i in range(R_old.shape[0]):
        eo = _energy_at(R_old, i, C_ab, C_bb, i)
        en = _energy_at(R_new, i, C_ab, C_bb, i)
        e_old[i] = eo
        keep = en <= eo
        for row in range(D):
            for c in range(3):
                R_out[i, row, c] = R_new[i, row, c] if keep else R_old[i, row, c]
        for c in range(4):
            q_out[i, c] = q_new[i, c] if keep else q_old[i, c]
