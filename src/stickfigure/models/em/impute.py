"""Imputation with a learned structure, and the held-out check built on it.

:func:`start_state` and :func:`refit_motions` are what :meth:`Skeleton.impute`
runs for em (docs/em.md section 8): L, K, G and R fixed, motions re-estimated
from the visible points only. :func:`heldout_error` runs the same on a model's
own training data with some entries hidden, which measures how well a
structure predicts points it does not see (section 6, the held-out check of
small sticks).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .initialise import interpolate_rotations
from .model import Observations, Priors, StickState, chain_degree
from .updates import FLAT_RATIO, MIRROR_TIE, em_sweep, update_endpoints

__all__ = ["start_state", "chain_mirrors", "refit_motions", "heldout_error", "rotation_concentration",
           "centroid_concentration", "frame_scales"]

# A stick's visible points tell its image scale only when they span a plane: their second
# principal spread must be at least this fraction of the first (a line shows its length
# foreshortened, never more, so it bounds the scale from below only).
SCALE_MIN_SPREAD = 0.2


def start_state(labels: np.ndarray, local: np.ndarray, ends: np.ndarray, vertex_of: np.ndarray,
                alpha: np.ndarray, beta: np.ndarray, precisions: tuple[float, float, float], alpha0: float,
                obs: Observations, *, chain: bool = True) -> StickState:
    """A state for the frames of ``obs`` (normalised units): fixed L, K, G, R; motions by Procrustes.

    Parameters
    ----------
    labels : (P,) stick of every point; local : (P, 3) L; ends : (ES, 3) K; vertex_of : (ES,) G
    alpha, beta : (J,) the trained posterior of the vertex precisions phi
    precisions : (tau_w, tau_m, tau_t) of training
    alpha0 : the Gamma prior's shape (phi's posterior is rescaled to the new frame count)
    obs : the new observations
    chain : keep the Procrustes rotations of consecutive frames in one mirror branch where
        the visible points are coplanar (:func:`chain_mirrors`)

    Motions start from a per-frame Procrustes fit of each stick's shape to its visible
    points where it shows at least 4 points and 60 % of them, and those are not nearly
    coplanar; elsewhere the rotation is interpolated (slerp) and the translation taken
    from the visible points (interpolated where none is). Where the frames so fitted show
    coplanar points (a 3-point stick always does), a frame's fit and its mirror through
    that plane fit them equally; with ``chain``, in frames where the two fit within
    ``updates.MIRROR_TIE`` in energy (``tau_w`` times the squared residual), the one nearer
    the previous frame's is taken, so that the slerp between frames does not cross from
    one branch to the other. Vertices start at the mean of their endpoints' predictions.
    """
    from ...geometry import orthogonal_procrustes_rows

    mask = obs.mask > 0
    S = int(labels.max()) + 1
    P, F, D = obs.w.shape
    tau_w, tau_m, tau_t = (float(v) for v in precisions)
    rot = np.zeros((S, F, D, 3))
    trans = np.zeros((S, F, D))
    for s in range(S):  # one batched Procrustes per stick over all frames
        idx = np.flatnonzero(labels == s)
        m = mask[idx].T.astype(float)  # (F, n)
        cnt = m.sum(axis=1)
        if not cnt.any():  # never visible here (the held-out check may hide all of a small stick):
            rot[s] = np.eye(3)[:D]  # no pose to start from; its joints, if any, move it in EM
            continue
        # A rotation from a few points can sit in the wrong mirror branch: start those frames
        # from the interpolation of the well-observed ones, and let EM refine them locally.
        good = cnt >= max(4, int(np.ceil(0.6 * idx.size)))
        w = obs.w[idx].transpose(1, 2, 0)  # (F, D, n), 0 where missing
        cw = np.maximum(cnt, 1)
        abar = np.einsum("fdn,fn->fd", w, m) / cw[:, None]
        lbar = (m @ local[idx]) / cw[:, None]  # (F, 3)
        A = (w - abar[..., None]) * m[:, None, :]
        B = (local[idx].T[None] - lbar[..., None]) * m[:, None, :]
        # The visible points alone may be nearly coplanar where the stick is not: their mirror
        # image fits them as well and puts the hidden ones elsewhere. Such frames are
        # interpolated like the sparse ones.
        lam = np.linalg.eigvalsh(B @ np.swapaxes(B, 1, 2))  # (F, 3), ascending
        Lc = local[idx] - local[idx].mean(axis=0)
        lam_all = np.linalg.eigvalsh(Lc.T @ Lc)
        ratio_all = lam_all[0] / max(lam_all[2], 1e-300)
        ratio = lam[:, 0] / np.maximum(lam[:, 2], 1e-300)
        good &= ratio >= min(FLAT_RATIO ** 2, 0.5 * ratio_all)
        if not good.any():
            good = cnt >= max(cnt.max(), 1)
        R = np.zeros((F, D, 3))  # the other frames are interpolated: not solved for
        R[good] = orthogonal_procrustes_rows(A[good], B[good])
        if chain and D == 2 and good.any():
            # Visible points in a plane (every frame of a 3-point stick) fit a rotation and its
            # mirror through that plane equally, and the solver picks either: a slerp between
            # frames of the two branches swings the points off the plane (and the endpoints)
            # far away. A frame is tied when the mirror through the plane of least spread of
            # its visible points fits them within MIRROR_TIE in energy (training's rule).
            # (Two visible points lie in every plane through their line: the mirror through any
            # of them fits alike, and the chain takes the one of least turn from the frame before.)
            Ag, Bg, Rg = A[good], B[good], R[good]
            vec = np.linalg.eigh(Bg @ np.swapaxes(Bg, 1, 2))[1][:, :, 0]  # (n_good, 3) plane normals
            Mg = Rg - 2.0 * np.einsum("kdi,ki,kj->kdj", Rg, vec, vec)
            energy = [tau_w * np.sum((Ag - X @ Bg) ** 2, axis=(1, 2)) for X in (Rg, Mg)]
            tied = np.abs(energy[1] - energy[0]) <= MIRROR_TIE
            R[good] = chain_mirrors(Rg, tied, vec[tied])
        R = interpolate_rotations(R, good)
        t = abar - np.einsum("fdk,fk->fd", R, lbar)
        seen = cnt > 0
        if not seen.all():  # no visible point: translation interpolated between frames that have one
            si = np.flatnonzero(seen)
            for d in range(D):
                t[~seen, d] = np.interp(np.flatnonzero(~seen), si, t[si, d])
        rot[s], trans[s] = R, t
    vertex_of = np.asarray(vertex_of, np.int64)
    J = int(vertex_of.max()) + 1
    a = np.asarray(alpha, float) / np.asarray(beta, float)
    st = StickState(labels=labels.copy(), vertex_of=vertex_of.copy(), rot=rot, trans=trans, local=local.copy(),
                    ends=ends.copy(), mu_e=np.zeros((ends.shape[0], F, D)), tau_e=tau_m + a[vertex_of],
                    mu_v=np.zeros((J, F, D)), tau_v=np.ones((J, F)), alpha=np.asarray(alpha, float).copy(),
                    beta=np.asarray(beta, float).copy(), tau_w=tau_w, tau_m=tau_m, tau_t=tau_t)
    pred = st.end_predictions()
    n = np.bincount(vertex_of, minlength=J).astype(float)
    sums = np.zeros((J, F, D))
    np.add.at(sums, vertex_of, pred)
    st.mu_v = sums / n[:, None, None]
    st.tau_v = (a * n)[:, None] + tau_t * chain_degree(F)[None, :]
    # Scale phi's posterior to the new number of frames, keeping its mean.
    st.alpha = float(alpha0) + 0.5 * D * F * n
    st.beta = st.alpha / a
    update_endpoints(st)
    return st


def refit_motions(st: StickState, obs: Observations, priors: Priors, settings: Any, n_iter: int, *,
                  collapse: bool = False, kappa: np.ndarray | None = None,
                  lam: np.ndarray | None = None) -> StickState:
    """``n_iter`` EM iterations with L, K, the structure and the precisions fixed (in place).

    In frames where a stick's visible points and its joints (endpoints on a vertex
    shared with another stick) number fewer than 3, its rotation keeps its start (the
    model has no prior on motions, so such a frame cannot pin it down: a turn about
    the line through two points, a mirror) while its translation is updated; with
    ``kappa`` only sticks of 1 or 2 points are so held. A
    2-point stick with both ends jointed is thus fitted in every frame that shows one
    of its points (holding it instead kept its rotation at the interpolation between
    frames that show both, which a long occlusion makes a guess).
    Every ``settings.resample_every`` sweeps, except in the last ones, the multi-start
    rotation search of training runs too: a rotation fitted to a few nearly coplanar
    points can sit in the mirror branch, and the joints (endpoint terms) tell the
    branches apart. ``collapse`` updates motions and endpoints as one block, and
    ``kappa`` (S,) adds a smoothness prior on each stick's rotations
    (:func:`.updates.update_motions`, :func:`rotation_concentration`; docs/em.md section 8),
    and ``lam`` (S,) one on each stick's centroid (:func:`centroid_concentration`).
    """
    # A joint (an endpoint on a vertex shared with another stick) pins a point of the stick too.
    joined = st.joints_per_stick()
    hold = st.design(obs).n + joined[:, None] < 3
    if kappa is not None:
        # With the rotation prior every frame has a posterior. A stick of 3 or more points is then
        # released: its neighbours' rotations, its joints and its path place it. One of 1-2
        # points turns freely about its line but for that prior, which training's mirror flips
        # can make weak, and stays held (docs/em.md section 8).
        hold &= (st.stick_sizes() < 3)[:, None]
    every = max(int(settings.resample_every), 1) if settings.resample_every else 10
    for it in range(n_iter):
        em_sweep(st, obs, priors, precisions=False, local=False, n_procrustes=settings.n_procrustes,
                 hold=hold, global_rotations=it % every == 0 and it < n_iter - every, collapse=collapse,
                 kappa=kappa, lam=lam)
    return st


def heldout_error(st: StickState, obs: Observations, priors: Priors, settings: Any, hidden: np.ndarray,
                  n_iter: int = 50) -> np.ndarray:
    """Squared error of a model's prediction of the entries ``hidden`` from the others.

    The model's L, K, G, R and precisions are kept; its motions are re-estimated
    from the visible entries as in imputation (:func:`start_state`,
    :func:`refit_motions`), so nothing it learned from a hidden entry's own frame
    reaches the prediction except through the time-invariant shapes. The motion
    update is the paper's order without the rotation prior, and the start without the
    mirror chain (``Skeleton.impute``'s defaults differ): the held-out check's margins
    were measured with them, and the new update changed the CMU skeletons both ways
    (docs/em.md section 11).

    Parameters
    ----------
    hidden : ndarray of bool, shape (P, F)
        Entries to hide (only observed ones count).

    Returns
    -------
    ndarray, shape (P,)
        Each point's ``sum over its hidden observed entries |w - R l - t|^2``
        (normalised units).
    """
    hid = np.asarray(hidden, bool) & (obs.mask > 0)
    keep = obs.mask * ~hid
    sub = Observations(obs.w * keep[..., None], keep)
    start = start_state(st.labels, st.local, st.ends, st.vertex_of, st.alpha, st.beta,
                        (st.tau_w, st.tau_m, st.tau_t), priors.alpha0, sub, chain=False)
    refit_motions(start, sub, priors, settings, n_iter)
    err = np.sum((start.point_predictions() - obs.w) ** 2, axis=2)
    return np.sum(np.where(hid, err, 0.0), axis=1)


def chain_mirrors(R: np.ndarray, flat: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Consecutive frames' rotations put in the same mirror branch where the data leave it open.

    Parameters
    ----------
    R : ndarray, shape (K, 2, 3)
        Orthonormal-row rotations of one stick in K frames, in time order.
    flat : ndarray of bool, shape (K,)
        Frames whose visible points lie in a plane, so that ``R`` and its mirror
        ``R (I - 2 n n^T)`` (``n`` the plane's normal in the stick's frame) fit them alike
        (:func:`start_state` asks for a tie in energy).
    normals : ndarray, shape (flat.sum(), 3)
        Unit normal of that plane in each flat frame.

    Returns
    -------
    ndarray, shape (K, 2, 3)
        Each flat frame takes whichever of its two rotations is nearer the previous
        frame's choice (the angle between them); frames that are not flat are kept and
        anchor the chain. The choice is made relative to the previous frame's own
        solution and carried forward as a parity (exact when consecutive flat frames
        share the plane, as every frame of a 3-point stick does), so it is vectorised
        over frames.
    """
    R = np.asarray(R, float)
    flat = np.asarray(flat, bool)
    K = R.shape[0]
    if K < 2 or not flat.any():
        return R.copy()
    n = np.zeros((K, 3))
    n[flat] = normals
    M = R - 2.0 * np.einsum("kdi,ki,kj->kdj", R, n, n)  # R (I - 2 n n^T); = R where not flat

    def full(X: np.ndarray) -> np.ndarray:  # (K, 3, 3): the rows and their cross product
        return np.concatenate([X, np.cross(X[:, 0], X[:, 1])[:, None]], axis=1)

    Rf, Mf = full(R), full(M)
    keep = np.einsum("kij,kij->k", Rf[:-1], Rf[1:])  # tr(A^T B) = 1 + 2 cos(angle): larger is nearer
    swap = np.einsum("kij,kij->k", Rf[:-1], Mf[1:])
    flip = np.concatenate([[False], flat[1:] & (swap > keep)])
    count = np.cumsum(flip)
    # The parity restarts at every anchor (a frame that is not flat keeps its own branch).
    anchor = np.maximum.accumulate(np.where(~flat, np.arange(K), -1))
    parity = (count - np.where(anchor >= 0, count[np.maximum(anchor, 0)], 0)) % 2 == 1
    return np.where(parity[:, None, None], M, R)


def rotation_concentration(rot: np.ndarray) -> np.ndarray:
    """Concentration kappa (S,) of a von Mises-Fisher chain on each stick's rotations, from motions.

    The prior ``p(R_f | R_f-1) ~ exp(kappa tr(R_f R_f-1^T))`` over the D rows the projection
    sees (docs/em.md section 8). For a small turn omega between frames, ``D - tr`` is
    ``omega_z^2 + (omega_x^2 + omega_y^2) / 2`` for D = 2, so the prior puts variance
    ``1 / (2 kappa)`` on the turn in the image plane; matched to the trained motions'
    ``E[D - tr]`` (= 2 sigma^2 for an isotropic turn of variance sigma^2 per axis) that is
    ``kappa = 1 / E[D - tr]``. A mirror flip between frames (a flat stick's two equal fits)
    counts as a large turn, which only weakens the prior.

    Parameters
    ----------
    rot : ndarray, shape (S, F, D, 3)
        Rotations with orthonormal rows (the trained motions).

    Returns
    -------
    ndarray, shape (S,)
        0 where there are fewer than two frames.
    """
    rot = np.asarray(rot, float)
    if rot.ndim != 4 or rot.shape[-1] != 3:
        raise ValueError(f"rot must have shape (S, F, D, 3), got {rot.shape}")
    S, F, D, _ = rot.shape
    if F < 2:
        return np.zeros(S)
    tr = np.einsum("sfij,sfij->sf", rot[:, 1:], rot[:, :-1])
    return 1.0 / np.maximum(np.mean(D - tr, axis=1), 1e-12)


def centroid_concentration(rot: np.ndarray, trans: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Precision lam (S,) of a Gaussian random walk on each stick's centroid, from motions.

    The prior ``p(c_f | c_f-1) ~ exp(-lam |c_f - c_f-1|^2 / 2)`` on the centroid
    ``c_f = R_f lbar + t_f`` of the stick's points in the image (D coordinates), matched to
    the trained motions: for steps of variance sigma^2 per coordinate ``E|c_f - c_f-1|^2 =
    D sigma^2``, so ``lam = 1 / sigma^2 = D / E|c_f - c_f-1|^2``. The centroid, unlike the
    local origin, does not move when a flat stick's pose flips to its mirror image or a
    stick turns about its own points (docs/em.md section 8).

    Parameters
    ----------
    rot : ndarray, shape (S, F, D, 3)
        Rotations with orthonormal rows (the trained motions).
    trans : ndarray, shape (S, F, D)
        Translations, in the units ``lam`` is wanted in.
    centroids : ndarray, shape (S, 3)
        Each stick's mean local coordinates, same units.

    Returns
    -------
    ndarray, shape (S,)
        0 where there are fewer than two frames.
    """
    rot, trans, centroids = (np.asarray(a, float) for a in (rot, trans, centroids))
    if rot.ndim != 4 or rot.shape[-1] != 3:
        raise ValueError(f"rot must have shape (S, F, D, 3), got {rot.shape}")
    S, F, D, _ = rot.shape
    if trans.shape != (S, F, D) or centroids.shape != (S, 3):
        raise ValueError(f"trans must have shape {(S, F, D)} and centroids {(S, 3)}, got {trans.shape} and "
                         f"{centroids.shape}")
    if F < 2:
        return np.zeros(S)
    c = np.einsum("sfdj,sj->sfd", rot, centroids) + trans
    step = np.mean(np.sum(np.diff(c, axis=1) ** 2, axis=-1), axis=1)
    return D / np.maximum(step, 1e-12)


def frame_scales(labels: np.ndarray, local: np.ndarray, xy: np.ndarray, *,
                 min_spread: float = SCALE_MIN_SPREAD) -> np.ndarray:
    """The figure's image scale in each frame, against the learned shapes of its sticks.

    Under a weak-perspective camera a stick's points are ``c_f R l + t`` with ``R`` of
    orthonormal rows and ``c_f`` the frame's scale (the model's cameras have ``c_f = 1``).
    For one stick and frame, take its visible points' local coordinates about their
    mean, ``U`` (n, 2) along their two principal axes, and fit the 2 x 2 affine map ``A``
    from ``U`` to the centred image points by least squares. The map is ``c R B`` with
    ``B`` (3, 2) the orthonormal axes, and ``R B`` has singular values 1 and ``cos theta``
    (theta the tilt of that plane out of the image), so the largest singular value of
    ``A`` is ``c``: closed form, unlike a fit of ``c`` after the rotations, where a
    stick turned out of the image plane already accounts for a smaller image. A frame's
    scale is the median over its sticks of those values, each weighted by its visible
    points; frames without a stick showing at least 3 points that span a plane
    (second principal spread at least ``min_spread`` of the first) are interpolated in
    time (1 where no frame has one).

    Parameters
    ----------
    labels : ndarray of int, shape (P,)
        Stick of every point.
    local : ndarray, shape (P, 3)
        The points' local coordinates (the learned stick shapes), in the units of ``xy``.
    xy : ndarray, shape (P, F, 2)
        Image trajectories, NaN where missing.
    min_spread : float
        See above.

    Returns
    -------
    ndarray, shape (F,)
        Positive scales; 1 where the image is as large as the shapes.
    """
    labels = np.asarray(labels)
    local = np.asarray(local, float)
    xy = np.asarray(xy, float)
    if xy.ndim != 3 or xy.shape[2] != 2 or local.shape != (xy.shape[0], 3) or labels.shape != (xy.shape[0],):
        raise ValueError(f"need labels (P,), local (P, 3) and xy (P, F, 2); got {labels.shape}, {local.shape}, "
                         f"{xy.shape}")
    seen = ~np.isnan(xy[..., 0])  # (P, F)
    F = xy.shape[1]
    logs, weights = [], []
    for s in np.unique(labels[labels >= 0]):  # one batched fit per stick over all frames
        idx = np.flatnonzero(labels == s)
        if idx.size < 3:
            continue
        m = seen[idx].T.astype(float)  # (F, n)
        cnt = m.sum(axis=1)
        cw = np.maximum(cnt, 1.0)
        L = local[idx]
        Lc = (L[None] - ((m @ L) / cw[:, None])[:, None]) * m[..., None]  # (F, n, 3) about the visible mean
        x = np.where(seen[idx].T[..., None], xy[idx].transpose(1, 0, 2), 0.0)  # (F, n, 2)
        Xc = (x - (np.einsum("fnd,fn->fd", x, m) / cw[:, None])[:, None]) * m[..., None]
        lam, V = np.linalg.eigh(np.einsum("fni,fnj->fij", Lc, Lc))  # ascending
        ok = (cnt >= 3) & (lam[:, 1] >= min_spread ** 2 * lam[:, 2]) & (lam[:, 2] > 0)
        U = Lc @ V[..., [2, 1]]  # (F, n, 2)
        UtU = np.einsum("fni,fnj->fij", U, U)
        UtU[~ok] = np.eye(2)
        A = np.einsum("fnd,fni->fdi", Xc, U) @ np.linalg.inv(UtU)  # (F, 2, 2)
        top = np.linalg.svd(A, compute_uv=False)[:, 0]
        ok &= top > 0
        logs.append(np.where(ok, np.log(np.where(ok, top, 1.0)), 0.0))
        weights.append(np.where(ok, cnt, 0.0))
    if not logs:
        return np.ones(F)
    lg, wt = np.array(logs), np.array(weights)  # (S', F)
    # Weighted median over the sticks of every frame at once: sort each frame's values and
    # take the first whose cumulative weight reaches half the frame's total.
    order = np.argsort(lg, axis=0)
    lg_s, cum = np.take_along_axis(lg, order, axis=0), np.cumsum(np.take_along_axis(wt, order, axis=0), axis=0)
    total = cum[-1]
    good = total > 0
    if not good.any():
        return np.ones(F)
    pick = np.argmax(cum >= 0.5 * total[None], axis=0)
    med = lg_s[pick, np.arange(F)]
    f = np.arange(F)
    return np.exp(np.interp(f, f[good], med[good]))
