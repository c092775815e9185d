"""Biovision Hierarchy (``.bvh``) motion: joint positions by forward kinematics.

A BVH file holds a joint hierarchy (``ROOT``/``JOINT`` blocks with an ``OFFSET``
from the parent joint, a list of ``CHANNELS`` and ``End Site`` leaves) and a
``MOTION`` table with one row of channel values per frame.

Forward kinematics follows the usual reading of the format (Biovision; CMU's
conversions; bvh11): the transform of joint ``j`` relative to its parent is

    L_j = T(offset_j) * C_1 * C_2 * ... * C_n

where ``C_i`` are the joint's channels *in the order listed* (a translation
along an axis for ``?position``, a rotation about an axis for ``?rotation``,
angles in degrees). Listed rotations ``Zrotation Xrotation Yrotation`` thus give
``Rz @ Rx @ Ry`` (intrinsic Z-X-Y), which scipy builds as
``Rotation.from_euler("ZXY", ...)``; any order and interleaving is accepted, and
position channels may appear on any joint. Global transforms compose down the
tree, vectorised over frames. Some exporters write position channels as the
joint's full local translation rather than an increment on ``OFFSET``
(their channel values stay near ``OFFSET``); ``position_mode="replace"`` reads
them that way, and the default ``"auto"`` picks the reading from the data
(:func:`guess_position_mode`; recorded in ``meta["position_mode"]``).

The data are y-up (``up_axis=1``); BVH carries no length unit, so
``meta["units"]`` is ``None`` unless ``units=`` is given. What the points and the
ground truth are is described in :mod:`stickfigure.io._kinematics`: by default
one point per joint and end site (named ``<joint>`` and ``<joint>_End``), each
labelled with the part of its parent joint; ``markers_per_bone=k`` gives ``k``
virtual markers rigidly attached around every bone instead.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..trajectories import Trajectories
from ._common import OptionError, check_file, fail
from ._kinematics import Rig, check_rig_options, rig_to_trajectories
from .markersets import segment_ground_truth
from .placement import MARKER_SETS, place_cmu41

__all__ = ["load_bvh", "read_bvh"]

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class _Node:
    name: str
    parent: int
    offset: np.ndarray
    channels: list[str] = field(default_factory=list)
    end_site: bool = False
    first_channel: int = 0


@dataclass
class BVH:
    """The parsed content of a BVH file.

    Attributes
    ----------
    nodes : list
        Joints and end sites in file order (parents first), each with ``name``,
        ``parent`` (-1 for a root), ``offset`` (3,), ``channels`` and ``end_site``.
    motion : ndarray, shape (F, C)
        Channel values per frame.
    frame_time : float
        Seconds per frame.
    """

    nodes: list[_Node]
    motion: np.ndarray
    frame_time: float


def _tokens(text: str) -> list[str]:
    return text.replace("{", " { ").replace("}", " } ").split()


def read_bvh(path: str | os.PathLike) -> BVH:
    """Parse a BVH file (hierarchy and motion table), with format checks."""
    path = check_file(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        text = path.read_text(encoding="latin-1")
    head, sep, motion_text = text.partition("MOTION")
    if not sep:
        if "HIERARCHY" not in text[:1000]:
            raise fail(path, "not a BVH file (no HIERARCHY section)")
        raise fail(path, "truncated BVH file: no MOTION section")
    tok = _tokens(head)
    if not tok or tok[0] != "HIERARCHY":
        raise fail(path, f"not a BVH file: expected 'HIERARCHY', found {tok[0] if tok else 'nothing'!r}")
    nodes: list[_Node] = []
    stack: list[int] = []
    n_channels = 0
    i = 1
    expect_open = False

    def floats(at: int, n: int, what: str) -> np.ndarray:
        try:
            vals = np.array([float(t) for t in tok[at:at + n]])
        except ValueError:
            raise fail(path, f"bad {what} values {' '.join(tok[at:at + n])!r}") from None
        if vals.size != n:
            raise fail(path, f"truncated {what} in the hierarchy")
        return vals

    while i < len(tok):
        t = tok[i]
        if t in ("ROOT", "JOINT", "End"):
            if t == "End":
                if i + 1 >= len(tok) or tok[i + 1] != "Site":
                    raise fail(path, "expected 'End Site'")
                if not stack:
                    raise fail(path, "'End Site' outside a joint")
                parent = stack[-1]
                base = f"{nodes[parent].name}_End"
                taken = {n.name for n in nodes}
                name, n = base, 1
                while name in taken:
                    name, n = f"{base}{n}", n + 1
                i += 2
            else:
                if t == "JOINT" and not stack:
                    raise fail(path, "'JOINT' outside a ROOT block")
                if t == "ROOT" and stack:
                    raise fail(path, "'ROOT' inside another joint")
                j = i + 1
                while j < len(tok) and tok[j] != "{":
                    j += 1
                name = " ".join(tok[i + 1:j])
                if not name:
                    raise fail(path, f"{t} without a name")
                parent = stack[-1] if stack else -1
                i = j
            nodes.append(_Node(name=name, parent=parent, offset=np.zeros(3), end_site=(t == "End")))
            stack.append(len(nodes) - 1)
            expect_open = True
            continue
        if t == "{":
            if not expect_open:
                raise fail(path, "unexpected '{' in the hierarchy")
            expect_open = False
            i += 1
        elif t == "}":
            if not stack:
                raise fail(path, "unbalanced '}' in the hierarchy")
            stack.pop()
            i += 1
        elif t == "OFFSET":
            if not stack:
                raise fail(path, "OFFSET outside a joint")
            nodes[stack[-1]].offset = floats(i + 1, 3, "OFFSET")
            i += 4
        elif t == "CHANNELS":
            if not stack or nodes[stack[-1]].end_site:
                raise fail(path, "CHANNELS outside a joint")
            try:
                n = int(tok[i + 1])
            except (IndexError, ValueError):
                raise fail(path, "CHANNELS without a channel count") from None
            chans = tok[i + 2:i + 2 + n]
            bad = [c for c in chans if len(c) != 9 or c[0].lower() not in _AXES
                   or c[1:].lower() not in ("position", "rotation")]
            if len(chans) != n or bad:
                raise fail(path, f"bad CHANNELS list for joint {nodes[stack[-1]].name!r}: "
                                 f"{' '.join(tok[i + 1:i + 2 + n])!r}")
            node = nodes[stack[-1]]
            node.channels = chans
            node.first_channel = n_channels
            n_channels += n
            i += 2 + n
        else:
            raise fail(path, f"unexpected token {t!r} in the hierarchy")
    if stack:
        raise fail(path, f"hierarchy not closed ({len(stack)} open block(s) before MOTION)")
    if not nodes:
        raise fail(path, "the hierarchy has no joints")

    mtok = motion_text.split()
    if len(mtok) < 5 or mtok[0] != "Frames:" or mtok[2:4] != ["Frame", "Time:"]:
        raise fail(path, "bad MOTION header: expected 'Frames: N' and 'Frame Time: T'")
    try:
        n_frames = int(mtok[1])
        frame_time = float(mtok[4])
    except ValueError:
        raise fail(path, f"bad MOTION header values {mtok[1]!r}, {mtok[4]!r}") from None
    if frame_time <= 0 or not np.isfinite(frame_time):
        raise fail(path, f"Frame Time must be > 0, got {mtok[4]}")
    try:
        values = np.array(mtok[5:], dtype=float)
    except ValueError:
        bad = next(v for v in mtok[5:] if not _is_float(v))
        raise fail(path, f"non-numeric motion value {bad!r}") from None
    expected = n_frames * n_channels
    if values.size != expected:
        if values.size < expected:
            got = values.size // n_channels if n_channels else 0
            raise fail(path, f"truncated motion data: header says {n_frames} frames x {n_channels} channels, "
                             f"found {values.size} values ({got} complete frames)")
        raise fail(path, f"motion data has {values.size} values, more than {n_frames} frames x "
                         f"{n_channels} channels")
    if not np.isfinite(values).all():
        raise fail(path, "motion data contain non-finite values")
    return BVH(nodes=nodes, motion=values.reshape(n_frames, n_channels), frame_time=frame_time)


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _local_transforms(node: _Node, motion: np.ndarray, position_mode: str
                      ) -> tuple[np.ndarray, np.ndarray]:
    """A joint's rotation (F, 3, 3) and translation (F, 3) relative to its parent."""
    F = motion.shape[0]
    R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
    has_pos = any(c[1:].lower() == "position" for c in node.channels)
    t = np.zeros((F, 3)) if (has_pos and position_mode == "replace") else np.tile(node.offset, (F, 1))
    c = 0
    chans = node.channels
    while c < len(chans):
        kind = chans[c][1:].lower()
        if kind == "position":
            axis = _AXES[chans[c][0].lower()]
            # A translation after rotations moves along the rotated axis.
            t += R[:, :, axis] * motion[:, node.first_channel + c, None]
            c += 1
        else:
            run = c
            while run < len(chans) and chans[run][1:].lower() == "rotation":
                run += 1
            seq = "".join(ch[0].upper() for ch in chans[c:run])
            if len(set(seq)) != len(seq):  # repeated axes: compose one at a time
                for k in range(c, run):
                    Rk = Rotation.from_euler(seq[k - c], motion[:, node.first_channel + k], degrees=True)
                    R = R @ Rk.as_matrix()
            else:
                ang = motion[:, node.first_channel + c:node.first_channel + run]
                R = R @ Rotation.from_euler(seq, ang, degrees=True).as_matrix()
            c = run
    return R, t


