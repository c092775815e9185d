"""Method "yan-pollefeys": the stage-wise articulated-chain baseline of Ross et al.

Yan & Pollefeys, *Automatic kinematic chain building from feature trajectories
of articulated objects* (CVPR 2006), as summarised by Ross, Tarlow & Zemel
(section 2 and Fig. 7):

1. Segment the trajectories with the local subspace affinity (each
   trajectory's local subspace from its nearest neighbours, rank by model
   selection, affinity from principal angles:
   :func:`stickfigure.geometry.local_subspace_affinity`) and spectral
   clustering (:func:`stickfigure.segmentation.spectral_segments`), the number
   of parts estimated by a rigid-motion BIC over the clusterings for every
   count (:func:`select_n_segments`).
2. Fit each part's affine structure from motion
   (:func:`stickfigure.geometry.affine_factorization`, rank 3 + translation).
3. Connect the parts by the minimum spanning tree whose edge weights are the
   principal angles between the parts' motion subspaces (smallest angle by
   default): two parts sharing a joint share the joint's trajectory, so their
   subspaces intersect and the smallest angle is ~0.
4. Locate each joint at the intersection of the two motion subspaces (see
   :func:`joint_trajectories`).

Known failure (Ross et al., Fig. 7): parts whose motions are dependent without
being connected -- limbs moving in phase -- also have (nearly) intersecting
subspaces and get joined; the spanning tree then propagates the error.

"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

from .._validation import check_labels, check_positive
from ..skeleton import Skeleton, orient_tree
from ..trajectories import Trajectories
from .base import StickEstimator, register

__all__ = ["YanPollefeys", "select_n_segments", "motion_subspaces", "subspace_distances", "joint_trajectories"]


def motion_subspaces(xy: np.ndarray, labels: np.ndarray, n_parts: int, *, kappa: float = 1e-3,
                     random_state: Any = None) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Each part's affine structure from motion and the orthonormal basis of its motion subspace.

    Part ``s`` is factorised as ``x_pf = A_f l_p + t_f``
    (:func:`stickfigure.geometry.affine_factorization`, gaps handled there); its
    motion matrix is the (F*D, r+1) stack ``M_s = [A | t]`` and its motion
    subspace the column space of ``M_s`` (Yan & Pollefeys). The shape rank ``r``
    (at most 3, a rigid body) is chosen by model selection
    (:func:`stickfigure.geometry.estimate_rank` on the singular values of the
    part's gap-filled, per-frame-centred trajectories): a stick whose points
    are collinear or that only turns in one plane has a smaller subspace.

    Parameters
    ----------
    xy : ndarray, shape (P, F, D)
        Trajectories, NaN where missing.
    labels : ndarray of int, shape (P,)
    n_parts : int
    kappa : float
        Rank model-selection penalty.
    random_state : None, int or Generator

    Returns
    -------
    bases : list of ndarray, each (F*D, r_s + 1)
    ranks : ndarray of int, shape (S,)
        Shape ranks r_s.
    motions : ndarray, shape (S, F, D, 4)
        Rank-3 affine motions ``[A | t]`` (for the skeleton and its joints).
    local : ndarray, shape (P, 3)
        Rank-3 affine shapes (zeros for unassigned points).
    """
    from ..geometry import affine_factorization, estimate_rank

    P, F, D = xy.shape
    motions = np.zeros((n_parts, F, D, 4))
    local = np.zeros((P, 3))
    bases, ranks = [], []
    for s in range(n_parts):  # parts are few; each factorisation is vectorised
        idx = np.flatnonzero(labels == s)
        r3 = int(min(3, max(idx.size - 1, 1), F * D))
        fac = affine_factorization(xy[idx], rank=r3, random_state=random_state)
        motions[s, ..., :r3] = fac.motions[..., :r3]
        motions[s, ..., 3] = fac.motions[..., -1]
        local[idx, :r3] = fac.shape
        filled = np.where(np.isnan(xy[idx]), fac.predict(), xy[idx])
        centred = filled - filled.mean(axis=0, keepdims=True)
        sv = np.linalg.svd(centred.transpose(1, 2, 0).reshape(F * D, idx.size), compute_uv=False)
        r = max(1, min(r3, estimate_rank(sv, idx.size, kappa=kappa, max_rank=3)))
        M = fac.motions if r == r3 else affine_factorization(xy[idx], rank=r, random_state=random_state).motions
        U, sm, _ = np.linalg.svd(M.reshape(F * D, -1), full_matrices=False)
        bases.append(U[:, sm > sm[0] * 1e-12])
        ranks.append(r)
    return bases, np.asarray(ranks), motions, local


