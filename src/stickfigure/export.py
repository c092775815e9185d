"""Where a learned skeleton is in every frame, its joint angles, and a BVH export.

Three things live here, all built on one computation, :func:`pose`:

* :func:`pose` places the sticks and joints of a :class:`~stickfigure.skeleton.Skeleton`
  in every frame of its training data or of new trajectories of the same points;
  the pictures (:mod:`stickfigure.plot`) draw what it returns.
* :func:`joint_angles` / :func:`write_angles_csv`: per frame and per joint, the
  angle between the two joined sticks.
* :func:`write_bvh`: a Biovision Hierarchy file of the skeleton and its motion,
  which animation tools open and :func:`stickfigure.load` reads back.

Definitions
-----------
**Tree orientation.** The stick tree is rooted as :meth:`Skeleton.parents` does
(each component at its largest stick). For the joint of edge ``e`` the *parent
stick* is the one nearer the root, the *child stick* the other.

**Positions used.** When the skeleton has stick motions (``motions`` and
``local``), the motions are re-fitted to the given trajectories
(:func:`stickfigure.geometry.fit_motions`, the structure kept fixed) and missing
points take their predicted positions, so every stick is placed in every frame.
Without ``traj`` the training motions are used. A skeleton without motions
uses the observed points only (a stick with no visible point in a frame is
unknown there).

**Joints on new frames.** The method's joint positions are known for its
training frames, and are used as they are when ``traj`` holds those frames
(recognised by the stored motions fitting its points as well as re-fitted
ones do). Each joint is rigidly attached to both of its sticks, so it
has fixed coordinates ``c`` in each stick's local frame: the least-squares
solution of ``A_sf c + t_sf = J_f`` over the training frames. On new frames
the joint is the mean of the two sticks' predictions ``A_sf c_s + t_sf``.
On the training data this reproduces the method's joints up to its own
fitting error.

**Stick direction** ``u_sf`` (a unit vector per stick and frame):

1. a stick with a parent joint ``J`` and child joints: from ``J`` to the child
   joint farthest from ``J`` on average over the frames (the next joint down a
   chain);
2. a stick with a parent joint and no children (a leaf): from ``J`` to the
   centroid of the stick's points;
3. a stick without a parent joint (a root) but with child joints: from the
   centroid of its points to the child joint farthest from it on average;
4. a stick without any joint, or frames where the rule's ends are unknown:
   the principal axis of the stick's shape (its local coordinates carried by
   its motion when it has one, else of its points in that frame), signed
   consistently over the frames (and like rules 1-3 where they apply).

**Joint angle** of the joint between parent stick ``p`` and child stick ``c``:
for 2D data the signed angle from ``u_p`` to ``u_c`` in (-180, 180] degrees,
positive from the data's +x axis towards its +y axis (counter-clockwise in a
y-up picture, clockwise on screen for image data whose y axis points down);
0 means the child continues straight on from the parent. For 3D data the
unsigned angle in [0, 180] (a sign needs a rotation axis 3D data do not fix).

**Stick segments** (what a picture draws as the stick): the stick's
*anchors* joined by their minimum spanning tree (distances in the mean pose).
The anchors are its joints when it has two or more; a stick with one joint
gets a second anchor, its *far end*, on the ray from the joint through its
centroid at the farthest projection of its points; a stick with no joint is
the segment of its principal axis spanned by its points' projections.
"""

from __future__ import annotations

import csv
import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._atomic import atomic_write_text
from .skeleton import Skeleton, as_trajectories_unobserved
from .trajectories import Trajectories

__all__ = ["Pose", "pose", "joint_angles", "write_angles_csv", "write_bvh"]