def guess_position_mode(bvh: BVH) -> str:
    """Whether position channels add to OFFSET ("add") or replace it ("replace").

    Exporters that put position channels on every joint write the full local
    translation, so the channel values stay near the joint's OFFSET; increments
    on OFFSET stay near zero instead. Each joint with position channels and a
    non-zero OFFSET votes for the reading its mean channel values are closer to;
    ties and files without such joints read "add" (CMU, bvh11).
    """
    votes = 0
    for node in bvh.nodes:
        pos = [i for i, c in enumerate(node.channels) if c[1:].lower() == "position"]
        if not pos or not np.any(node.offset):
            continue
        mean = np.zeros(3)
        for i in pos:
            mean[_AXES[node.channels[i][0].lower()]] = bvh.motion[:, node.first_channel + i].mean()
        d_replace = np.linalg.norm(mean - node.offset)
        d_add = np.linalg.norm(mean)
        votes += int(np.sign(d_add - d_replace))
    return "replace" if votes > 0 else "add"


def bvh_rig(bvh: BVH, position_mode: str = "add") -> Rig:
    """Forward kinematics of a parsed BVH: the posed :class:`Rig`."""
    if position_mode == "auto":
        position_mode = guess_position_mode(bvh)
    if position_mode not in ("add", "replace"):
        raise OptionError(f"position_mode must be 'auto', 'add' or 'replace', got {position_mode!r}")
    F = bvh.motion.shape[0]
    joints = [k for k, n in enumerate(bvh.nodes) if not n.end_site]
    frame_of = {k: i for i, k in enumerate(joints)}
    J = len(joints)
    R = np.empty((J, F, 3, 3))
    o = np.empty((J, F, 3))
    parent = np.full(J, -1, np.int64)
    translating = np.zeros(J, bool)
    for i, k in enumerate(joints):
        node = bvh.nodes[k]
        Rl, tl = _local_transforms(node, bvh.motion, position_mode)
        translating[i] = any(c[1:].lower() == "position" for c in node.channels)
        if node.parent < 0:
            R[i], o[i] = Rl, tl
        else:
            p = frame_of[node.parent]
            parent[i] = p
            R[i] = R[p] @ Rl
            o[i] = o[p] + np.einsum("fij,fj->fi", R[p], tl)
    pnames, pframe, plocal = [], [], []
    bnames, bframe, bend = [], [], []
    for k, node in enumerate(bvh.nodes):
        pnames.append(node.name)
        if node.end_site:
            f = frame_of[node.parent]
            pframe.append(f)
            plocal.append(node.offset)
            bnames.append(f"{bvh.nodes[node.parent].name}-{node.name}")
            bframe.append(f)
            bend.append(node.offset)
            continue
        i = frame_of[k]
        if parent[i] < 0 or translating[i]:
            # The root, or a joint that slides: fixed only in its own frame.
            pframe.append(i)
            plocal.append(np.zeros(3))
        else:
            pframe.append(parent[i])
            plocal.append(node.offset)
            bnames.append(f"{bvh.nodes[node.parent].name}-{node.name}")
            bframe.append(parent[i])
            bend.append(node.offset)
    return Rig(
        names=[bvh.nodes[k].name for k in joints],
        parent=parent,
        rotation=R,
        origin=o,
        point_names=pnames,
        point_frame=np.asarray(pframe, np.int64),
        point_local=np.asarray(plocal, float).reshape(-1, 3),
        bone_names=bnames,
        bone_frame=np.asarray(bframe, np.int64),
        bone_start=np.zeros((len(bnames), 3)),
        bone_end=np.asarray(bend, float).reshape(-1, 3),
    )


