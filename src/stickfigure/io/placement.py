"""A named marker set placed on a posed BVH skeleton: the markers a lab would have recorded.

:func:`place_cmu41` puts the Vicon 41-marker set of the CMU and HDM05 databases
(``LFHD``, ``C7``, ``LSHO``, ``LELB``, ``LWRA``, ``LTHI``, ``LKNE``, ``LANK``, ...) at
its anatomical landmarks on a skeleton with CMU's joint names. With it, a BVH clip
of another subject and motion becomes a take with the same markers, the same
ground truth (:func:`stickfigure.io.markersets.segment_ground_truth`) and the same
checks as a recorded CMU C3D take: it is how the CMU structure target is measured
on motions the data directory has no marker file for.

How a marker is placed
----------------------
Each marker sits on one bone: ``A + s (B - A) + d``, with ``A`` and ``B`` the
bone's two joints in the rest pose, ``s`` a fraction along it and ``d`` an
offset (left, up, forward) in thigh lengths, so the placement scales with the
subject. It is fixed in the frame of the bone's proximal joint, so it moves
rigidly with that bone. The offsets were set by hand from the landmarks the
marker set names (lateral epicondyle, malleolus, acromion, ...), not measured on
a subject: a head-band marker sits about 7 cm to the side and 9 cm to the front
or back, a thigh marker about 6 cm lateral halfway down (a thigh length taken as
43 cm).

A BVH's rest pose has every joint rotation at zero, so a point's rest position is
the sum of the ``OFFSET``s above it and its local coordinates in a frame are its
rest position less that frame's rest origin. Up is the file's y; *left* is the
horizontal direction from the right hip to the left one; forward is left x up.

What differs from a recorded take: the markers are rigid on their bones (no
skin or soft-tissue motion; :func:`stickfigure.synthetic.skin_motion` adds it)
and the bones are the BVH fit's, so a segment the fit keeps rigid (CMU's pelvis,
each spine link) is rigid here, and ``T10``, on the lower spine link, moves
against the exactly rigid upper thorax where on a recorded take it moves with it
as much as the thorax markers move with each other. The shoulder marker
(``SHO``) sits on the collar bone, which turns against the thorax, as the
acromion does. The placement is mirror-symmetric, so
the pelvis's four markers (two mirrored pairs, whose chords are parallel) and the
head band's four are exactly coplanar. On the recorded CMU 85_02 take they are
not quite: the third singular value of the centred markers is 2.5 mm for the
pelvis and 3.7 mm for the head band (median over frames). An orthographic image
of a flat stick fits its mirror-image pose as well (docs/em.md, sections 4 and 6).

Joint names: CMU's own conversion (``LeftHip``, ``LeftKnee``, ``LeftCollar``,
``LeftShoulder``, ``LeftElbow``, ``lhand``: 131_01.bvh) and the MotionBuilder
names of the widely shared CMU conversion (``LeftUpLeg``, ``LeftLeg``,
``LeftShoulder``, ``LeftArm``, ``LeftForeArm``, ``LeftHand``). A bone is the
first of its alternatives whose two joints exist, the second a descendant of the
first.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ._common import OptionError

__all__ = ["MARKER_SETS", "CMU41", "place_cmu41", "rest_positions"]

#: Each bone's alternatives: (proximal joint, distal joint or end site), left side.
#: ``None`` as distal joint: a bone without a direction (the pelvis: markers by offset only).
_BONES: dict[str, tuple[tuple[str, str | None], ...]] = {
    "pelvis": (("Hips", None),),
    "chest": (("Chest", "Chest2"), ("Spine", "Spine1")),
    "upper_chest": (("Chest2", "Neck"), ("Spine1", "Neck")),
    "head": (("Head", "Head_End"),),
    "collar": (("LeftCollar", "LeftShoulder"), ("LeftShoulder", "LeftArm")),
    "upperarm": (("LeftShoulder", "LeftElbow"), ("LeftArm", "LeftForeArm")),
    "forearm": (("LeftElbow", "LeftWrist"), ("LeftForeArm", "LeftHand")),
    "hand": (("lhand", "LFingers"), ("LeftHand", "LeftFingerBase"), ("LeftHand", "LeftHand_End")),
    "thigh": (("LeftHip", "LeftKnee"), ("LeftUpLeg", "LeftLeg")),
    "shin": (("LeftKnee", "LeftAnkle"), ("LeftLeg", "LeftFoot")),
    "foot": (("LeftAnkle", "LeftToe"), ("LeftFoot", "LeftToeBase")),
}
_SIDED_BONES = {"collar", "upperarm", "forearm", "hand", "thigh", "shin", "foot"}

#: The 41-marker set, left side and centre: (name, bone, s, (left, up, forward) in thigh lengths).
#: A name starting with "L" on a sided bone or with a non-zero left offset is mirrored to "R".
CMU41: tuple[tuple[str, str, float, tuple[float, float, float]], ...] = (
    ("LFHD", "head", 0.5, (0.16, 0.0, 0.20)),
    ("LBHD", "head", 0.5, (0.16, 0.0, -0.20)),
    ("C7", "upper_chest", 1.0, (0.0, 0.0, -0.15)),
    ("CLAV", "upper_chest", 0.85, (0.0, 0.0, 0.15)),
    ("STRN", "upper_chest", 0.0, (0.0, 0.0, 0.22)),
    ("T10", "chest", 0.3, (0.0, 0.0, -0.20)),
    ("RBAC", "upper_chest", 0.5, (-0.20, 0.0, -0.18)),
    ("LSHO", "collar", 1.0, (0.03, 0.08, 0.0)),
    ("LUPA", "upperarm", 0.5, (0.10, 0.0, -0.05)),
    ("LELB", "upperarm", 1.0, (0.08, 0.0, -0.03)),
    ("LFRM", "forearm", 0.45, (0.08, 0.0, -0.06)),
    ("LWRA", "forearm", 1.0, (0.03, 0.0, 0.06)),
    ("LWRB", "forearm", 1.0, (0.03, 0.0, -0.06)),
    ("LFIN", "hand", 0.6, (0.03, 0.0, 0.03)),
    ("LFWT", "pelvis", 0.0, (0.25, 0.05, 0.18)),
    ("LBWT", "pelvis", 0.0, (0.15, 0.08, -0.20)),
    ("LTHI", "thigh", 0.5, (0.15, 0.0, 0.05)),
    ("LKNE", "thigh", 1.0, (0.12, 0.0, 0.0)),
    ("LSHN", "shin", 0.5, (0.05, 0.0, 0.10)),
    ("LANK", "shin", 1.0, (0.08, 0.0, -0.02)),
    ("LHEE", "foot", 0.0, (0.0, -0.06, -0.12)),
    ("LTOE", "foot", 1.0, (0.0, 0.0, 0.02)),
    ("LMT5", "foot", 0.85, (0.08, -0.03, 0.0)),
)

MARKER_SETS = ("cmu41",)


def _right(name: str) -> str:
    for a, b in (("Left", "Right"), ("lhand", "rhand"), ("LFingers", "RFingers")):
        if name.startswith(a):
            return b + name[len(a):]
    return name


def rest_positions(point_names: Sequence[str], point_frame: np.ndarray, point_local: np.ndarray,
                   frame_names: Sequence[str], parent: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Rest-pose positions of a BVH rig's points and frame origins (all rotations zero).

    Returns
    -------
    points : dict name -> ndarray, shape (3,)
    origins : ndarray, shape (J, 3)
    """
    index = {n: i for i, n in enumerate(point_names)}
    J = len(frame_names)
    origins = np.zeros((J, 3))
    for j in range(J):  # parents precede children
        p = parent[j]
        k = index.get(frame_names[j])
        if p >= 0 and k is not None and point_frame[k] == p:
            origins[j] = origins[p] + point_local[k]
        elif p >= 0:
            origins[j] = origins[p]  # a sliding joint: its rest place is its parent's
    points = {n: origins[point_frame[i]] + point_local[i] for i, n in enumerate(point_names)}
    for j, n in enumerate(frame_names):
        points.setdefault(n, origins[j])
    return points, origins


