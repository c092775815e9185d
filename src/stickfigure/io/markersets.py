"""Marker names → body segments, and the body's segment tree.

Motion-capture marker sets name markers by anatomical landmark. Markers on the
same bone move rigidly together (up to skin motion), so the landmark decides the
marker's true rigid part. The table covers the Vicon 41-marker set used by the
CMU and HDM05 databases (``LFHD``, ``C7``, ``LSHO``, ``LELB``, ``LWRA``, ``LKNE``,
``LANK``, ...), the Plug-in Gait names (``LASI``, ``LPSI``, ``SACR``, ``LTIB``, ...)
and the MoCap Toolbox demo names (``Head_FL``, ``Shoulder_L``, ``Radius_L``,
``Knee_R``, ``BigToe_L``, ...).

Matching ignores case, a subject prefix (``Male:LFHD``) and punctuation, and
reads the side from a leading or trailing ``L``/``R``/``Left``/``Right`` token
(``LKNE``, ``l_knee``, ``Knee_L``, ``LeftKnee``; ``Head_FL`` is a head marker).

Segments and why each landmark belongs to one
----------------------------------------------
``head``       front/back head markers (a head band).
``thorax``     C7, T10, clavicle notch, sternum, back offset and the acromion
               (``SHO``): the shoulder girdle moves little against the thorax,
               and no marker set here tracks the clavicle on its own.
``pelvis``     waist/iliac markers (``FWT``, ``BWT``, ``ASI``, ``PSI``, ``SACR``).
``*_upperarm`` upper-arm marker and the lateral epicondyle (``ELB``), a point of
               the humerus.
``*_forearm``  forearm marker and the wrist bar (``WRA``/``WRB``: radial and
               ulnar styloids).
``*_hand``     finger / hand markers.
``*_thigh``    thigh marker and the lateral femoral condyle (``KNE``).
``*_shin``     shin/tibia marker and the lateral malleolus (``ANK``).
``*_foot``     heel, toe and metatarsal markers.

The segment tree is the body's: pelvis → thorax → head, thorax → upper arm →
forearm → hand, pelvis → thigh → shin → foot. :func:`segment_ground_truth`
keeps the segments that hold a marker and contracts the tree over the others.
"""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np

__all__ = ["SEGMENTS", "SEGMENT_PARENT", "JOINT_NAMES", "strip_prefix", "segment_of", "segment_ground_truth",
           "contract_tree", "guess_up_axis"]

#: Segments in a fixed order (part numbering follows it).
SEGMENTS: tuple[str, ...] = (
    "pelvis", "thorax", "head",
    "l_upperarm", "l_forearm", "l_hand", "r_upperarm", "r_forearm", "r_hand",
    "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot",
)

#: Parent of each segment in the body tree (the pelvis is the root).
SEGMENT_PARENT: dict[str, str | None] = {
    "pelvis": None, "thorax": "pelvis", "head": "thorax",
    "l_upperarm": "thorax", "l_forearm": "l_upperarm", "l_hand": "l_forearm",
    "r_upperarm": "thorax", "r_forearm": "r_upperarm", "r_hand": "r_forearm",
    "l_thigh": "pelvis", "l_shin": "l_thigh", "l_foot": "l_shin",
    "r_thigh": "pelvis", "r_shin": "r_thigh", "r_foot": "r_shin",
}

#: Name of the joint between each segment and its parent.
JOINT_NAMES: dict[str, str] = {
    "thorax": "lumbar", "head": "neck",
    "l_upperarm": "l_shoulder", "l_forearm": "l_elbow", "l_hand": "l_wrist",
    "r_upperarm": "r_shoulder", "r_forearm": "r_elbow", "r_hand": "r_wrist",
    "l_thigh": "l_hip", "l_shin": "l_knee", "l_foot": "l_ankle",
    "r_thigh": "r_hip", "r_shin": "r_knee", "r_foot": "r_ankle",
}

# Landmarks without a side.
_CENTRAL = {
    "C7": "thorax", "T8": "thorax", "T10": "thorax", "T12": "thorax", "CLAV": "thorax", "CLAVICLE": "thorax",
    "STRN": "thorax", "STER": "thorax", "STERNUM": "thorax", "SPINE": "thorax", "BACK": "thorax",
    "XIPH": "thorax", "RBAK": "thorax", "RBAC": "thorax", "LBAK": "thorax", "LBAC": "thorax",
    "SACR": "pelvis", "SACRUM": "pelvis",
    "HEAD": "head", "FHD": "head", "BHD": "head", "HEADTOP": "head", "FOREHEAD": "head", "ARIEL": "head",
    "THD": "head",
}