def load_bvh(
    path: str | os.PathLike,
    *,
    markers_per_bone: int = 0,
    random_state: Any = None,
    marker_spread: float = 0.25,
    merge_rigid: bool = True,
    position_mode: str = "auto",
    scale: float = 1.0,
    units: str | None = None,
    marker_set: str | None = None,
) -> Trajectories:
    """Load a BVH clip as 3D trajectories of its joints (or of virtual markers).

    Parameters
    ----------
    path : path-like
    markers_per_bone : int
        0 (default): one point per joint and end site. ``k > 0``: ``k`` virtual
        markers rigidly attached around every bone, labelled by bone part.
    random_state : None, int or Generator
        Seed of the virtual marker placement.
    marker_spread : float
        Marker distance from the bone axis as a fraction of the bone length.
    merge_rigid : bool
        Weld joints that never move relative to their parent into the parent's part.
    position_mode : {"auto", "add", "replace"}
        Position channels add to ``OFFSET`` or replace it; "auto" (default)
        decides from the data (:func:`guess_position_mode`).
    scale : float
        Factor applied to every position.
    units : str, optional
        Length unit of the file (after ``scale``), recorded in ``meta["units"]``.
    marker_set : {None, "cmu41"}
        ``"cmu41"``: the Vicon 41-marker set of CMU and HDM05 placed at its
        landmarks on a skeleton with CMU joint names
        (:mod:`stickfigure.io.placement`), with the marker set's ground truth
        (body segments by marker name, as for a C3D take; no ``joints_true``).
        Not with ``markers_per_bone``.

    Returns
    -------
    Trajectories
        Positions (P, F, 3), y up, with ``labels_true``, ``part_names``,
        ``edges_true`` and ``joints_true``.
    """
    path = check_file(path)
    check_rig_options(markers_per_bone, marker_spread, scale)
    if marker_set is not None:  # checked before the file is read, like the other options
        if not isinstance(marker_set, str) or marker_set not in MARKER_SETS:
            raise OptionError(f"marker_set must be one of {', '.join(map(repr, MARKER_SETS))} or None, "
                              f"got {marker_set!r}")
        if markers_per_bone:
            raise OptionError("give marker_set or markers_per_bone, not both")
    if position_mode not in ("auto", "add", "replace"):
        raise OptionError(f"position_mode must be 'auto', 'add' or 'replace', got {position_mode!r}")
    bvh = read_bvh(path)
    if position_mode == "auto":
        position_mode = guess_position_mode(bvh)
    rig = bvh_rig(bvh, position_mode)
    meta = {"source": str(path), "format": "bvh", "units": units, "frame_time": bvh.frame_time,
            "position_mode": position_mode,
            # one figure per ROOT hierarchy (EMSkeleton(max_trees="auto") reads it)
            "n_figures": sum(1 for n in bvh.nodes if n.parent < 0)}
    if marker_set is not None:
        return _marker_set_trajectories(rig, marker_set, scale, 1.0 / bvh.frame_time, meta)
    return rig_to_trajectories(
        rig,
        markers_per_bone=markers_per_bone,
        random_state=random_state,
        marker_spread=marker_spread,
        merge_rigid=merge_rigid,
        scale=scale,
        up_axis=1,
        frame_rate=1.0 / bvh.frame_time,
        meta=meta,
    )


def _marker_set_trajectories(rig: Rig, marker_set: str, scale: float, frame_rate: float,
                             meta: dict[str, Any]) -> Trajectories:
    """A named marker set on the rig, with the marker set's segment ground truth."""
    names, frames, local = place_cmu41(rig.names, rig.parent, rig.point_names, rig.point_frame, rig.point_local)
    labels_true, part_names, edges, joint_names = segment_ground_truth(names)
    meta = {**meta, "points": f"marker set {marker_set}", "marker_set": marker_set, "joint_names": joint_names}
    return Trajectories(xy=rig.positions(frames, local) * scale, names=names, frame_rate=frame_rate,
                        labels_true=labels_true, part_names=part_names, edges_true=edges, up_axis=1,
                        meta=meta)