def subspace_distances(bases: list[np.ndarray], n_angles: int = 1) -> np.ndarray:
    """Pairwise distance between subspaces: the mean of their ``n_angles`` smallest principal angles.

    ``n_angles = 1`` is the smallest principal angle of Yan & Pollefeys (0 for
    intersecting subspaces).

    Returns
    -------
    ndarray, shape (S, S)
        Radians, symmetric, 0 on the diagonal.
    """
    S = len(bases)
    D = np.zeros((S, S))
    for i in range(S):
        for j in range(i + 1, S):
            ang = np.sort(scipy.linalg.subspace_angles(bases[i], bases[j]))
            D[i, j] = D[j, i] = float(np.mean(ang[:n_angles]))
    return D


def joint_trajectories(motions_p: np.ndarray, motions_c: np.ndarray, *, ridge: float = 1e-9,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Joint trajectory at the intersection of two parts' motion subspaces.

    Part ``s`` moves its local 3D points ``x`` to ``M_s [x; 1]`` (``M_s`` the
    (F*D, 4) stack of affine cameras ``[A_f | t_f]``); its motion subspace is the
    column space of ``M_s``. A joint is a point of both parts, so its trajectory
    ``j = M_p [x_p; 1] = M_c [x_c; 1]`` lies in the intersection, with the
    homogeneous coordinate fixed to 1 -- a spherical joint gives a 1-dimensional
    intersection (the joint's trajectory; a hinge gives a 2-dimensional one, the
    trajectories of the points on its axis). With noise the intersection is
    solved in the least-squares sense::

        min_{x_p, x_c}  |M_p [x_p; 1] - M_c [x_c; 1]|^2  (+ ridge |x|^2)

    i.e. ``[A_p, -A_c] [x_p; x_c] = t_c - t_p``, a (F*D) x 6 linear system solved
    in closed form. When the solution is not unique (a hinge, or parts that do
    not turn relative to each other) the small ridge picks the solution closest
    to the two parts' centroids (the origins of their centred local frames).

    Parameters
    ----------
    motions_p, motions_c : ndarray, shape (E, F, D, 4)
        Affine motions of parent and child parts.
    ridge : float
        Relative Tikhonov weight.

    Returns
    -------
    x_p, x_c : ndarray, shape (E, 3)
        The joint in each part's local frame.
    joints : ndarray, shape (E, F, D)
        Its trajectory (mean of the two parts' predictions).
    rms : ndarray, shape (E,)
        RMS distance between the two predictions: ~noise for a true joint.
    """
    E, F, D, _ = motions_p.shape
    Ap = motions_p[..., :3].reshape(E, F * D, 3)
    Ac = motions_c[..., :3].reshape(E, F * D, 3)
    rhs = (motions_c[..., 3] - motions_p[..., 3]).reshape(E, F * D)
    G = np.concatenate([Ap, -Ac], axis=2)  # (E, F*D, 6)
    GtG = np.einsum("eki,ekj->eij", G, G)
    lam = ridge * np.trace(GtG, axis1=1, axis2=2)[:, None, None] / 6 + 1e-300
    x = np.linalg.solve(GtG + lam * np.eye(6), np.einsum("eki,ek->ei", G, rhs)[..., None])[..., 0]
    x_p, x_c = x[:, :3], x[:, 3:]
    jp = np.einsum("efdk,ek->efd", motions_p[..., :3], x_p) + motions_p[..., 3]
    jc = np.einsum("efdk,ek->efd", motions_c[..., :3], x_c) + motions_c[..., 3]
    rms = np.sqrt(np.mean(np.sum((jp - jc) ** 2, axis=-1), axis=1))
    return x_p, x_c, 0.5 * (jp + jc), rms


def select_n_segments(xy: np.ndarray, affinity: np.ndarray, *, max_segments: int = 12, rank: int = 3,
                      random_state: Any = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Spectral clusterings of the LSA for k = 1..max_segments; the count by a rigid-motion BIC.

    Every k gets a spectral clustering of ``affinity``
    (:func:`stickfigure.segmentation.spectral_segments`); the partition with the
    lowest Bayesian information criterion of rigid affine parts wins
    (:func:`stickfigure.segmentation.partition_bic`: residual to each part's
    rank-``rank`` affine fit over sigma^2, plus F*D*(rank+1) log N per part).

    Why not the eigengap of the affinity: ``exp(-sum sin^2)`` of principal
    angles stays between ``exp(-4)`` and 1, so every pair of trajectories is
    strongly linked and the normalised Laplacian's largest gap is after its
    first eigenvalue -- one part -- on every random figure and every Hopkins
    sequence we tried.

    sigma is the scale a rigid part actually fits to: the local tracking noise
    (:func:`stickfigure.geometry.noise_level` through the rigid hypotheses of
    :func:`stickfigure.geometry.rigid_affinity`) times the 90th-percentile misfit
    of those rigid hypotheses when it exceeds 1. On synthetic figures that
    factor is ~1.5 (parts fit to the noise); on real footage (perspective,
    non-rigid clothing) it is 5-30, and judging parts against the bare tracking
    noise would split every body into many.

    Parameters
    ----------
    xy : ndarray, shape (P, F, D)
    affinity : ndarray, shape (P, P)
        The local subspace affinity.
    max_segments : int
    rank : int
        Affine rank of one rigid part.
    random_state : None, int or Generator

    Returns
    -------
    labels : ndarray of int, shape (P,)
    info : dict
        ``bic`` per k (from 1), ``chosen``, ``sigma`` and ``misfit_level``.
    """
    from .._validation import check_random_state
    from ..geometry import _complete_for_affinity, measurement_matrix, rigid_affinity
    from ..segmentation import _bic, _noise_regime, spectral_segments

    rng = check_random_state(random_state)
    seed = int(rng.integers(2**31 - 1))
    P = xy.shape[0]
    xyc = _complete_for_affinity(np.asarray(xy, float))
    X = measurement_matrix(xyc)
    _, hyp = rigid_affinity(xyc, rank=rank, random_state=seed, return_info=True)
    sig2 = float(hyp["sigma"]) ** 2
    _, level = _noise_regime(X, np.zeros(P, np.int64), hyp["inliers"], rank, sig2)
    level = float(level) if np.isfinite(level) else 1.0
    sig2_eff = max(sig2 * max(level, 1.0), 1e-300)
    kmax = int(min(max_segments, max(1, P // (rank + 1))))
    best: tuple[float, np.ndarray] | None = None
    bics = []
    for k in range(1, kmax + 1):
        lab = np.asarray(spectral_segments(affinity, k, random_state=seed), dtype=np.int64)
        b = float(_bic(X, lab, rank, sig2_eff))
        bics.append(round(b, 3))
        if best is None or b < best[0]:
            best = (b, lab)
    assert best is not None
    labels = best[1]
    return labels, {"bic": bics, "chosen": int(labels.max()) + 1, "sigma": float(np.sqrt(sig2)),
                    "misfit_level": round(level, 3)}


@register("yan-pollefeys")
class YanPollefeys(StickEstimator):
    """Yan & Pollefeys: LSA + spectral clustering, then a minimum spanning tree of subspace angles.

    Parameters
    ----------
    n_segments : int, optional
        Number of parts; estimated by :func:`select_n_segments` when omitted.
    labels : array_like of int, shape (P,), optional
        A given segmentation (skips step 1), e.g. the true one.
    max_segments : int
        Upper bound of the estimated number of parts.
    n_neighbors : int, optional
        Neighbours of each trajectory's local subspace (LSA default when omitted).
    kappa : float
        Rank model-selection penalty (local subspaces and motion subspaces).
    n_angles : int
        Edge weight = mean of the ``n_angles`` smallest principal angles (1: the
        smallest, as in the paper).
    random_state : None, int or Generator
        Seeds the spectral clustering.
    progress : bool
        Unused; accepted for a uniform interface.

    Attributes
    ----------
    skeleton_ : Skeleton
    subspace_angles_ : ndarray, shape (S, S)
        The edge weights (radians).
    affinity_ : ndarray, shape (P, P) or None
        The local subspace affinity (None when labels were given).
    """

    min_points = 2
    min_frames = 2

    def __init__(self, n_segments: int | None = None, *, labels: Any = None, max_segments: int = 12,
                 n_neighbors: int | None = None, kappa: float = 1e-3, n_angles: int = 1,
                 random_state: Any = None, progress: bool = False) -> None:
        self.n_segments = n_segments
        self.labels = labels
        self.max_segments = max_segments
        self.n_neighbors = n_neighbors
        self.kappa = kappa
        self.n_angles = n_angles
        self.random_state = random_state
        self.progress = progress

    def _fit(self, traj: Trajectories, rng: np.random.Generator) -> Skeleton:
        from ..geometry import local_subspace_affinity

        if self.n_segments is not None:
            check_positive(self.n_segments, "n_segments", integer=True)
        check_positive(self.max_segments, "max_segments", integer=True)
        check_positive(self.kappa, "kappa")
        check_positive(self.n_angles, "n_angles", integer=True)
        xy = traj.xy
        P, F, D = xy.shape
        info: dict[str, Any] = {}
        affinity = None
        if self.labels is not None:
            lab = check_labels(self.labels, P, "labels")
            info["segmentation"] = "given"
        else:
            if P < 5:
                raise ValueError(f"yan-pollefeys needs at least 5 points to segment, got {P}")
            from ..segmentation import spectral_segments

            affinity = local_subspace_affinity(xy, n_neighbors=self.n_neighbors, kappa=self.kappa)
            if self.n_segments is not None:
                lab = np.asarray(spectral_segments(affinity, self.n_segments, random_state=rng), dtype=np.int64)
            else:
                lab, count_info = select_n_segments(xy, affinity, max_segments=self.max_segments,
                                                    random_state=rng)
                info["n_segments_selection"] = count_info
            info["segmentation"] = "local_subspace_affinity+spectral"
        ids = np.unique(lab[lab >= 0])
        if ids.size == 0:
            raise ValueError("labels assign no point to a part")
        labels = np.full(P, -1, np.int64)
        for k, s in enumerate(ids):
            labels[lab == s] = k
        S = int(ids.size)
        info["segment_ids"] = ids.tolist()

        # Steps 2-3: each part's structure from motion, then the minimum spanning tree of
        # the principal angles between the parts' motion subspaces.
        bases, ranks, motions, local = motion_subspaces(xy, labels, S, kappa=self.kappa, random_state=rng)
        if S >= 2:
            dist = subspace_distances(bases, int(self.n_angles))
            tree = _minimum_spanning_tree(dist)
        else:
            dist = np.zeros((1, 1))
            tree = []
        sizes = np.bincount(labels[labels >= 0], minlength=S)
        edges = orient_tree(tree, int(np.argmax(sizes)), S)

        # Step 4: joints at the subspace intersections.
        if edges:
            par = [p for p, _ in edges]
            chi = [c for _, c in edges]
            _, _, joints, joint_rms = joint_trajectories(motions[par], motions[chi])
        else:
            joints, joint_rms = np.zeros((0, F, D)), np.zeros(0)
        self.subspace_angles_ = dist
        self.affinity_ = affinity
        info.update(n_segments=S, subspace_ranks=ranks.tolist(), joint_rms=joint_rms.tolist(),
                    subspace_angles=dist.tolist())
        state = {"subspace_angles": dist, "subspace_ranks": ranks, "joint_rms": joint_rms}
        return Skeleton(method=self.method_name, labels=labels, n_sticks=S, edges=edges, joints=joints,
                        motions=motions, local=local, n_dims=D, state=state, info=info)

    @classmethod
    def impute_skeleton(cls, skeleton: Skeleton, traj: Trajectories) -> np.ndarray:
        """Refit each part's affine motions to the visible points of ``traj`` (shapes fixed) and predict.

        Returns
        -------
        ndarray, shape (P, F, D)
        """
        from ..geometry import fit_motions, predict_points

        if skeleton.local is None:
            raise ValueError("this yan-pollefeys skeleton has no local shapes to impute with")
        motions = fit_motions(traj.xy, skeleton.local, skeleton.labels, skeleton.n_sticks)
        return predict_points(motions, skeleton.local, skeleton.labels)


def _minimum_spanning_tree(dist: np.ndarray) -> list[tuple[int, int]]:
    """Edges (i < j) of the minimum spanning tree of a symmetric distance matrix (networkx, Kruskal)."""
    import networkx as nx

    S = dist.shape[0]
    g = nx.Graph()
    g.add_nodes_from(range(S))
    for i in range(S):
        for j in range(i + 1, S):
            g.add_edge(i, j, weight=float(dist[i, j]))
    tree = nx.minimum_spanning_tree(g, weight="weight", algorithm="kruskal")
    return sorted((min(u, v), max(u, v)) for u, v in tree.edges())
