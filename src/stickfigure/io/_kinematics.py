"""Posed kinematic trees (BVH, ASF/AMC) turned into points with ground truth.

A skeleton file gives a tree of coordinate *frames* (BVH joints, ASF bones), each
with a global rotation and origin in every frame of the clip. What the loaders
return as points, and what the ground truth means, is decided here once for both
formats.

Ground truth, derived
---------------------
A rigid part is a set of points whose coordinates in some moving frame never
change. A point of the file (a BVH joint or end site, the distal end of an ASF
bone) is a *constant* offset in the frame of the segment proximal to it: the BVH
``OFFSET`` of joint ``j`` is expressed in its parent's frame, and the end of an
ASF bone is ``direction * length`` in the bone's own frame. So each joint point
is labelled with the proximal segment that ends at it (a BVH joint with its
parent joint's part, an ASF bone end with that bone's part); the root point is
the origin of the root frame. A joint whose translation relative to its parent
varies (BVH position channels below the root) is fixed only in its own frame and
is labelled with its own part.

Frames whose motion relative to their parent is constant over the clip are
welded to the parent and cannot be told apart from it by any method that sees
only the motion (CMU's ``LHipJoint``, ASF bones without degrees of freedom).
With ``merge_rigid`` (the default) such a frame joins its parent's part; the
part is named after its top frame and ``meta["part_frames"]`` lists the merged
frames. Parts that end up with no point (for example a frame whose only bones
have zero length) are contracted: their children attach to the nearest
ancestor part that has points, and when the root part itself is empty its
children are joined to the first of them, so ``edges_true`` stays a tree (a
forest only if the file holds several roots).

``edges_true`` holds ``(parent part, child part)`` for each joint of the tree and
``joints_true[e]`` the position of that joint: the origin of the child part's top
frame (for BVH the child joint's position, for ASF the start of the child bone).

Virtual markers
---------------
Joint positions alone make a poor learning problem: every part holds a handful
of collinear points. ``markers_per_bone=k`` replaces them by ``k`` markers rigidly
attached around every bone (a segment from a frame's origin to a child joint or
end site, or an ASF bone), scattered off the bone axis as in
:func:`stickfigure.synthetic.random_figure`, each labelled with the part of the
bone's frame. Bones of zero length carry no markers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..synthetic import _scatter_points
from ..trajectories import Trajectories
from ._common import OptionError, positive_option, rng_option

__all__ = ["Rig", "rig_to_trajectories", "check_rig_options"]

#: Tolerances for "this frame moves rigidly with its parent".
_ROT_TOL = 1e-6
_TRANS_TOL = 1e-6


@dataclass
class Rig:
    """A kinematic tree of frames posed in every frame of a clip.

    Attributes
    ----------
    names : list of str, length J
        Frame names; parents precede children.
    parent : ndarray of int, shape (J,)
        Parent frame, -1 for a root.
    rotation : ndarray, shape (J, F, 3, 3)
        Global rotation of each frame.
    origin : ndarray, shape (J, F, 3)
        Global position of each frame's origin.
    point_names : list of str, length P
    point_frame : ndarray of int, shape (P,)
        The frame each point is fixed in.
    point_local : ndarray, shape (P, 3)
        Each point's coordinates in that frame.
    bone_names : list of str, length B
    bone_frame : ndarray of int, shape (B,)
    bone_start, bone_end : ndarray, shape (B, 3)
        Bone end points in the bone's frame.
    """

    names: list[str]
    parent: np.ndarray
    rotation: np.ndarray
    origin: np.ndarray
    point_names: list[str]
    point_frame: np.ndarray
    point_local: np.ndarray
    bone_names: list[str] = field(default_factory=list)
    bone_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    bone_start: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bone_end: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def positions(self, frame: np.ndarray, local: np.ndarray) -> np.ndarray:
        """Global positions of points fixed in frames, shape (P, F, 3)."""
        return np.einsum("pfij,pj->pfi", self.rotation[frame], local) + self.origin[frame]


def _bone_markers(rig: Rig, k: int, rng: np.random.Generator, spread: float
                  ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """``k`` markers around every bone of non-zero length: names, frames (P,), local coords (P, 3)."""
    names: list[str] = []
    frames: list[int] = []
    local: list[np.ndarray] = []
    for b, bname in enumerate(rig.bone_names):
        axis = rig.bone_end[b] - rig.bone_start[b]
        length = float(np.linalg.norm(axis))
        if length <= 0:
            continue
        # An orthonormal basis whose first axis is the bone: markers are drawn
        # around the x axis and turned onto the bone.
        u = axis / length
        helper = np.eye(3)[int(np.argmin(np.abs(u)))]
        v = np.cross(u, helper)
        v /= np.linalg.norm(v)
        basis = np.column_stack([u, v, np.cross(u, v)])
        pts = _scatter_points(rng, length, k, False, spread) @ basis.T + rig.bone_start[b]
        names += [f"{bname}/m{i}" for i in range(k)]
        frames += [rig.bone_frame[b]] * k
        local.append(pts)
    if not names:
        return [], np.zeros(0, np.int64), np.zeros((0, 3))
    return names, np.asarray(frames, np.int64), np.concatenate(local)


def _frame_groups(rig: Rig, merge_rigid: bool) -> np.ndarray:
    """Group index of every frame: a frame welded to its parent joins the parent's group."""
    J = len(rig.names)
    group = np.arange(J)
    if not merge_rigid:
        return group
    scale = float(np.nanmax(np.abs(rig.point_local))) if rig.point_local.size else 1.0
    scale = scale if scale > 0 else 1.0
    for j in range(J):  # parents precede children, so group[p] is final
        p = rig.parent[j]
        if p < 0:
            continue
        Rp = rig.rotation[p]
        rel_R = np.einsum("fji,fjk->fik", Rp, rig.rotation[j])
        rel_t = np.einsum("fji,fj->fi", Rp, rig.origin[j] - rig.origin[p])
        if (np.abs(rel_R - rel_R[:1]).max() <= _ROT_TOL
                and np.abs(rel_t - rel_t[:1]).max() <= _TRANS_TOL * scale):
            group[j] = group[p]
    return group