# Landmark bases that take a side; "head", "thorax", "pelvis" ignore the side.
_SIDED = {
    "FHD": "head", "BHD": "head", "HEAD": "head", "EAR": "head",
    "SHO": "thorax", "SHOULDER": "thorax", "BAK": "thorax", "BAC": "thorax", "ACR": "thorax",
    "UPA": "upperarm", "UPPERARM": "upperarm", "HUM": "upperarm",
    "ELB": "upperarm", "ELBOW": "upperarm",
    "FRM": "forearm", "FOREARM": "forearm",
    "WRA": "forearm", "WRB": "forearm", "WRI": "forearm", "WRIST": "forearm", "RSP": "forearm", "USP": "forearm",
    "RADIUS": "forearm", "ULNA": "forearm", "RAD": "forearm", "ULN": "forearm",
    "FIN": "hand", "FINGER": "hand", "HAND": "hand", "HND": "hand", "MCP": "hand", "THUMB": "hand", "THM": "hand",
    "FWT": "pelvis", "BWT": "pelvis", "ASI": "pelvis", "PSI": "pelvis", "ASIS": "pelvis", "PSIS": "pelvis",
    "HIP": "pelvis", "ILC": "pelvis", "WAIST": "pelvis", "GTR": "thigh",
    "THI": "thigh", "THIGH": "thigh", "KNE": "thigh", "KNEE": "thigh", "FEM": "thigh", "KNEM": "thigh",
    "KNI": "thigh", "KNM": "thigh", "MKN": "thigh",
    "SHN": "shin", "SHIN": "shin", "TIB": "shin", "TIBIA": "shin", "ANK": "shin", "ANKLE": "shin",
    "ANKM": "shin", "MMA": "shin", "LMA": "shin", "MAL": "shin", "MED": "shin", "TT": "shin", "TUB": "shin",
    "HEE": "foot", "HEEL": "foot", "TOE": "foot", "BIGTOE": "foot", "MT1": "foot", "MT2": "foot",
    "MT5": "foot", "PINKIE": "foot", "FOOT": "foot", "FMH": "foot", "SMH": "foot",
    "VMH": "foot", "TOETIP": "foot",
}
_TRUNK = {"head", "thorax", "pelvis"}
_SIDE_WORDS = {"L": "l", "R": "r", "LEFT": "l", "RIGHT": "r", "LT": "l", "RT": "r"}
_TRAILING_SIDE = {**_SIDE_WORDS, "FL": "l", "BL": "l", "FR": "r", "BR": "r", "UL": "l", "UR": "r"}


def strip_prefix(label: str) -> str:
    """Marker label without a subject prefix (``"Male:LFHD"`` → ``"LFHD"``) or padding."""
    return str(label).rsplit(":", 1)[-1].strip()


def _segment(base: str, side: str | None) -> str | None:
    seg = _SIDED.get(base)
    if seg is None:
        return None
    if seg in _TRUNK:
        return seg
    return f"{side}_{seg}" if side else None


def segment_of(label: str) -> str | None:
    """The body segment a marker name belongs to, or None when it is not in the table.

    >>> segment_of("Male:LFHD"), segment_of("RKNE"), segment_of("Radius_L"), segment_of("*12")
    ('head', 'r_thigh', 'l_forearm', None)
    """
    name = strip_prefix(label)
    tokens = [t.upper() for t in re.split(r"[^A-Za-z0-9]+", name) if t]
    if not tokens:
        return None
    joined = "".join(tokens)
    if joined in _CENTRAL:
        return _CENTRAL[joined]
    # Side as a separate token: "l_knee", "Knee_L", "Head_FL", "Left Knee".
    if len(tokens) > 1:
        if tokens[0] in _SIDE_WORDS:
            seg = _segment("".join(tokens[1:]), _SIDE_WORDS[tokens[0]])
            if seg:
                return seg
        if tokens[-1] in _TRAILING_SIDE:
            seg = _segment("".join(tokens[:-1]), _TRAILING_SIDE[tokens[-1]])
            if seg:
                return seg
    # Side fused to the name: "LKNE", "LeftKnee", "RBWT".
    for word in ("LEFT", "RIGHT", "L", "R"):
        if joined.startswith(word) and len(joined) > len(word):
            seg = _segment(joined[len(word):], _SIDE_WORDS[word])
            if seg:
                return seg
    # Side fused at the end: "KNEEL", "HEADFL".
    for word in ("FL", "FR", "BL", "BR", "L", "R"):
        if joined.endswith(word) and len(joined) > len(word):
            seg = _segment(joined[:-len(word)], _TRAILING_SIDE[word])
            if seg:
                return seg
    seg = _segment(joined, None)
    if seg is None and joined[-1].isdigit() and not joined.rstrip("0123456789").endswith("MT"):
        # Numbered extra markers ("LFIN2", "RTHI1") belong where their base name does.
        base = joined.rstrip("0123456789")
        if base and base != joined:
            return segment_of(base)
    return seg


