"""MoCap Toolbox (Jyväskylä) MATLAB data, e.g. ``mcdemodata.mat``.

A take is a MATLAB struct of type ``'MoCap data'`` with ``markerName`` (N names),
``data`` (F x 3N: x, y, z of marker 1, then marker 2, ...; NaN in gaps), ``freq``
(frame rate) and ``nFrames``. ``load(path, take="walk1")`` picks a take; the
default is the first take in the file (takes without marker names, such as the
one-marker ``wiidata`` of the demo file, are listed but skipped by default).

Ground truth
------------
The toolbox's own skeleton is given by two more structs: ``m2jpar`` maps markers
to joints (each of its 20 joints is the mean of a list of markers) and
``japar.conn`` joins the joints into a 19-edge tree. The joints sit *between*
segments (a knee joint is the knee marker), so they do not say on which rigid
segment each marker is. We therefore label markers by anatomical landmark, with
the same body-segment table as C3D files (:mod:`stickfigure.io.markersets`:
``Head_FL`` → head, ``Radius_L`` → left forearm, ``Knee_L`` → left thigh,
``BigToe_L`` → left foot, ...), and use ``m2jpar`` for what it does give: the
position of each joint between two segments. ``joints_true[e]`` is the
``m2jpar`` joint named like the joint of ``edges_true[e]`` (``lhip``, ``lknee``,
``lankle``, ``neck``, ``lshoulder``, ``lelbow``, ``lwrist``...; the pelvis-thorax
joint is ``midtorso``), the mean of its markers in every frame (NaN where one
is missing). When a struct is absent or a joint cannot be matched,
``joints_true`` is None. ``meta["joint_names"]`` and ``meta["joint_edges"]`` keep
the toolbox's own joint tree (0-based).

Units are millimetres (the toolbox's convention for Qualisys/Vicon data);
``up_axis`` is guessed from the markers (head above feet), else z.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..trajectories import Trajectories
from ._common import OptionError, check_file, drop_never_observed, fail
from .hopkins import read_mat
from .markersets import guess_up_axis, segment_ground_truth

__all__ = ["load_mocaptoolbox", "list_takes", "is_mocaptoolbox"]

# Toolbox joint names (normalised) for each of our joints.
_TOOLBOX_JOINTS = {
    "lumbar": ("midtorso", "root", "torso"),
    "neck": ("neck",),
    "l_shoulder": ("lshoulder",), "r_shoulder": ("rshoulder",),
    "l_elbow": ("lelbow",), "r_elbow": ("relbow",),
    "l_wrist": ("lwrist",), "r_wrist": ("rwrist",),
    "l_hip": ("lhip",), "r_hip": ("rhip",),
    "l_knee": ("lknee",), "r_knee": ("rknee",),
    "l_ankle": ("lankle",), "r_ankle": ("rankle",),
}


def _field(struct: Any, name: str) -> Any:
    """A field of a MATLAB struct as loaded by scipy (record array of shape (1, 1))."""
    try:
        return struct[name][0, 0] if struct.dtype.names and name in struct.dtype.names else None
    except (IndexError, AttributeError, TypeError, ValueError):
        return None


def _strings(a: Any) -> list[str]:
    if a is None:
        return []
    out = []
    for v in np.asarray(a, dtype=object).ravel():
        v = np.asarray(v).ravel()
        out.append(str(v[0]) if v.size else "")
    return out


def _is_take(v: Any) -> bool:
    return (isinstance(v, np.ndarray) and v.dtype.names is not None and "data" in v.dtype.names
            and "markerName" in v.dtype.names)


def is_mocaptoolbox(variables: dict[str, Any]) -> bool:
    """Whether MATLAB variables look like MoCap Toolbox data."""
    return any(_is_take(v) for v in variables.values())


def list_takes(variables: dict[str, Any]) -> list[str]:
    """Names of the MoCap Toolbox takes among MATLAB variables."""
    return [k for k, v in variables.items() if _is_take(v)]


def _joint_tree(variables: dict[str, Any]) -> tuple[list[str], list[list[int]], list[tuple[int, int]]] | None:
    m2j = variables.get("m2jpar")
    if not isinstance(m2j, np.ndarray) or m2j.dtype.names is None:
        return None
    names = _strings(_field(m2j, "markerName"))
    nums = _field(m2j, "markerNum")
    if not names or nums is None:
        return None
    members = []
    for v in np.asarray(nums, dtype=object).ravel():
        members.append([int(i) - 1 for i in np.asarray(v, dtype=float).ravel()])
    if len(members) != len(names):
        return None
    edges: list[tuple[int, int]] = []
    japar = variables.get("japar")
    if isinstance(japar, np.ndarray) and japar.dtype.names is not None:
        conn = _field(japar, "conn")
        if conn is not None:
            conn = np.asarray(conn, dtype=float).reshape(-1, 2)
            edges = [(int(a) - 1, int(b) - 1) for a, b in conn]
    return names, members, edges


def load_mocaptoolbox(path: str | os.PathLike, *, take: str | None = None, drop_unobserved: bool = True,
                      up_axis: int | None = None, variables: dict[str, Any] | None = None) -> Trajectories:
    """Load one take of a MoCap Toolbox ``.mat`` file.

    Parameters
    ----------
    path : path-like
    take : str, optional
        Variable name of the take (``"walk1"``, ...); default: the first take with markers.
    drop_unobserved : bool
        Drop markers that are never observed.
    up_axis : int, optional
        Override the vertical axis.
    variables : dict, optional
        Already-read MATLAB variables (internal use).

    Returns
    -------
    Trajectories
        3D marker positions (P, F, 3) in mm with segment ground truth.
    """
    path = Path(path) if variables is not None else check_file(path)
    m = variables if variables is not None else read_mat(path)
    takes = list_takes(m)
    if not takes:
        raise fail(path, f"no MoCap Toolbox take (struct with 'data' and 'markerName') among {sorted(m)}")
    with_markers = [t for t in takes if _strings(_field(m[t], "markerName"))]
    if take is None:
        if not with_markers:
            raise fail(path, f"no take has marker names; takes: {', '.join(takes)}")
        take = with_markers[0]
    elif take not in takes:
        raise OptionError(f"take {take!r} is not in {path}; takes: {', '.join(takes)}")
    s = m[take]
    names = _strings(_field(s, "markerName"))
    data = _field(s, "data")
    if data is None:
        raise fail(path, f"take {take!r} has no data")
    data = np.asarray(data, dtype=float)
    N = len(names) if names else data.shape[1] // 3 if data.ndim == 2 else 0
    if data.ndim != 2 or N == 0 or data.shape[1] != 3 * N:
        raise fail(path, f"take {take!r}: data must be F x 3N for {N} markers, got shape {data.shape}")
    if not names:
        names = [f"marker{i + 1}" for i in range(N)]
    nf = _field(s, "nFrames")
    if nf is not None and np.size(nf) == 1 and int(np.ravel(nf)[0]) != data.shape[0]:
        raise fail(path, f"take {take!r}: nFrames says {int(np.ravel(nf)[0])}, data has {data.shape[0]} rows")
    freq = _field(s, "freq")
    frame_rate = float(np.ravel(freq)[0]) if freq is not None and np.size(freq) == 1 else None
    xyz = data.reshape(data.shape[0], N, 3).transpose(1, 0, 2).copy()
    xyz[~np.isfinite(xyz)] = np.nan
    dropped: list[str] = []
    if drop_unobserved:
        xyz, names, dropped, _ = drop_never_observed(xyz, names)
        if not names:
            raise fail(path, f"take {take!r}: no marker is ever observed")
    labels_true, part_names, edges, joint_names = segment_ground_truth(names)

    joints_true = None
    meta: dict[str, Any] = {}
    tree = _joint_tree(m)
    if tree is not None:
        tj_names, members, tj_edges = tree
        meta["joint_names"] = tj_names
        meta["joint_edges"] = [list(e) for e in tj_edges]
        full = data.reshape(data.shape[0], -1, 3)
        norm = {re.sub(r"[^a-z0-9]", "", n.lower()): k for k, n in enumerate(tj_names)}
        rows = []
        for jn in joint_names:
            cands = _TOOLBOX_JOINTS.get(jn, ())
            k = next((norm[c] for c in cands if c in norm), None)
            if k is None or not members[k] or max(members[k]) >= full.shape[1]:
                rows = None
                break
            # mean of the joint's markers (repeats weight a marker more, as in the toolbox)
            rows.append(full[:, members[k]].mean(axis=1))
        if rows:
            joints_true = np.stack(rows)
    axis = up_axis if up_axis is not None else guess_up_axis(xyz, labels_true, part_names)
    meta.update({"source": str(path), "format": "mocaptoolbox", "take": take, "takes": takes, "units": "mm",
                 "dropped_points": dropped, "edge_joints": joint_names, "n_figures": 1,
                 "up_axis_source": "argument" if up_axis is not None else
                 ("guessed (head above feet)" if axis is not None else "default (z up)")})
    return Trajectories(
        xy=xyz,
        names=names,
        frame_rate=frame_rate,
        labels_true=labels_true,
        part_names=part_names,
        edges_true=edges,
        joints_true=joints_true,
        up_axis=2 if axis is None else axis,
        meta=meta,
        allow_unobserved=not drop_unobserved,
    )