@dataclass
class Pose:
    """A skeleton placed in every frame (see the module docstring for the definitions).

    Attributes
    ----------
    points : ndarray, shape (P, F, D)
        Point positions used: observed where seen, predicted by the stick
        motions where missing (NaN where neither is known).
    observed : ndarray of bool, shape (P, F)
        Which entries of ``points`` were observed.
    joints : ndarray, shape (E, F, D)
        The joint of every edge, in the order of ``skeleton.edges`` (NaN where unknown).
    centroids : ndarray, shape (S, F, D)
        Mean position of each stick's points.
    directions : ndarray, shape (S, F, D)
        Unit direction of each stick.
    far_ends : ndarray, shape (S, F, D)
        The far end of each stick with at most one joint (NaN for the others).
    segments : ndarray, shape (K, 2, F, D)
        Line segments that draw the sticks.
    segment_stick : ndarray of int, shape (K,)
        Stick of each segment.
    parent_stick, child_stick : ndarray of int, shape (E,)
        The edges oriented away from the root.
    parents : ndarray of int, shape (S,)
        Parent of every stick, -1 for roots.
    frames : ndarray of int, shape (F,)
        Frame numbers (``meta["frame_offset"]`` added for sliced clips).
    """

    points: np.ndarray
    observed: np.ndarray
    joints: np.ndarray
    centroids: np.ndarray
    directions: np.ndarray
    far_ends: np.ndarray
    segments: np.ndarray
    segment_stick: np.ndarray
    parent_stick: np.ndarray
    child_stick: np.ndarray
    parents: np.ndarray
    frames: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[1])


# ---------------------------------------------------------------------- pose
def _check_pair(skeleton: Any, traj: Any) -> tuple[Skeleton, Trajectories | None]:
    if not isinstance(skeleton, Skeleton):
        raise TypeError(f"skeleton must be a stickfigure Skeleton, got {type(skeleton).__name__}")
    if traj is None:
        return skeleton, None
    traj = as_trajectories_unobserved(traj)
    if traj.n_points != skeleton.n_points:
        raise ValueError(f"traj has {traj.n_points} points, but the skeleton was fitted to {skeleton.n_points}")
    if traj.n_dims != skeleton.n_dims:
        raise ValueError(f"traj is {traj.n_dims}D, but the skeleton was fitted to {skeleton.n_dims}D data")
    return skeleton, traj