def contract_tree(parent: dict[str, str | None], present: Sequence[str]) -> list[tuple[str, str]]:
    """Edges of a tree restricted to ``present`` nodes.

    A present node hangs from its nearest present ancestor. Present nodes with
    no present ancestor but the same absent root are joined to the first of
    them (they are connected through that root), so the result stays a tree.

    Returns
    -------
    list of (parent, child) names
    """
    keep = set(present)
    edges: list[tuple[str, str]] = []
    orphans: dict[str, list[str]] = {}
    for node in present:
        p = parent.get(node)
        root = node
        while p is not None and p not in keep:
            root = p
            p = parent.get(p)
        if p is not None:
            edges.append((p, node))
        else:
            while parent.get(root) is not None:
                root = parent[root]  # type: ignore[assignment]
            orphans.setdefault(root, []).append(node)
    for group in orphans.values():
        edges += [(group[0], n) for n in group[1:]]
    return edges


def segment_ground_truth(labels: Sequence[str], groups: Sequence[str] | None = None
                         ) -> tuple[np.ndarray, list[str], list[tuple[int, int]], list[str]]:
    """Ground truth of markers from their names.

    Parameters
    ----------
    labels : sequence of str, length P
        Marker names.
    groups : sequence of str, optional
        A subject per marker (several subjects in one take): each subject gets
        its own parts, named ``"<subject>:<segment>"``.

    Returns
    -------
    labels_true : ndarray of int, shape (P,)
        Part index per marker, -1 for names not in the table.
    part_names : list of str
        The segments that hold at least one marker, in :data:`SEGMENTS` order.
    edges_true : list of (int, int)
        The body tree over those parts, (parent, child).
    joint_names : list of str
        The joint of each edge (:data:`JOINT_NAMES` of the child segment, or
        ``"parent~child"`` for an edge that contracts missing segments).
    """
    groups = list(groups) if groups is not None else [""] * len(labels)
    segs = [segment_of(n) for n in labels]
    part_names: list[str] = []
    edges_named: list[tuple[str, str]] = []
    for g in dict.fromkeys(groups):
        present = [s for s in SEGMENTS if any(seg == s and gg == g for seg, gg in zip(segs, groups))]
        qual = (lambda s: f"{g}:{s}") if g else (lambda s: s)
        part_names += [qual(s) for s in present]
        edges_named += [(qual(a), qual(b)) for a, b in contract_tree(SEGMENT_PARENT, present)]
    index = {n: i for i, n in enumerate(part_names)}
    labels_true = np.array([
        index[(f"{g}:{s}" if g else s)] if s is not None else -1 for s, g in zip(segs, groups)
    ], dtype=np.int64)
    edges = [(index[a], index[b]) for a, b in edges_named]
    joint_names = []
    for a, b in edges_named:
        sa, sb = a.rsplit(":", 1)[-1], b.rsplit(":", 1)[-1]
        joint_names.append(JOINT_NAMES[sb] if SEGMENT_PARENT.get(sb) == sa else f"{sa}~{sb}")
    return labels_true, part_names, edges, joint_names


def guess_up_axis(xy: np.ndarray, labels_true: np.ndarray, part_names: Sequence[str]) -> int | None:
    """The vertical axis of 3D marker data from where the head is above the feet, or None.

    Uses the mean of head (else thorax) markers minus the mean of foot (else
    shin) markers: its largest component is the vertical axis. Returns None
    when the parts are missing or the answer is not clear (largest component
    less than twice the next).
    """
    names = [n.rsplit(":", 1)[-1] for n in part_names]

    def mean_of(segs: tuple[str, ...]) -> np.ndarray | None:
        ids = [i for i, n in enumerate(names) if n in segs]
        if not ids:
            return None
        pts = xy[np.isin(labels_true, ids)]
        if not np.isfinite(pts).any():
            return None
        return np.nanmean(pts.reshape(-1, xy.shape[-1]), axis=0)

    top = mean_of(("head",))
    if top is None:
        top = mean_of(("thorax",))
    bottom = mean_of(("l_foot", "r_foot"))
    if bottom is None:
        bottom = mean_of(("l_shin", "r_shin"))
    if top is None or bottom is None:
        return None
    d = np.abs(top - bottom)
    order = np.argsort(d)[::-1]
    if d[order[0]] < 2 * d[order[1]]:
        return None
    return int(order[0])
