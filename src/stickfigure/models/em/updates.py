"""The variational EM updates of Ross, Tarlow & Zemel (section 4.1), vectorised.

Each function maximises the objective (:func:`model.objective_terms`) over one
block of variables with the others fixed, so a sweep never decreases it
(tests/test_em_updates.py checks this after every single update). Nothing
loops over frames: updates act on stacked (stick, frame) or (vertex, frame)
arrays, the vertex chain is one banded solve over all vertices at once.

Where the printed updates differ (docs/em.md has the derivations):

* **Translations.** The paper's update has ``M_s^f k_i`` (which contains the
  unknown ``t``) on its right-hand side. Setting the derivative of
  ``tau_w sum_p o_pf |w - R l - t|^2 + tau_m sum_i |mu(e_i) - R k_i - t|^2`` to zero
  gives ``t = [tau_w sum_p o_pf (w - R l) + tau_m sum_i (mu(e_i) - R k_i)] /
  (tau_w n_sf + E tau_m)`` with ``n_sf`` the number of the stick's points seen in
  frame f. We solve rotation and translation *jointly*: with weighted centroids
  the optimal t for any R is ``a_bar - R b_bar``, which leaves a centred
  Procrustes problem for R alone.
* **Rotations.** For a 2x3 R with orthonormal rows the SVD solution is exact
  only when the source points are isotropic, because ``|R B|^2`` depends on R.
  We start from it and take Green-Gower completion steps (each a 3x3 orthogonal
  Procrustes problem solved by SVD), via
  :func:`stickfigure.geometry.orthogonal_procrustes_rows`; the new rotation is
  kept only where it lowers the stick's energy, so the step is monotone.
* **Vertices.** The paper's mean update for ``mu(v_j^f)`` depends on its temporal
  neighbours: it is one Gauss-Seidel sweep of the tridiagonal system
  ``(a_j n_j + tau_t c_f) mu_f - tau_t (mu_f-1 + mu_f+1) = a_j sum_i mu(e_i^f)``. We
  solve that system exactly with one ``scipy.linalg.solveh_banded`` call on the
  chain of all vertices laid end to end (zero coupling between vertices).
* **Missing data** drops out of every point sum (``o_pf``), including the counts
  in tau_w and in the translation's denominator.
* **Dimension.** The printed precision updates are for D = 2 with isotropic
  posteriors; we keep D symbolic (e.g. ``alpha(phi_j) = alpha_j + D F n_j / 2``).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
from scipy.linalg import solveh_banded
from scipy.spatial.transform import Rotation

from ... import _rotation_kernels as _rk
from ...geometry import flat_rotation_batch
from ...geometry import rotation_energy as _rotation_energy
from ...geometry import rotation_newton_step as newton_step
from . import _point_kernels as _pk
from .model import Observations, Priors, StickState, chain_degree

__all__ = ["align_mirrors", "mirror_alignment", "update_endpoints", "update_vertices", "update_phi",
           "update_motions", "update_local",
           "update_ends", "update_precisions", "em_sweep"]


def update_endpoints(st: StickState, which: np.ndarray | None = None) -> None:
    """Gaussian posterior of every endpoint (or of the endpoints ``which``) given its stick and vertex.

    ``tau(e_i) = tau_m + a_g``, ``mu(e_i^f) = (tau_m R k_i + t + a_g mu(v_g^f)) / tau(e_i)``.
    """
    if which is None:
        a = (st.alpha / st.beta)[st.vertex_of]  # (ES,)
        tau = st.tau_m + a
        pred = st.end_predictions()
        st.mu_e = (st.tau_m * pred + a[:, None, None] * st.mu_v[st.vertex_of]) / tau[:, None, None]
        st.tau_e = tau
        return
    g = st.vertex_of[which]
    a = st.alpha[g] / st.beta[g]
    tau = st.tau_m + a
    s = which // st.ends_per_stick
    pred = (st.rot[s] @ st.ends[which][:, None, :, None])[..., 0] + st.trans[s]
    st.mu_e[which] = (st.tau_m * pred + a[:, None, None] * st.mu_v[g]) / tau[:, None, None]
    st.tau_e[which] = tau


def _vertex_sums(st: StickState) -> tuple[np.ndarray, np.ndarray]:
    """Endpoint count (J,) and sum of endpoint means (J, F, D) per vertex, ghosts included."""
    J, F, D = st.mu_v.shape
    n = st.vertex_counts()
    s = np.empty((J, F * D))
    _pk.row_sums(np.ascontiguousarray(st.vertex_of, dtype=np.int64),
                 np.ascontiguousarray(st.mu_e, dtype=float).reshape(-1, F * D), s)
    s = s.reshape(J, F, D)
    if st.ghosts is not None:
        n = n + st.ghosts.n
        s = s + st.ghosts.sum
    return n, s


def update_vertices(st: StickState) -> None:
    """Exact Gaussian posterior means of all vertex chains, and their precisions.

    ``tau(v_j^f) = a_j n_j + tau_t c_f`` (c_f = 1 at the ends, 2 inside) is the
    diagonal of the chain's precision matrix (the mean-field optimum); the means
    solve the full tridiagonal system (the mean-field fixed point, which the
    paper's update approaches one sweep at a time).
    """
    J, F, D = st.mu_v.shape
    a = st.alpha / st.beta
    n, s = _vertex_sums(st)
    c = chain_degree(F)
    diag = (a * n)[:, None] + st.tau_t * c[None, :]  # (J, F)
    st.tau_v = diag
    if F == 1:
        st.mu_v = (a[:, None, None] * s) / diag[..., None]
        return
    ab = np.empty((2, J * F))
    ab[1] = diag.ravel()
    sup = np.full((J, F), -st.tau_t)
    sup[:, 0] = 0.0  # no coupling between the last frame of one vertex and the first of the next
    ab[0] = sup.ravel()
    rhs = (a[:, None, None] * s).reshape(J * F, D)
    st.mu_v = solveh_banded(ab, rhs, lower=False, check_finite=False).reshape(J, F, D)


def update_phi(st: StickState, priors: Priors) -> None:
    """Gamma posterior of the vertex precisions.

    ``alpha(phi_j) = alpha_0 + D F n_j / 2`` and ``beta(phi_j) = beta_0 + 1/2 sum_{i in j, f}
    (|mu(e_i^f) - mu(v_j^f)|^2 + D / tau(e_i) + D / tau(v_j^f))`` (for D = 2 the paper's form).
    """
    J, F, D = st.mu_v.shape
    g = st.vertex_of
    dv = st.mu_e - st.mu_v[g]
    per_end = np.sum(dv * dv, axis=(1, 2)) + F * D / st.tau_e + D * np.sum(1.0 / st.tau_v[g], axis=1)
    ss = np.bincount(g, weights=per_end, minlength=J)
    n = st.vertex_counts()
    if st.ghosts is not None:
        gh = st.ghosts
        gsq = gh.sq - 2.0 * np.sum(gh.sum * st.mu_v, axis=2) + gh.n[:, None] * np.sum(st.mu_v ** 2, axis=2)
        ss = ss + np.sum(gsq + gh.var + gh.n[:, None] * D / st.tau_v, axis=1)
        n = n + gh.n
    st.alpha = priors.alpha0 + 0.5 * D * F * n
    st.beta = priors.beta0 + 0.5 * np.maximum(ss, 0.0)


def _motion_statistics(st: StickState, obs: Observations, collapse: bool = False,
                       kappa: np.ndarray | None = None, lam: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Weighted centroids and centred second moments of each (stick, frame) Procrustes problem.

    Sources are the stick's visible points (weight tau_w, target w, source l)
    and its endpoints: with ``collapse`` False (the paper's M-step) weight tau_m,
    target mu(e), source k; with ``collapse`` True the endpoint posterior is
    optimised jointly with the motion (:func:`update_motions`): weight
    ``tau_m a_g / (tau_m + a_g)``, target the vertex mean mu(v_g), source k.
    ``kappa`` (S,): a rotation prior ``kappa tr(R (R_f-1 + R_f+1)^T)`` on each frame given its
    neighbours' current rotations, which adds ``kappa (R_f-1 + R_f+1)`` to C_ab.
    ``lam`` (S,): a Gaussian random-walk prior ``lam |c_f - c_f-1|^2`` on each stick's centroid
    ``c_f = R_f lbar + t_f`` (``lbar`` the mean of its points' local coordinates), given the
    neighbours' current centroids: one more source point, ``lbar`` with weight ``lam`` times the
    number of neighbours and the neighbours' mean centroid as its target.

    Returns
    -------
    a_bar : (S, F, D), b_bar : (S, F, 3), C_ab : (S, F, D, 3), C_bb : (S, F, 3, 3)
    """
    S, F, D = st.trans.shape
    des = st.design(obs)
    s_l, s_ll, s_wl = des.point_stats(st.local)
    s_w, n = des.s_w, des.n
    tw = st.tau_w
    E = st.ends_per_stick
    ends = st.ends.reshape(S, E, 3)
    # Per stick: the endpoints' total weight (S,) or scalar, weighted target sum (S, F, D), weighted
    # source sum (S, 3), cross moment (S, F, D, 3) and second moment (S, 3, 3).
    if not collapse:  # the paper's M-step
        tm = st.tau_m
        mue = st.mu_e.reshape(S, E, F, D)
        w_sum = E * tm
        t_sum = tm * mue.sum(axis=1)
        k_sum = tm * ends.sum(axis=1)
        # sum_e mu(e) k_e^T as one (F D, E) x (E, 3) product per stick
        e_cross = tm * np.matmul(mue.transpose(0, 2, 3, 1).reshape(S, F * D, E), ends).reshape(S, F, D, 3)
        kk = tm * (np.swapaxes(ends, 1, 2) @ ends)
    else:
        a = (st.alpha / st.beta)[st.vertex_of]
        wm = (st.tau_m * a / (st.tau_m + a)).reshape(S, E)  # the two springs in series
        tgt = st.mu_v[st.vertex_of].reshape(S, E, F, D)
        w_sum = wm.sum(axis=1)
        t_sum = np.einsum("se,sefd->sfd", wm, tgt)
        k_sum = (wm[..., None] * ends).sum(axis=1)
        wt = (wm[:, :, None, None] * tgt).transpose(0, 2, 3, 1).reshape(S, F * D, E)
        e_cross = np.matmul(wt, ends).reshape(S, F, D, 3)
        kk = np.einsum("se,sej,sek->sjk", wm, ends, ends)
    a_bar, b_bar = np.empty((S, F, D)), np.empty((S, F, 3))
    C_ab, C_bb = np.empty((S, F, D, 3)), np.empty((S, F, 3, 3))
    c = np.ascontiguousarray
    _pk.procrustes_moments(float(tw), s_w, n, s_l, s_ll, s_wl, c(np.broadcast_to(w_sum, (S,)), dtype=float),
                           c(t_sum, dtype=float), c(k_sum, dtype=float), c(e_cross, dtype=float), c(kk, dtype=float),
                           a_bar, b_bar, C_ab, C_bb)
    if kappa is not None and F > 1:
        C_ab = C_ab + np.asarray(kappa, float)[:, None, None, None] * _neighbour_sum(st.rot)
    if lam is not None and F > 1:
        W = tw * n + np.broadcast_to(w_sum, (S,))[:, None]  # the pooled weight of every problem
        a_bar, b_bar, C_ab, C_bb = _with_centroid_prior(st, np.asarray(lam, float), W, a_bar, b_bar, C_ab, C_bb)
    return a_bar, b_bar, C_ab, C_bb


def _neighbour_sum(x: np.ndarray) -> np.ndarray:
    """(S, F, ...) sum of each frame's neighbours in time, ``x[:, f-1] + x[:, f+1]`` (one at either end)."""
    nb = np.zeros_like(x)
    nb[:, 1:] += x[:, :-1]
    nb[:, :-1] += x[:, 1:]
    return nb


def stick_centroids(st: StickState) -> np.ndarray:
    """(S, 3) mean local coordinates of each stick's points (the centroid the prior follows)."""
    S = st.n_sticks
    cnt = np.maximum(st.stick_sizes(), 1).astype(float)
    return np.stack([np.bincount(st.labels, weights=st.local[:, j], minlength=S) for j in range(3)], axis=1) \
        / cnt[:, None]


def _with_centroid_prior(st: StickState, lam: np.ndarray, W: np.ndarray, a_bar: np.ndarray, b_bar: np.ndarray,
                         C_ab: np.ndarray, C_bb: np.ndarray) -> tuple[np.ndarray, ...]:
    """The Procrustes moments with each stick's centroid pulled toward its neighbours' (``lam``, (S,)).

    One source point ``lbar`` (the stick's centroid in local coordinates), weight
    ``omega = lam * (number of neighbouring frames)``, target the neighbours' mean centroid
    ``y``, pooled with the others (total weight ``W`` (S, F)): the centred moments gain
    ``W omega / (W + omega) (y - a_bar)(lbar - b_bar)^T`` (a point added to a weighted mean).
    """
    S, F, D = st.trans.shape
    lbar = stick_centroids(st)
    c = np.einsum("sfdj,sj->sfd", st.rot, lbar) + st.trans  # (S, F, D) current centroids
    k = np.full(F, 2.0)  # neighbouring frames
    k[0] = k[-1] = 1.0
    y = _neighbour_sum(c) / k[None, :, None]
    omega = lam[:, None] * k[None, :]  # (S, F)
    Wn = W + omega
    da, db = y - a_bar, lbar[:, None, :] - b_bar  # (S, F, D), (S, F, 3)
    g = (W * omega / Wn)[..., None, None]
    return (a_bar + (omega / Wn)[..., None] * da, b_bar + (omega / Wn)[..., None] * db,
            C_ab + g * da[..., :, None] * db[..., None, :], C_bb + g * db[..., :, None] * db[..., None, :])


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) = (w, x, y, z) (scipy's Rotation)."""
    out = np.zeros(q.shape[:-1] + (3, 3))
    if out.size:  # scipy's (x, y, z, w) order; scalar_first needs scipy 1.14
        out[:] = Rotation.from_quat(q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(out.shape)
    return out


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) = (w, x, y, z) of proper rotations (..., 3, 3), as scipy's Rotation gives them.

    Compiled (:func:`stickfigure._rotation_kernels.rot_to_quat`, the same bits as
    ``Rotation.from_matrix``); the matrices that are not orthonormal to scipy's
    tolerance, or not proper, go to scipy itself (which orthogonalises or refuses them).
    """
    flat = np.ascontiguousarray(R, dtype=float).reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    ok = np.empty(flat.shape[0], dtype=np.bool_)
    _rk.rot_to_quat(flat, out, ok)
    if not ok.all():
        out[~ok] = Rotation.from_matrix(flat[~ok]).as_quat()[:, [3, 0, 1, 2]]
    return out.reshape(R.shape[:-2] + (4,))


def complete_rotation(R: np.ndarray) -> np.ndarray:
    """Proper 3x3 rotations whose first D rows are ``R`` (..., D, 3) with orthonormal rows."""
    if R.shape[-2] == 3:
        return R  # assumed proper
    r3 = np.cross(R[..., 0, :], R[..., 1, :])
    return np.concatenate([R, r3[..., None, :]], axis=-2)


def procrustes_step(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, *, n_outer: int = 1,
                    n_square: int = 3, quat: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A monotone step for ``min_R -2 tr(R C_ab^T) + tr(R C_bb R^T)`` over R (..., D, 3), R R^T = I.

    For D = 2 this is projection Procrustes; each outer iteration is a
    Green-Gower completion step: with ``r3`` the current third row of the
    rotation, ``C = [C_ab; r3^T C_bb]`` and the rotation maximising ``tr(Q^T C)``
    does not increase the energy. That 3x3 problem is solved with Horn's
    quaternion matrix N(C) by ``2**n_square`` steps of power iteration on the
    shifted ``N + sigma I`` (positive semi-definite for ``sigma = sqrt(3) |C|_F``),
    warm-started at the current rotation: each power step cannot lower the
    Rayleigh quotient ``q^T N q = tr(R(q)^T C)``, so the whole step is monotone.
    ``quat`` (..., 4), the quaternion of the current rotation, saves converting R.
    Returns the new R and its quaternion.

    Matrix squaring keeps it to a few 4x4 products: a batched 3x3 SVD
    (what :func:`stickfigure.geometry.orthogonal_procrustes_rows` uses) costs about
    5 us per matrix in LAPACK, 100x more, and this runs on every (stick, frame)
    pair in every EM iteration. The loop over the pairs is compiled
    (:mod:`stickfigure._rotation_kernels`).
    """
    D = R.shape[-2]
    batch, Rf, Ca, Cb = flat_rotation_batch(R, C_ab, C_bb)
    q = rot_to_quat(complete_rotation(Rf)) if quat is None else quat
    q = np.ascontiguousarray(np.broadcast_to(q, batch + (4,)), dtype=float).reshape(-1, 4)
    R_out = np.empty_like(Ca)
    q_out = np.empty_like(q)
    _rk.procrustes_step(q, Ca, Cb, n_outer, n_square, R_out, q_out)
    return R_out.reshape(batch + (D, 3)), q_out.reshape(batch + (4,))


#: A stick whose smallest principal spread is below this fraction of its largest is "flat":
#: its rotations get mirrored starts in :func:`best_rotations`.
FLAT_RATIO = 0.3


def _plane_normal(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvector of the smallest eigenvalue of symmetric 3x3 ``C`` and lambda_min / lambda_max.

    The eigenvector is the longest cross product of two rows of ``C - lambda_min I``
    (closed form, :func:`stickfigure.geometry.min_eig_sym3` for the eigenvalues;
    one matrix at a time in a compiled loop, :func:`stickfigure._rotation_kernels.plane_normals`).
    """
    flat = np.ascontiguousarray(C, dtype=float).reshape(-1, 3, 3)
    n = np.empty((flat.shape[0], 3))
    ratio = np.empty(flat.shape[0])
    _rk.plane_normals(flat, n, ratio)
    return n.reshape(C.shape[:-1]), ratio.reshape(C.shape[:-2])


def _polar_rows(C: np.ndarray) -> np.ndarray:
    """The paper's rotation update: the orthonormal-row polar factor ``U V^T`` of C (..., D, 3).

    For D = 3 made proper (det +1). For D = 2 in closed form, ``(C C^T)^(-1/2) C``
    (compiled; a batched LAPACK SVD costs about 5 us per matrix); where C is
    near rank 1 the factor is not unique and the SVD picks one.
    """
    if C.shape[-2] == 2:
        flat = np.ascontiguousarray(C, dtype=float).reshape(-1, 2, 3)
        out = np.empty_like(flat)
        ok = np.empty(flat.shape[0], dtype=np.bool_)
        _rk.polar_rows2(flat, out, ok)
        if not ok.all():
            U, _, Vt = np.linalg.svd(flat[~ok], full_matrices=False)
            out[~ok] = U @ Vt
        return out.reshape(C.shape)
    U, _, Vt = np.linalg.svd(C, full_matrices=False)
    polar = U @ Vt
    if C.shape[-2] == 3:
        polar = polar * np.sign(np.linalg.det(polar))[..., None, None]
    return polar


def best_rotations(R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, axes: np.ndarray | None = None,
                   flat: np.ndarray | None = None, *, use_polar: bool = True, n_newton: int = 2,
                   frame_mirrors: bool = True, only_mirrors: bool = False) -> np.ndarray:
    """Multi-start minimisation of the per-(stick, frame) rotation energy.

    The energy of a 2x3 rotation has several local minima when the sources it
    maps (the stick's visible points and its endpoints) are nearly planar or
    collinear — a flat stick, or a frame where only three of its points are seen
    — the depth-reversal ambiguity of orthographic projection; EM's
    one-step-at-a-time updates can sit in the wrong one for hundreds of
    iterations. For sources in a plane with unit normal n the projections of
    ``R`` and of its mirror image ``R (I - 2 n n^T)`` coincide (both have
    orthonormal rows), so the two are equally good until something off that plane
    (a joint, the other points) tells them apart. Starts: the current R; the
    paper's SVD solution (polar factor of C_ab) when ``use_polar``; for the sticks
    marked in ``flat`` (boolean over R's first axis), R mirrored through the planes
    normal to the two minor principal axes of the stick's shape (``axes``, rows in
    increasing order of spread, shape (S, 1, 3, 3)); and with ``frame_mirrors``, in
    every (stick, frame) whose weighted sources are nearly planar (smallest
    eigenvalue of C_bb below ``FLAT_RATIO**2`` of the largest), R mirrored through
    that frame's plane. Each start is polished by ``n_newton`` Newton steps; the
    lowest energy wins (never above the current one). ``only_mirrors`` tries the
    mirrored starts alone (the current R is not polished: cheap where few
    frames are ambiguous). The starts are made here; a compiled loop
    (:func:`stickfigure._rotation_kernels.best_rotations`) polishes them and keeps
    the best, one problem at a time, where the numpy form gathered, polished and
    scattered each start over the batch (the same bits; 18 % less time in the human-sized fit,
    where the Newton steps themselves are most of what is left).
    """
    batch, Rf, Ca, Cb = flat_rotation_batch(R, C_ab, C_bb)
    n_prob, D = Rf.shape[:2]
    # The starts, each where it applies (the mirrors by numpy's matmul, as before: the same bits);
    # the compiled loop polishes them and keeps the best, problem by problem.
    starts: list[np.ndarray] = []
    has: list[np.ndarray] = []
    if use_polar:
        starts.append(_polar_rows(Ca))
        has.append(np.ones(n_prob, bool))
    if flat is not None and axes is not None and np.any(flat):
        mask = np.broadcast_to(np.reshape(flat, flat.shape + (1,) * (len(batch) - flat.ndim)), batch).reshape(-1)
        ax = np.broadcast_to(axes, batch + (3, 3)).reshape(-1, 3, 3)[mask]
        for k in range(2):
            n = ax[..., k, :]
            X = np.zeros((n_prob, D, 3))
            X[mask] = Rf[mask] @ (np.eye(3) - 2.0 * n[..., :, None] * n[..., None, :])
            starts.append(X)
            has.append(mask)
    if frame_mirrors:
        n, ratio = _plane_normal(Cb)
        mask = ratio < FLAT_RATIO ** 2
        if mask.any():
            n = n[mask]
            X = np.zeros((n_prob, D, 3))
            X[mask] = Rf[mask] @ (np.eye(3) - 2.0 * n[..., :, None] * n[..., None, :])
            starts.append(X)
            has.append(mask)
    out = np.empty_like(Rf)
    _rk.best_rotations(Rf, Ca, Cb, np.stack(starts) if starts else np.empty((0, n_prob, D, 3)),
                       np.stack(has) if has else np.empty((0, n_prob), bool), int(n_newton), not only_mirrors, out)
    return out.reshape(batch + (D, 3))


def _principal_axes(st: StickState) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes of every stick's points and whether the stick is flat.

    Returns
    -------
    axes : ndarray, shape (S, 1, 3, 3)
        Rows in increasing order of spread.
    flat : ndarray of bool, shape (S,)
        Smallest spread below ``FLAT_RATIO`` times the largest.
    """
    cov = np.empty((st.n_sticks, 3, 3))
    _pk.stick_scatter(np.ascontiguousarray(st.labels, dtype=np.int64), np.ascontiguousarray(st.local, dtype=float),
                      cov)
    lam, V = np.linalg.eigh(cov)
    lam = np.maximum(lam, 0.0)
    flat = np.sqrt(lam[:, 0]) < FLAT_RATIO * np.sqrt(np.maximum(lam[:, 2], 1e-300))
    return np.swapaxes(V, -1, -2)[:, None], flat


#: A stick's rotation in a frame is determined by its points only where it shows at least this many
#: (two points leave a turn about the line through them free, and let the stick's depth grow
#: without bound: any projected distance up to the 3D one is then fitted exactly).
MIN_ROTATION_POINTS = 3


def slerp_fill(q: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Quaternions (..., F, 4) kept where ``good`` (..., F), spherically interpolated in between.

    Frames before the first / after the last good frame take its value; rows without
    a good frame are returned unchanged.
    """
    F = good.shape[-1]
    f = np.arange(F)
    prev = np.maximum.accumulate(np.where(good, f, -1), axis=-1)
    nxt = np.flip(np.minimum.accumulate(np.flip(np.where(good, f, F), axis=-1), axis=-1), axis=-1)
    p = np.where(prev < 0, nxt, prev)
    n = np.where(nxt >= F, prev, nxt)
    none = (p < 0) | (p >= F)
    p, n = np.clip(p, 0, F - 1), np.clip(n, 0, F - 1)
    w = np.where(n > p, (f - p) / np.maximum(n - p, 1), 0.0)
    q0 = np.take_along_axis(q, p[..., None], axis=-2)
    q1 = np.take_along_axis(q, n[..., None], axis=-2)
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    th = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    sth = np.sin(th)
    small = sth < 1e-8
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * th) / np.where(small, 1.0, sth))
    b = np.where(small, w, np.sin(w * th) / np.where(small, 1.0, sth))
    qi = a[..., None] * q0 + b[..., None] * q1
    qi /= np.maximum(np.linalg.norm(qi, axis=-1, keepdims=True), 1e-300)
    return np.where(none[..., None], q, qi)


def underdetermined_frames(st: StickState, obs: Observations) -> np.ndarray | None:
    """(S, F) bool: frames where a stick of >= 3 points shows fewer than ``MIN_ROTATION_POINTS``.

    Only sticks with at least one frame that does show that many are marked (a
    stick of one or two points has its rotation from its joints, not from
    interpolation). None when no frame is marked (complete data).
    """
    des = st.design(obs)
    size = st.stick_sizes()
    few = des.n < MIN_ROTATION_POINTS
    ok = (size >= MIN_ROTATION_POINTS) & (~few).any(axis=1)
    out = few & ok[:, None]
    return out if out.any() else None


#: Energy (``sum w |a - R b|^2``, twice a log-likelihood) within which a flat stick's two mirror
#: images count as equally good in a frame when mirror alignment is on (:func:`align_mirrors`).
MIRROR_TIE = 1.0

# Mirror alignment for the fit in progress (:func:`mirror_alignment`); None: off.
_mirror_tie: float | None = None


@contextmanager
def mirror_alignment(on: bool) -> Iterator[None]:
    """Turn :func:`align_mirrors` on inside every motion update of the block (a whole fit).

    A fit-wide switch rather than an argument: the motion update is reached from a dozen
    sub-fits (merge scoring, splits, bridges), all of which must see the same rule.
    Forked workers (:mod:`.forked`) inherit it.
    """
    global _mirror_tie
    old = _mirror_tie
    _mirror_tie = MIRROR_TIE if on else None
    try:
        yield
    finally:
        _mirror_tie = old


def align_mirrors(st: StickState, R: np.ndarray, C_ab: np.ndarray, C_bb: np.ndarray, tie: float
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Give each flat stick the same mirror image in consecutive frames where the data allow.

    For a stick whose points lie in a plane with unit normal ``n`` (in its local
    frame), ``R`` and its mirror ``R (I - 2 n n^T)`` project the points alike, and
    they differ only through what lies off the plane (a joint below the pelvis's
    four markers, a head band's neck). Each frame's rotation is updated on its own,
    so while nothing off the plane is known the mirror flips from frame to frame
    with round-off and noise: measured on CMU 131_01 with the 41 markers placed,
    200 sweeps of the disconnected model gave the pelvis 234 flips and the head
    187, none at the start. A joint off such a plane is then predicted on one
    side in half the frames and on the other in the rest: no stick can share it,
    and the least-squares joint (:func:`.structure.joint_least_squares`) of the
    true hip is worse than one with a stick that is not flat (the thorax).

    Here the flips are undone where they cost nothing: a frame is *tied* when
    its two mirror images' energies differ by at most ``tie``; the projected
    normal ``R n`` flips between consecutive frames where its dot product is
    negative while both are at least 0.3 long (a true motion turns it by less
    than 90 degrees between frames; through a frame where the plane faces the
    camera, ``R n`` is short and its sign is left alone). Each run of tied
    frames is made continuous within itself (the parity of the flips since the
    run began), in whichever of its two consistent
    images has the lower total energy, and where those tie, the one that flips
    fewer frames. Continuing the frame before the run instead carried one
    frame's wrong image over the whole run: on a 60-frame random figure the fit
    lost 1200 in BIC and grew a fourth stick. Frames that are not tied keep what
    the energy chose. A tie-break is not an ascent:
    each frame it flips may lower the objective by up to ``tie / 2`` (the
    energy is twice a log-likelihood), so with alignment on the motion update is
    not monotone by that much.

    The rules run one stick at a time in one compiled pass over its frames
    (:func:`stickfigure._rotation_kernels.mirror_runs`; the numpy form took 1.0 ms
    a call on the human-sized figure's 15 sticks x 400 frames, 0.18 ms now, the same bits).

    Parameters
    ----------
    st : StickState
        Supplies the sticks' points (which are flat, and their planes).
    R : ndarray, shape (S, F, D, 3)
        The rotations just updated.
    C_ab, C_bb : ndarray, shapes (S, F, D, 3) and (S, F, 3, 3)
        Their energy's statistics (:func:`_motion_statistics`).
    tie : float
        Largest energy difference treated as a tie.

    Returns
    -------
    R : ndarray, shape (S, F, D, 3)
    changed : ndarray of bool, shape (S, F), or None when nothing changed
    """
    axes, flat = _principal_axes(st)
    counts = st.stick_sizes()
    idx = np.flatnonzero(flat & (counts >= 3))  # 1 or 2 points: no plane to mirror in
    F = R.shape[1]
    if idx.size == 0 or F < 2:
        return R, None
    n = np.ascontiguousarray(axes[idx, 0, 0])  # (k, 3): the minor axis, the plane's normal
    S, _, D = R.shape[:3]
    flat_R = np.ascontiguousarray(R, dtype=float).reshape(S * F, D, 3)
    Rm = np.empty((idx.size * F, D, 3))
    odd = np.empty((idx.size, F), dtype=bool)
    _rk.mirror_runs(flat_R, np.ascontiguousarray(C_ab, dtype=float).reshape(S * F, D, 3),
                    np.ascontiguousarray(C_bb, dtype=float).reshape(S * F, 3, 3), F, idx.astype(np.int64), n,
                    float(tie), Rm, odd)
    if not odd.any():
        return R, None
    Rm = Rm.reshape(idx.size, F, D, 3)
    Rk = R[idx]
    R = R.copy()
    R[idx] = np.where(odd[..., None, None], Rm, Rk)
    changed = np.zeros(R.shape[:2], bool)
    changed[idx] = odd
    return R, changed


def _keep_lower(R_old: np.ndarray, q_old: np.ndarray, R_new: np.ndarray, q_new: np.ndarray, C_ab: np.ndarray,
                C_bb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The new rotations (S, F, D, 3) and quaternions (S, F, 4) where their energy is not above the old, else the old.

    Also returns the old rotations' energies (S, F). One compiled pass
    (:func:`stickfigure._rotation_kernels.keep_lower`) for two energies and two selections.
    """
    batch, Ro, Ca, Cb = flat_rotation_batch(R_old, C_ab, C_bb)
    D = Ro.shape[1]
    Rn = np.ascontiguousarray(np.broadcast_to(R_new, batch + (D, 3)), dtype=float).reshape(-1, D, 3)
    qo = np.ascontiguousarray(np.broadcast_to(q_old, batch + (4,)), dtype=float).reshape(-1, 4)
    qn = np.ascontiguousarray(np.broadcast_to(q_new, batch + (4,)), dtype=float).reshape(-1, 4)
    R_out, q_out, e_old = np.empty_like(Ro), np.empty_like(qo), np.empty(Ro.shape[0])
    _rk.keep_lower(Ro, qo, Rn, qn, Ca, Cb, R_out, q_out, e_old)
    return R_out.reshape(batch + (D, 3)), q_out.reshape(batch + (4,)), e_old.reshape(batch)


def update_motions(st: StickState, obs: Observations, *, n_procrustes: int = 1, newton: bool = False,
                   global_search: bool = False, sticks: np.ndarray | None = None, use_polar: bool = True,
                   hold: np.ndarray | None | str = "auto", n_newton: int = 2, only_mirrors: bool = False,
                   collapse: bool = False, kappa: np.ndarray | None = None,
                   lam: np.ndarray | None = None) -> None:
    """Rotations and translations of every stick in every frame, jointly.

    The weighted problem ``min_{R,t} sum_n w_n |a_n - R b_n - t|^2`` over the
    stick's points (w = tau_w, visible only) and endpoints (w = tau_m) reduces,
    with ``t = a_bar - R b_bar``, to ``min_R -2 tr(R C_ab^T) + tr(R C_bb R^T)``,
    improved by :func:`procrustes_step` for all (stick, frame) pairs at once and
    then by a :func:`newton_step` (quadratic convergence where the
    Green-Gower iteration crawls: sticks whose points are nearly collinear); each
    new rotation is kept only where it lowers that energy, so the update is
    monotone. ``global_search`` runs :func:`best_rotations` instead of the Newton
    step, on the sticks in ``sticks`` (indices) or on all (``only_mirrors``: see
    :func:`best_rotations`). ``hold`` (S, F) marks (stick, frame) pairs whose
    rotation the frame cannot determine; ``"auto"`` (default) marks those of
    :func:`underdetermined_frames` (frames of a stick showing fewer than 3 of its
    points: with missing data the free rotations there let the stick's depth grow
    without bound). A held rotation is not solved for; it moves to the spherical
    interpolation of the stick's rotations in its nearest determined frames
    where that lowers the frame's energy, else it stays (so the update stays
    monotone). Translations are updated everywhere.

    ``collapse`` optimises the motions and the endpoint posteriors jointly (a
    larger block of the same coordinate ascent; derivation in docs/em.md
    section 8). For fixed M and vertex mean mu(v), the endpoint terms
    ``tau_m |mu(e) - M k|^2 + a_g |mu(e) - mu(v)|^2`` are minimised by
    :func:`update_endpoints`' mean and then equal ``tau_m a_g / (tau_m + a_g)
    |M k - mu(v)|^2``: the motion is fitted with every endpoint pulled to its
    vertex by that series weight, and mu(e) is set afterwards. The paper's
    order (mu(e) first, then M against it) makes each endpoint an anchor of
    weight tau_m at the stick's previous pose: where tau_m is ten times tau_w
    and an endpoint sits far from the points, a stick's rotation moves a
    small part of the way to the data per sweep.

    ``kappa`` (S,) adds a von Mises-Fisher chain prior on each stick's rotations
    (imputation only; :func:`.impute.rotation_concentration`): each frame's rotation
    is the MAP given its neighbours' current ones, all frames at once (a Jacobi
    step; frames in ``hold`` are held as above; :func:`.impute.refit_motions` holds
    only 1-2 point sticks when it passes ``kappa``). ``lam`` (S,) adds a Gaussian
    random-walk prior on each stick's centroid, also given its neighbours' (imputation
    only; :func:`.impute.centroid_concentration`): a stick that shows no point in a run
    of frames then follows its own path as well as its joints.
    """
    if isinstance(hold, str):
        hold = underdetermined_frames(st, obs) if hold == "auto" else None
    a_bar, b_bar, C_ab, C_bb = _motion_statistics(st, obs, collapse, kappa, lam)
    q0 = st._quat if st._quat is not None and st._quat_of is st.rot else rot_to_quat(complete_rotation(st.rot))
    R_new, q_new = procrustes_step(st.rot, C_ab, C_bb, n_outer=n_procrustes, quat=q0)
    R, q, old = _keep_lower(st.rot, q0, R_new, q_new, C_ab, C_bb)
    if global_search:
        axes, flat = _principal_axes(st)
        if sticks is None:
            R = best_rotations(R, C_ab, C_bb, axes, flat, use_polar=use_polar, n_newton=n_newton,
                               only_mirrors=only_mirrors)
            q = rot_to_quat(complete_rotation(R))
        else:
            R, q = R.copy(), q.copy()
            R[sticks] = best_rotations(R[sticks], C_ab[sticks], C_bb[sticks], axes[sticks], flat[sticks],
                                       use_polar=use_polar, n_newton=n_newton, only_mirrors=only_mirrors)
            q[sticks] = rot_to_quat(complete_rotation(R[sticks]))
    elif newton:
        R_n = newton_step(R, C_ab, C_bb)
        better = np.any(R_n != R, axis=(-1, -2))
        if better.any():
            R = R_n
            q = np.where(better[..., None], rot_to_quat(complete_rotation(R_n)), q)
    if hold is not None:  # rotations the frame cannot determine: interpolated, where that is better
        q_int = slerp_fill(q, ~hold)
        R_int = quat_to_rot(q_int)[..., :R.shape[-2], :]
        better = hold & (_rotation_energy(R_int, C_ab, C_bb) < old)
        R = np.where(hold[..., None, None], np.where(better[..., None, None], R_int, st.rot), R)
        q = np.where(hold[..., None], np.where(better[..., None], q_int, q0), q)
    if _mirror_tie is not None:  # mirror_alignment: tie-breaks by continuity (not monotone, see there)
        R, changed = align_mirrors(st, R, C_ab, C_bb, _mirror_tie)
        if changed is not None:  # only the flipped frames' quaternions change
            q = q.copy()
            q[changed] = rot_to_quat(complete_rotation(R[changed]))
    st.rot = R
    st._quat = q
    st._quat_of = R
    st.trans = a_bar - (R @ b_bar[..., None])[..., 0]
    if collapse:
        update_endpoints(st)  # the endpoint half of the joint step


def update_local(st: StickState, obs: Observations, priors: Priors) -> None:
    """Local coordinates of the points: ``(tau_w sum_f o R^T R + tau_p I) l = tau_w sum_f o R^T (w - t)``.

    (The paper's form divided by tau_w, with missing frames dropped from both sums.)
    """
    H, rhs = st.design(obs).local_normal_equations(st.rot, st.trans)
    st.local = np.linalg.solve(st.tau_w * H + priors.tau_p * np.eye(3), st.tau_w * rhs[..., None])[..., 0]


def update_ends(st: StickState, priors: Priors) -> None:
    """Local coordinates of the endpoints: ``(tau_m sum_f R^T R + tau_p I) k = tau_m sum_f R^T (mu(e) - t)``."""
    s = st.stick_of_end
    S, F, D = st.trans.shape
    Rf = st.rot.reshape(S, F * D, 3)
    RtR = np.swapaxes(Rf, 1, 2) @ Rf  # (S, 3, 3)
    H = st.tau_m * RtR[s] + priors.tau_p * np.eye(3)
    diff = (st.mu_e - st.trans[s]).reshape(-1, 1, F * D)
    rhs = st.tau_m * (diff @ Rf[s])[:, 0, :]
    st.ends = np.linalg.solve(H, rhs[..., None])[..., 0]


def update_precisions(st: StickState, obs: Observations, priors: Priors) -> None:
    """Maximum-likelihood tau_w, tau_m and tau_t (tau_w and tau_t capped at ``priors.max_precision``,
    tau_m at ``priors.max_tau_m_ratio * tau_w``).

    ``1/tau_w = sum o |w - R l - t|^2 / (D N_obs)``;
    ``1/tau_m = sum_{i,f} (|mu(e) - R k - t|^2 + D/tau(e)) / (D E S F)``;
    ``1/tau_t = sum_{j, f>1} (|mu(v_f) - mu(v_f-1)|^2 + D/tau(v_f) + D/tau(v_f-1)) / (D J (F-1))``.
    """
    D = st.n_dims
    F = st.n_frames
    cap = priors.max_precision
    des = st.design(obs)
    ss = des.residual_sq(st.rot, st.trans, st.local).sum()
    st.tau_w = float(min(D * des.n.sum() / max(ss, 1e-300), cap))
    eres = st.mu_e - st.end_predictions()
    ss = np.sum(eres * eres) + F * D * np.sum(1.0 / st.tau_e)
    # tau_m's bound follows tau_w's (max_tau_m_ratio), which is capped: a cap of its own at
    # max_precision would bind on real data whose tau_w is within 10x of it.
    st.tau_m = float(min(D * st.mu_e.shape[0] * F / max(ss, 1e-300), priors.max_tau_m_ratio * st.tau_w))
    if F > 1:
        dmu = np.diff(st.mu_v, axis=1)
        inv = 1.0 / st.tau_v
        ss = np.sum(dmu * dmu) + D * np.sum(inv[:, 1:] + inv[:, :-1])
        st.tau_t = float(min(D * st.n_vertices * (F - 1) / max(ss, 1e-300), cap))


def em_sweep(st: StickState, obs: Observations, priors: Priors, *, precisions: bool = True,
             local: bool = True, n_procrustes: int = 1, global_rotations: bool = False,
             use_polar: bool = True, hold: np.ndarray | None | str = "auto",
             collapse: bool = False, kappa: np.ndarray | None = None, lam: np.ndarray | None = None) -> None:
    """One EM iteration: E-step (endpoints, vertices, phi) then M-step (motions, L, K, precisions).

    Parameters
    ----------
    precisions : bool
        Re-estimate tau_w, tau_m, tau_t (off when scoring a block of a larger model
        or when imputing new frames with a trained model).
    local : bool
        Re-estimate L and K (off when imputing).
    global_rotations : bool
        Use the multi-start rotation search (:func:`best_rotations`) in this sweep
        (with the SVD start when ``use_polar``).
    hold : ndarray of bool, shape (S, F), "auto" or None
        Rotations the frames cannot determine (see :func:`update_motions`).
    collapse : bool
        Fit motions and endpoint posteriors jointly (see :func:`update_motions`).
    kappa : ndarray, shape (S,), optional
        A smoothness prior on each stick's rotations (see :func:`update_motions`).
    lam : ndarray, shape (S,), optional
        A smoothness prior on each stick's centroid (see :func:`update_motions`).
    """
    update_endpoints(st)
    update_vertices(st)
    update_phi(st, priors)
    update_motions(st, obs, n_procrustes=n_procrustes, global_search=global_rotations, use_polar=use_polar,
                   hold=hold, collapse=collapse, kappa=kappa, lam=lam)
    if local:
        update_local(st, obs, priors)
        update_ends(st, priors)
    if precisions:
        update_precisions(st, obs, priors)