def _joint_locals(skeleton: Skeleton, joints: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Least-squares coordinates (E, 3) of each edge's joint in the frame of stick ``a[e]``.

    Solves ``sum_f |A_f c + t_f - J_f|^2`` for ``c``; the pseudo-inverse leaves
    directions the motions never use (e.g. depth of a planar stick) at zero.
    """
    M = skeleton.motions[a]  # (E, F, D, 4)
    ok = np.isfinite(joints).all(axis=2) & np.isfinite(M).all(axis=(2, 3))  # (E, F)
    A = np.where(ok[..., None, None], M[..., :3], 0.0)
    r = np.where(ok[..., None], joints - M[..., 3], 0.0)
    G = np.einsum("efdi,efdj->eij", A, A)
    b = np.einsum("efdi,efd->ei", A, r)
    return np.einsum("eij,ej->ei", np.linalg.pinv(G, rcond=1e-10, hermitian=True), b)


def _is_training_data(skeleton: Skeleton, traj: Trajectories, refit: np.ndarray) -> bool:
    """Whether ``traj`` holds the skeleton's training frames.

    True when the stored motions explain the observed points about as well as
    motions re-fitted to them (median residual at most 1.5 times the re-fit's):
    for any other clip the stored motions describe other poses and miss by far.
    """
    if skeleton.motions.shape[1] != traj.n_frames:
        return False
    obs = traj.observed & (skeleton.labels >= 0)[:, None]
    if not obs.any():
        return False
    stored = skeleton.predict()
    r_stored = np.median(np.linalg.norm(stored[obs] - traj.xy[obs], axis=1))
    r_refit = np.median(np.linalg.norm(refit[obs] - traj.xy[obs], axis=1))
    return bool(np.isfinite(r_stored) and r_stored <= 1.5 * r_refit + 1e-12 * (1 + np.nanstd(traj.xy)))


def _nanmean_weighted(X: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Weighted mean over axis 0 of X (N, F, D) with weights W (N, F) -> (F, D), NaN where no weight."""
    w = W.sum(axis=0)
    s = np.einsum("nf,nfd->fd", W, np.where(W[..., None] > 0, X, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(w[:, None] > 0, s / w[:, None], np.nan)


def _principal_axes(X: np.ndarray, mask: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """Principal axis (F, D) of the points X (n, F, D) visible in ``mask`` (n, F), per frame."""
    d = np.where(mask[..., None], X - centroid[None], 0.0)
    C = np.einsum("nfi,nfj->fij", d, d)
    C = np.where(np.isfinite(C), C, 0.0)
    _, vecs = np.linalg.eigh(C)
    axis = vecs[..., -1]
    axis[~mask.any(axis=0) | ~np.isfinite(centroid).all(axis=1)] = np.nan
    return axis


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    """np.nanmean without the warning for all-NaN slices (they give NaN, as intended)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(a, axis=axis)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 1e-12, v / np.where(n > 0, n, 1.0), np.nan)


def _mst_pairs(positions: np.ndarray) -> list[tuple[int, int]]:
    """Edges of the Euclidean minimum spanning tree of a few positions (k, D)."""
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial.distance import pdist, squareform

    k = positions.shape[0]
    if k < 2:
        return []
    ok = np.isfinite(positions).all(axis=1)
    D = squareform(pdist(np.where(ok[:, None], positions, 0.0)))
    D = D + 1e-9 * (1 - np.eye(k))  # keep coincident anchors connected
    T = minimum_spanning_tree(D).tocoo()
    return [(int(i), int(j)) for i, j in zip(T.row, T.col)]


def pose(skeleton: Skeleton, traj: Trajectories | np.ndarray | None = None) -> Pose:
    """Place a skeleton's sticks and joints in every frame.

    Parameters
    ----------
    skeleton : Skeleton
    traj : Trajectories or ndarray, shape (P, F, D), optional
        Trajectories of the skeleton's points (its training data or new frames).
        Without it the skeleton's training frames are used, which needs stick
        motions.

    Returns
    -------
    Pose

    Raises
    ------
    ValueError
        ``traj`` does not match the skeleton, or ``traj`` is missing and the
        skeleton has no motions to place it with.
    """
    skeleton, traj = _check_pair(skeleton, traj)
    S, E = skeleton.n_sticks, len(skeleton.edges)
    labels = skeleton.labels
    has_motion = skeleton.motions is not None and skeleton.local is not None
    stored_joints = None
    if skeleton.joints is not None and E:
        stored_joints = skeleton.joints[skeleton.edge_joints]  # (E, F_train, D)

    parents = skeleton.parents()
    edges = np.asarray(skeleton.edges, np.int64).reshape(-1, 2)
    flip = parents[edges[:, 0]] == edges[:, 1]  # stored child-first
    parent_stick = np.where(flip, edges[:, 1], edges[:, 0])
    child_stick = np.where(flip, edges[:, 0], edges[:, 1])

    if traj is None:
        if not has_motion:
            raise ValueError(f"the {skeleton.method!r} skeleton has no stick motions; pass the trajectories "
                             "it was fitted to (traj=...)")
        points = skeleton.predict()
        observed = np.zeros(points.shape[:2], bool)
        motions = skeleton.motions
        joints = stored_joints if stored_joints is not None else np.full((E,) + points.shape[1:], np.nan)
        offset = 0
    else:
        observed = traj.observed
        offset = int(traj.meta.get("frame_offset", 0))
        if has_motion:
            from .geometry import fit_motions, predict_points

            motions = fit_motions(traj.xy, skeleton.local, labels, S)
            seen = np.zeros(S, bool)
            seen[np.unique(labels[(labels >= 0) & observed.any(axis=1)])] = True
            motions[~seen] = np.nan  # a stick never seen in these frames is unknown
            predicted = predict_points(motions, skeleton.local, labels)
            if _is_training_data(skeleton, traj, predicted):
                motions, predicted = skeleton.motions, skeleton.predict()
            points = np.where(observed[..., None], traj.xy, predicted)
            if stored_joints is not None and motions is skeleton.motions:
                joints = stored_joints  # the method's own joints for its own frames
            elif stored_joints is not None:
                ca = _joint_locals(skeleton, stored_joints, parent_stick)
                cb = _joint_locals(skeleton, stored_joints, child_stick)
                Ma, Mb = motions[parent_stick], motions[child_stick]
                ja = np.einsum("efdk,ek->efd", Ma[..., :3], ca) + Ma[..., 3]
                jb = np.einsum("efdk,ek->efd", Mb[..., :3], cb) + Mb[..., 3]
                joints = 0.5 * (ja + jb)
            else:
                joints = np.full((E,) + traj.xy.shape[1:], np.nan)
        else:
            motions = None
            points = traj.xy
            if stored_joints is not None and stored_joints.shape[1] == traj.n_frames:
                joints = stored_joints
            else:
                joints = np.full((E,) + traj.xy.shape[1:], np.nan)
    P, F, D = points.shape
    joints = np.asarray(joints, float).reshape(E, F, D)
    known = np.isfinite(points).all(axis=2)  # (P, F)

    onehot = (labels[:, None] == np.arange(S)[None, :])  # (P, S)
    centroids = np.empty((S, F, D))
    axes = np.full((S, F, D), np.nan)
    for s in range(S):  # a handful of sticks; frames are vectorised
        m = onehot[:, s]
        Xs, Ks = points[m], known[m]
        centroids[s] = _nanmean_weighted(Xs, Ks.astype(float))
        if Xs.shape[0]:
            axes[s] = _principal_axes(Xs, Ks, centroids[s])

    # Which joints sit on each stick, and the parent joint of each stick.
    joint_known = np.isfinite(joints).all(axis=2)  # (E, F)
    usable = joint_known.any(axis=1)
    parent_joint = -np.ones(S, np.int64)
    children: list[list[int]] = [[] for _ in range(S)]
    for e in range(E):
        if usable[e]:
            parent_joint[child_stick[e]] = e
            children[parent_stick[e]].append(e)

    directions = np.full((S, F, D), np.nan)
    for s in range(S):
        # Principal axis signed consistently over the frames: the fallback.
        if motions is not None and onehot[:, s].sum() >= 2:
            # Rigid: the principal axis of the stick's local shape, carried by its motion.
            loc = skeleton.local[onehot[:, s]]
            _, _, vt = np.linalg.svd(loc - loc.mean(axis=0), full_matrices=False)
            ax = _unit(np.einsum("fdk,k->fd", motions[s][..., :3], vt[0]))
        else:
            ax = axes[s]
        good = np.isfinite(ax).all(axis=1)
        if good.any():
            _, v = np.linalg.eigh(np.einsum("fi,fj->ij", ax[good], ax[good]))
            sign = np.sign(ax @ v[:, -1])
            ax = ax * np.where(sign == 0, 1.0, sign)[:, None]
        directions[s] = ax
        pj = parent_joint[s]
        start = joints[pj] if pj >= 0 else centroids[s]
        if children[s]:
            dist = [_nanmean(np.linalg.norm(joints[c] - start, axis=1), axis=0) for c in children[s]]
            if not np.isfinite(dist).any():
                continue
            target = joints[children[s][int(np.nanargmax(dist))]]
        elif pj >= 0:
            target = centroids[s]
        else:
            continue
        u = _unit(target - start)
        ok = np.isfinite(u).all(axis=1)
        directions[s, ok] = u[ok]
        if (~ok).any() and good.any():  # frames that fall back: sign the axis like the rule's direction
            if np.nansum(np.einsum("fd,fd->f", ax[ok], u[ok])) < 0:
                directions[s, ~ok] = -ax[~ok]

    # Segments that draw each stick.
    far_ends = np.full((S, F, D), np.nan)
    seg_list: list[np.ndarray] = []
    seg_stick: list[int] = []
    for s in range(S):
        on = [e for e in range(E) if usable[e] and s in (parent_stick[e], child_stick[e])]
        m = onehot[:, s]
        Xs = points[m]
        if len(on) >= 2:
            anchors = joints[on]  # (k, F, D)
            for i, j in _mst_pairs(_nanmean(anchors, axis=1)):
                seg_list.append(np.stack([anchors[i], anchors[j]]))
                seg_stick.append(s)
            continue
        if not Xs.shape[0]:
            continue
        if len(on) == 1:
            J = joints[on[0]]
            u = _unit(centroids[s] - J)
            proj = np.einsum("nfd,fd->nf", Xs - J[None], np.nan_to_num(u))
            reach = np.fmax.reduce(np.where(np.isfinite(proj), proj, -np.inf), axis=0)
            reach = np.where(np.isfinite(reach) & np.isfinite(u).all(axis=1), np.maximum(reach, 0.0), np.nan)
            far_ends[s] = J + u * reach[:, None]
            seg_list.append(np.stack([J, far_ends[s]]))
        else:
            u = directions[s]
            proj = np.einsum("nfd,fd->nf", Xs - centroids[s][None], np.nan_to_num(u))
            proj = np.where(np.isfinite(Xs).all(axis=2), proj, np.nan)
            with np.errstate(invalid="ignore"):
                lo = np.fmin.reduce(proj, axis=0)
                hi = np.fmax.reduce(proj, axis=0)
            far_ends[s] = centroids[s] + u * hi[:, None]
            seg_list.append(np.stack([centroids[s] + u * lo[:, None], far_ends[s]]))
        seg_stick.append(s)
    segments = np.stack(seg_list) if seg_list else np.zeros((0, 2, F, D))
    return Pose(
        points=points,
        observed=observed,
        joints=joints,
        centroids=centroids,
        directions=directions,
        far_ends=far_ends,
        segments=segments,
        segment_stick=np.asarray(seg_stick, np.int64),
        parent_stick=parent_stick,
        child_stick=child_stick,
        parents=parents,
        frames=offset + np.arange(F),
    )


# ------------------------------------------------------------- joint angles
def _angles_from_pose(p: Pose) -> np.ndarray:
    a = p.directions[p.parent_stick]  # (E, F, D)
    b = p.directions[p.child_stick]
    if a.shape[-1] == 2:
        cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        dot = np.einsum("efd,efd->ef", a, b)
        ang = np.degrees(np.arctan2(cross, dot))
        return np.where(ang <= -180.0, 180.0, ang)
    dot = np.clip(np.einsum("efd,efd->ef", a, b), -1.0, 1.0)
    return np.degrees(np.arccos(dot))


def joint_angles(skeleton: Skeleton, traj: Trajectories | np.ndarray | None = None
                 ) -> tuple[np.ndarray, list[dict[str, int]]]:
    """Per frame and per joint, the angle between the two joined sticks.

    Parameters
    ----------
    skeleton : Skeleton
    traj : Trajectories or ndarray, shape (P, F, D), optional
        Frames to measure; the training frames when omitted (needs stick motions).

    Returns
    -------
    angles : ndarray, shape (E, F)
        Degrees; 2D data: signed, in (-180, 180], positive from +x towards +y;
        3D data: unsigned, in [0, 180]. NaN where a stick's direction is unknown.
        Row ``e`` is the joint of ``skeleton.edges[e]``.
    table : list of dict, length E
        For each row: ``joint`` (= e), ``parent_stick`` and ``child_stick``
        (the edge oriented away from the root).

    Notes
    -----
    The stick directions and the sign convention are defined in the module
    docstring of :mod:`stickfigure.export`.
    """
    p = pose(skeleton, traj)
    table = [{"joint": e, "parent_stick": int(a), "child_stick": int(b)}
             for e, (a, b) in enumerate(zip(p.parent_stick, p.child_stick))]
    return _angles_from_pose(p), table


def write_angles_csv(skeleton: Skeleton, path: str | os.PathLike,
                     traj: Trajectories | np.ndarray | None = None) -> Path:
    """Write the joint angles as a long-format CSV.

    Columns: ``frame,joint,parent_stick,child_stick,angle_deg``, one row per
    frame and joint (frames numbered as in the source clip); an unknown angle
    is an empty field.

    Parameters
    ----------
    skeleton : Skeleton
    path : path-like
    traj : Trajectories or ndarray, optional
        As in :func:`joint_angles`.

    Returns
    -------
    Path
    """
    p = pose(skeleton, traj)
    angles = _angles_from_pose(p)
    E, F = angles.shape
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "joint", "parent_stick", "child_stick", "angle_deg"])
    frame = np.repeat(p.frames, E)
    joint = np.tile(np.arange(E), F)
    vals = angles.T.ravel()
    for f, e, v in zip(frame, joint, vals):
        w.writerow([int(f), int(e), int(p.parent_stick[e]), int(p.child_stick[e]),
                    "" if not np.isfinite(v) else f"{v:.4f}"])
    path = Path(path)
    atomic_write_text(path, buf.getvalue())
    return path


# ----------------------------------------------------------------------- BVH
def _to_bvh_axes(X: np.ndarray, n_dims: int, y_down: bool, up_axis: int) -> np.ndarray:
    """Data coordinates (..., D) to BVH coordinates (..., 3), y up.

    2D data go to the z = 0 plane (image data flipped so the figure stands
    upright); 3D data are turned by the cyclic axis permutation that takes the
    data's vertical axis to y (no reflection).
    """
    if n_dims == 2:
        out = np.zeros(X.shape[:-1] + (3,))
        out[..., 0] = X[..., 0]
        out[..., 1] = -X[..., 1] if y_down else X[..., 1]
        return out
    return X[..., [(up_axis + 2) % 3, up_axis, (up_axis + 1) % 3]]


def bvh_coordinates(X: np.ndarray, traj: Trajectories | None, n_dims: int) -> np.ndarray:
    """Map data positions (..., D) to the coordinates :func:`write_bvh` writes (..., 3).

    Useful to compare a BVH file read back with :func:`stickfigure.load` to the
    skeleton it came from.
    """
    y_down = traj is not None and traj.image_size is not None
    up = traj.up_axis if traj is not None else 2
    return _to_bvh_axes(np.asarray(X, float), n_dims, y_down, up)


def _fill_gaps(X: np.ndarray, what: str) -> np.ndarray:
    """Linear interpolation over frames of NaN entries of X (F, 3); constant beyond the ends."""
    ok = np.isfinite(X).all(axis=1)
    if ok.all():
        return X
    if not ok.any():
        raise ValueError(f"cannot export {what}: its position is unknown in every frame")
    f = np.arange(X.shape[0])
    return np.column_stack([np.interp(f, f[ok], X[ok, k]) for k in range(X.shape[1])])


def _min_rotations(ref: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Rotations (F, 3, 3) taking the unit vector ``ref`` (3,) to each ``u`` (F, 3) about ref x u."""
    v = np.cross(ref, u)
    c = u @ ref
    K = np.zeros(u.shape[:1] + (3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    opposite = c < -1 + 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        R = np.eye(3) + K + np.einsum("fij,fjk->fik", K, K) / (1 + np.where(opposite, 1.0, c))[:, None, None]
    if opposite.any():  # a half turn about any axis perpendicular to ref
        perp = np.cross(ref, np.eye(3)[np.argmin(np.abs(ref))])
        perp /= np.linalg.norm(perp)
        R[opposite] = 2 * np.outer(perp, perp) - np.eye(3)
    return R


def _fmt_rows(a: np.ndarray) -> list[str]:
    return [" ".join(f"{v:.6f}" for v in row) for row in a]


def write_bvh(skeleton: Skeleton, path: str | os.PathLike, traj: Trajectories | np.ndarray | None = None,
              frame_rate: float | None = None, *, lengths: str = "exact") -> Path:
    """Export the skeleton and its motion as a Biovision Hierarchy (BVH) file.

    The hierarchy is the stick tree: one BVH joint per stick, named ``stick<s>``,
    nested as in :meth:`Skeleton.parents`. A non-root stick's BVH joint sits at
    the joint to its parent stick; a root stick's sits at the centroid of its
    points; a stick without children ends in an ``End Site`` at its far end
    (see :mod:`stickfigure.export`). A forest of several trees (or sticks
    without joints) hangs from an extra fixed ``ROOT`` named ``figure``.

    Rotations: each stick's world rotation in a frame turns its mean direction
    into that frame's direction (2D data: about z, the figure lies in the
    z = 0 plane; 3D data: the smallest rotation). The rest pose (all channels
    zero) is therefore the mean pose, and a 2D child's ``Zrotation`` is its
    joint angle minus the mean joint angle. ``OFFSET`` values are the mean
    joint-to-joint vectors in the parent's rotated frame.

    Lengths: ``lengths="exact"`` (default) also writes per-joint
    ``X/Y/Zposition`` channels holding each frame's deviation from ``OFFSET``,
    so forward kinematics reproduces the joints exactly even where projected
    limbs change length; ``"rigid"`` writes rotations only (mean lengths), the
    classic form some tools prefer. End sites are fixed offsets (the mean
    far-end vector) in both forms.

    Axes: y is up. 2D data with an image size (y down) are flipped upright;
    3D data are turned so their ``up_axis`` becomes y (see :func:`bvh_coordinates`).
    Frames where a joint is unknown are interpolated from their neighbours.

    Parameters
    ----------
    skeleton : Skeleton
    path : path-like
        Output ``.bvh`` file (written atomically).
    traj : Trajectories or ndarray, shape (P, F, D), optional
        Frames to export; the training frames when omitted (needs stick motions).
    frame_rate : float, optional
        Frames per second; default ``traj.frame_rate``, else 30.
    lengths : {"exact", "rigid"}

    Returns
    -------
    Path
    """
    if lengths not in ("exact", "rigid"):
        raise ValueError(f"lengths must be 'exact' or 'rigid', got {lengths!r}")
    p = pose(skeleton, traj)
    t_obj = traj if isinstance(traj, Trajectories) else None
    if frame_rate is None:
        frame_rate = (t_obj.frame_rate if t_obj is not None and t_obj.frame_rate else None) or 30.0
    frame_rate = float(frame_rate)
    if not np.isfinite(frame_rate) or frame_rate <= 0:
        raise ValueError(f"frame_rate must be > 0, got {frame_rate}")
    S, F, D = p.directions.shape
    E = p.parent_stick.shape[0]
    if E and not np.isfinite(p.joints).all(axis=2).any(axis=1).all():
        raise ValueError(f"the {skeleton.method!r} skeleton has no joint positions for its edges; "
                         "BVH export needs a method that estimates joints (e.g. em)")
    conv = lambda X: bvh_coordinates(X, t_obj, D)  # noqa: E731

    # Node positions (S, F, 3) in BVH coordinates.
    parent = -np.ones(S, np.int64)
    node = np.empty((S, F, 3))
    for s in range(S):
        node[s] = conv(p.centroids[s])
    for e in range(E):
        c = p.child_stick[e]
        parent[c] = p.parent_stick[e]
        node[c] = conv(p.joints[e])
    for s in range(S):
        node[s] = _fill_gaps(node[s], f"stick {s}")
    ends = np.stack([conv(p.far_ends[s]) for s in range(S)]) if S else np.zeros((0, F, 3))
    dirs = np.stack([conv(p.directions[s]) for s in range(S)]) if S else np.zeros((0, F, 3))
    # World rotations (S, F, 3, 3): the mean direction turned into each frame's.
    R = np.broadcast_to(np.eye(3), (S, F, 3, 3)).copy()
    for s in range(S):
        u = dirs[s]
        ok = np.isfinite(u).all(axis=1)
        if not ok.any():
            continue
        if D == 2:
            th = np.arctan2(u[:, 1], u[:, 0])
            mean = np.arctan2(np.sin(th[ok]).mean(), np.cos(th[ok]).mean())
            th = np.where(ok, th - mean, np.nan)
            f = np.arange(F)
            th = np.interp(f, f[ok], np.unwrap(th[ok]))
            c, sn = np.cos(th), np.sin(th)
            R[s, :, 0, 0], R[s, :, 0, 1], R[s, :, 1, 0], R[s, :, 1, 1] = c, -sn, sn, c
        else:
            uu = np.where(ok[:, None], u, 0.0)
            ref = uu.sum(axis=0)
            ref = ref / np.linalg.norm(ref) if np.linalg.norm(ref) > 1e-12 else uu[ok][0]
            filled = np.where(ok[:, None], u, ref)
            R[s] = _min_rotations(ref, filled)

    from scipy.spatial.transform import Rotation

    comps_roots = [s for s in range(S) if parent[s] < 0]
    world_root = len(comps_roots) != 1
    kids: dict[int, list[int]] = {s: [] for s in range(-1, S)}
    for s in range(S):
        kids[int(parent[s])].append(s)

    lines = ["HIERARCHY"]
    columns: list[np.ndarray] = []
    six = "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"

    def euler(Rl: np.ndarray) -> np.ndarray:
        if D == 2:
            z = np.degrees(np.arctan2(Rl[:, 1, 0], Rl[:, 0, 0]))
            return np.column_stack([z, np.zeros(F), np.zeros(F)])
        with warnings.catch_warnings():  # gimbal lock: the angles still compose to the same rotation
            warnings.simplefilter("ignore", UserWarning)
            return Rotation.from_matrix(Rl).as_euler("ZXY", degrees=True)

    def emit(s: int, depth: int, Rp: np.ndarray | None, pos_p: np.ndarray | None) -> None:
        ind = "  " * depth
        is_root = depth == 0
        kw = "ROOT" if is_root else "JOINT"
        lines.append(f"{ind}{kw} stick{s}")
        lines.append(f"{ind}{{")
        if Rp is None:  # a top-level node: world position, world rotation
            t = node[s] if pos_p is None else node[s] - pos_p
            offset = np.zeros(3)
            Rl = R[s]
            lines.append(f"{ind}  OFFSET 0.000000 0.000000 0.000000")
            lines.append(f"{ind}  {six}")
            columns.append(t)
        else:
            t = np.einsum("fji,fj->fi", Rp, node[s] - pos_p)  # in the parent's frame
            offset = t.mean(axis=0)
            Rl = np.einsum("fji,fjk->fik", Rp, R[s])
            lines.append(f"{ind}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}")
            if lengths == "exact":
                lines.append(f"{ind}  {six}")
                columns.append(t - offset)
            else:
                lines.append(f"{ind}  CHANNELS 3 Zrotation Xrotation Yrotation")
        columns.append(euler(Rl))
        for c in kids[s]:
            emit(c, depth + 1, R[s], node[s])
        if not kids[s]:
            end = ends[s]
            ok = np.isfinite(end).all(axis=1)
            off = (np.einsum("fji,fj->fi", R[s][ok], end[ok] - node[s][ok]).mean(axis=0)
                   if ok.any() else np.zeros(3))
            lines.append(f"{ind}  End Site")
            lines.append(f"{ind}  {{")
            lines.append(f"{ind}    OFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
            lines.append(f"{ind}  }}")
        lines.append(f"{ind}}}")

    if world_root:
        lines.append("ROOT figure")
        lines.append("{")
        lines.append("  OFFSET 0.000000 0.000000 0.000000")
        lines.append(f"  {six}")
        columns.append(np.zeros((F, 6)))
        start = len(lines)
        for r in comps_roots:
            emit(r, 0, None, None)
        # Re-indent the components one level and make them JOINTs of "figure".
        for i in range(start, len(lines)):
            text = lines[i]
            if text.startswith("ROOT "):
                text = "JOINT " + text[5:]
            lines[i] = "  " + text
        lines.append("}")
    else:
        emit(comps_roots[0], 0, None, None)
    motion = np.column_stack(columns) if columns else np.zeros((F, 0))
    if not np.isfinite(motion).all():
        raise ValueError("BVH export produced non-finite channel values (a stick is unknown in every frame)")
    out = lines + ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / frame_rate:.8f}"] + _fmt_rows(motion)
    path = Path(path)
    atomic_write_text(path, "\n".join(out) + "\n")
    return path