def _is_descendant(child: str, ancestor: str, frame_index: dict[str, int], parent: np.ndarray,
                   frame_of_point: dict[str, int]) -> bool:
    """Whether joint or end site ``child`` hangs below frame ``ancestor``."""
    j = int(parent[frame_index[child]]) if child in frame_index else frame_of_point[child]
    a = frame_index[ancestor]
    while j >= 0:
        if j == a:
            return True
        j = int(parent[j])
    return False


def place_cmu41(frame_names: Sequence[str], parent: np.ndarray, point_names: Sequence[str],
                point_frame: np.ndarray, point_local: np.ndarray
                ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The 41 markers' frames and local coordinates on a BVH rig with CMU joint names.

    Parameters
    ----------
    frame_names : sequence of str, length J
        The rig's joints (frames), parents first.
    parent : ndarray of int, shape (J,)
    point_names : sequence of str, length P
        Joints and end sites.
    point_frame : ndarray of int, shape (P,)
    point_local : ndarray, shape (P, 3)
        Each point in its frame (a joint: its ``OFFSET`` in the parent's frame).

    Returns
    -------
    names : list of str, length 41
    frames : ndarray of int, shape (41,)
    local : ndarray, shape (41, 3)

    Raises
    ------
    OptionError
        When a bone of the marker set has no joints of these names.
    """
    rest, origins = rest_positions(point_names, point_frame, point_local, frame_names, parent)
    frame_index = {n: i for i, n in enumerate(frame_names)}
    frame_of_point = {n: int(f) for n, f in zip(point_names, point_frame)}
    found: dict[tuple[str, bool], tuple[str, str | None]] = {}

    def bone(key: str, right: bool) -> tuple[str, str | None]:
        if (key, right) in found:
            return found[key, right]
        for a, b in _BONES[key]:
            a2, b2 = (_right(a), _right(b) if b else None) if right else (a, b)
            if a2 in frame_index and (b2 is None or (b2 in rest and _is_descendant(
                    b2, a2, frame_index, parent, frame_of_point))):
                found[key, right] = (a2, b2)
                return a2, b2
        options = ", ".join(f"{_right(a) if right else a}->{(_right(b) if right else b) or '(none)'}"
                            for a, b in _BONES[key])
        raise OptionError(f"marker_set='cmu41' needs CMU joint names; no bone for the "
                          f"{'right ' if right else ''}{key} ({options})")

    (hip_l, knee_l), hip_r = bone("thigh", False), bone("thigh", True)[0]
    up = np.array([0.0, 1.0, 0.0])
    left = rest[hip_l] - rest[hip_r]
    left -= left @ up * up
    if np.linalg.norm(left) == 0:
        raise OptionError("marker_set='cmu41': the two hips coincide in the rest pose")
    left /= np.linalg.norm(left)
    forward = np.cross(left, up)
    unit = float(np.linalg.norm(rest[knee_l] - rest[hip_l]))  # type: ignore[index]
    if unit == 0:
        raise OptionError("marker_set='cmu41': the thigh has zero length in the rest pose")
    basis = np.stack([left, up, forward]) * unit  # offset (left, up, forward) @ basis -> rest coords

    names: list[str] = []
    frames: list[int] = []
    local: list[np.ndarray] = []
    for name, key, s, offset in CMU41:
        sides = [False]
        if key in _SIDED_BONES or offset[0] != 0 and name.startswith("L"):
            sides.append(True)
        for right in sides:
            a, b = bone(key, right)
            d = np.array(offset, float)
            if right:
                d[0] = -d[0]
            start = rest[a]
            pos = start + s * (rest[b] - start if b else 0.0) + d @ basis
            names.append("R" + name[1:] if right else name)
            frames.append(frame_index[a])
            local.append(pos - origins[frame_index[a]])
    return names, np.asarray(frames, np.int64), np.stack(local)