def check_rig_options(markers_per_bone: Any, marker_spread: Any, scale: Any) -> tuple[int, float]:
    """Check the options shared by the BVH and ASF/AMC readers (before reading the file)."""
    k = positive_option(markers_per_bone, "markers_per_bone", integer=True, allow_zero=True)
    positive_option(marker_spread, "marker_spread")
    return k, positive_option(scale, "scale")


def rig_to_trajectories(
    rig: Rig,
    *,
    markers_per_bone: int = 0,
    random_state: Any = None,
    marker_spread: float = 0.25,
    merge_rigid: bool = True,
    scale: float = 1.0,
    up_axis: int = 1,
    frame_rate: float | None = None,
    meta: dict[str, Any] | None = None,
) -> Trajectories:
    """Points of a posed rig as :class:`Trajectories` with ground truth.

    Parameters
    ----------
    rig : Rig
    markers_per_bone : int
        0: the rig's own points (joints and end sites). ``k > 0``: ``k`` virtual
        markers around every bone instead (see the module docstring).
    random_state : None, int or Generator
        Seed of the virtual marker placement.
    marker_spread : float
        Marker distance from the bone axis, as a fraction of the bone length.
    merge_rigid : bool
        Weld frames that never move relative to their parent into the parent's part.
    scale : float
        Factor applied to every position (unit conversion).
    up_axis, frame_rate, meta
        Passed to :class:`Trajectories`.

    Returns
    -------
    Trajectories
        3D positions (P, F, 3), ``labels_true``, ``part_names``, ``edges_true`` and
        ``joints_true`` (E, F, 3).
    """
    k, scale = check_rig_options(markers_per_bone, marker_spread, scale)
    if k:
        rng = rng_option(random_state)
        names, pframe, plocal = _bone_markers(rig, k, rng, marker_spread)
        if not names:
            raise OptionError("markers_per_bone: the skeleton has no bone of non-zero length")
    else:
        names, pframe, plocal = list(rig.point_names), rig.point_frame, rig.point_local
    xy = rig.positions(pframe, plocal) * scale

    group = _frame_groups(rig, merge_rigid)
    has_points = np.zeros(len(rig.names), bool)
    has_points[group[pframe]] = True
    # Part tree over groups: a group's parent is the group of its top frame's parent.
    tops = [j for j in range(len(rig.names)) if group[j] == j]
    kept = [g for g in tops if has_points[g]]
    part_index = {g: i for i, g in enumerate(kept)}

    def nearest_kept_ancestor(g: int) -> int:
        p = rig.parent[g]
        while p >= 0:
            if has_points[group[p]]:
                return int(group[p])
            p = rig.parent[group[p]]
        return -1

    edges: list[tuple[int, int]] = []
    joints: list[np.ndarray] = []
    orphans: dict[int, list[int]] = {}  # kept parts hanging from an empty root, by that root
    for g in kept:
        if rig.parent[g] < 0:
            continue
        a = nearest_kept_ancestor(g)
        if a >= 0:
            edges.append((part_index[a], part_index[g]))
            joints.append(rig.origin[g])
        else:
            root = g
            while rig.parent[root] >= 0:
                root = int(group[rig.parent[root]])
            orphans.setdefault(root, []).append(g)
    for siblings in orphans.values():
        first = siblings[0]
        for g in siblings[1:]:
            edges.append((part_index[first], part_index[g]))
            joints.append(rig.origin[g])

    F = rig.rotation.shape[1]
    joints_true = np.stack(joints) * scale if joints else np.zeros((0, F, 3))
    part_frames = {rig.names[g]: [rig.names[j] for j in range(len(rig.names)) if group[j] == g] for g in kept}
    meta = dict(meta or {})
    meta.update({
        "part_frames": part_frames,
        "points": "virtual markers" if k else "joints",
    })
    if k:
        meta.update({"markers_per_bone": k, "marker_spread": float(marker_spread)})
    return Trajectories(
        xy=xy,
        names=names,
        frame_rate=frame_rate,
        labels_true=np.array([part_index[group[f]] for f in pframe], np.int64),
        edges_true=edges,
        part_names=[rig.names[g] for g in kept],
        joints_true=joints_true,
        up_axis=up_axis,
        meta=meta,
    )
