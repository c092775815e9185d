"""C3D motion-capture files (via ezc3d): labelled 3D markers with gaps.

* Labels: ``POINT:LABELS`` (and ``LABELS2``, ``LABELS3``... for more than 255
  markers); a subject prefix (``Male:LFHD``) is stripped. With several subjects
  in one take the prefixes are kept and each subject gets its own parts.
* Gaps: a negative residual marks an invalid sample (ezc3d returns those as
  NaN); samples at exactly (0, 0, 0), the other common gap marker, are missing
  too (``zeros_as_missing``). Markers never observed are dropped
  (``drop_unobserved``) and listed in ``meta["dropped_points"]``.
* Unlabelled markers (Vicon writes ``*12``) are kept, flagged in
  ``meta["unlabelled"]`` (bool, shape (P,)) and get ``labels_true = -1``.
* ``meta["n_figures"]``: the subjects named by prefixes, 1 when the labels carry
  none, None when no marker is labelled.
* Frame rate: ``POINT:RATE`` (else the header's). Units: ``POINT:UNITS``
  (``meta["units"]``, usually ``"mm"``).
* ``up_axis``: from ``POINT:Y_SCREEN`` (the axis that points up on screen, e.g.
  ``"+Z"``) when the file has it, else z (2), the Vicon convention.
* Ground truth: each marker's body segment from its name
  (:mod:`stickfigure.io.markersets`), the body's segment tree as ``edges_true``.
  No joint positions (``joints_true`` is None): markers sit on the skin, not at
  the joint centres.

ezc3d can loop forever on some truncated files and silently returns fewer
frames on others, so the header and block layout are checked first and a file
shorter than its header declares is rejected with a one-line error.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from ..trajectories import Trajectories
from ._common import check_file, drop_never_observed, fail
from .markersets import segment_ground_truth, strip_prefix

__all__ = ["load_c3d"]

_PROCESSORS = {84: "Intel", 85: "DEC", 86: "MIPS"}


def _dec_float(b: bytes) -> float:
    """A DEC (VAX F) float from its 4 bytes: swap 16-bit halves, then IEEE / 4."""
    return struct.unpack("<f", b[2:4] + b[0:2])[0] / 4.0


def _check_layout(path: Path) -> None:
    """Reject files that are not C3D or are shorter than their header declares."""
    size = path.stat().st_size
    if size < 512:
        raise fail(path, f"not a C3D file or truncated: {size} bytes, less than the 512-byte header")
    with path.open("rb") as fh:
        head = fh.read(512)
        if head[1] != 0x50:
            raise fail(path, "not a C3D file (byte 2 of the header is not the C3D key 0x50)")
        pblock = head[0]
        if pblock < 2:
            raise fail(path, f"not a C3D file (parameter section at block {pblock})")
        pstart = (pblock - 1) * 512
        if size < pstart + 4:
            raise fail(path, f"truncated C3D file: {size} bytes, the parameter section starts at byte {pstart}")
        fh.seek(pstart)
        phead = fh.read(4)
    n_pblocks, proc = phead[2], phead[3]
    if proc not in _PROCESSORS:
        raise fail(path, f"malformed C3D file: unknown processor type {proc}")
    if size < pstart + 512 * max(n_pblocks, 1):
        raise fail(path, f"truncated C3D file: {size} bytes, the parameter section needs "
                         f"{pstart + 512 * n_pblocks}")
    endian = ">" if proc == 86 else "<"
    with path.open("rb") as fh:
        fh.seek(pstart)
        psection = fh.read(512 * max(n_pblocks, 1))
    _check_parameters(path, psection, endian)
    n_points, n_analog, first, last = struct.unpack(endian + "4H", head[2:10])
    scale = _dec_float(head[12:16]) if proc == 85 else struct.unpack(endian + "f", head[12:16])[0]
    data_start = struct.unpack(endian + "H", head[16:18])[0]
    if data_start < 2:
        raise fail(path, f"malformed C3D file: data section at block {data_start}")
    n_frames = last - first + 1 if last >= first else 0
    bytes_per = 4 if scale < 0 else 2
    need = (data_start - 1) * 512 + n_frames * (4 * n_points + n_analog) * bytes_per
    # Long takes (> 65535 frames) clip the header's frame numbers, so this test
    # only errs on the side of accepting; ezc3d's frame count is checked after.
    if size < need:
        frame_bytes = (4 * n_points + n_analog) * bytes_per
        have = max(size - (data_start - 1) * 512, 0) // frame_bytes if frame_bytes else 0
        raise fail(path, f"truncated C3D file: the header declares {n_frames} frames "
                         f"({need} bytes), the file has {size} bytes ({have} complete frames)")


def _check_parameters(path: Path, sec: bytes, endian: str) -> None:
    """Walk the parameter records and check that each is well formed and in bounds.

    Record layout (C3D manual, ch. 3): name length (int8, negative when locked),
    group id (int8, negative for a group), the name, the offset to the next
    record (int16, 0 at the end); a parameter then has its type (-1 char, 1 byte,
    2 int16, 4 float), number of dimensions, dimensions and data; both end with a
    described length and a description. ezc3d can hang on records that break
    these rules, so they are rejected here.
    """
    pos, end = 4, len(sec)
    n_records = 0
    while pos < end:
        if pos + 2 > end:
            raise fail(path, "malformed C3D parameter section (record header past its end)")
        nlen = abs(struct.unpack("b", sec[pos:pos + 1])[0])
        gid = struct.unpack("b", sec[pos + 1:pos + 2])[0]
        if nlen == 0:
            break
        name = sec[pos + 2:pos + 2 + nlen]
        if len(name) < nlen or not all(32 < ch < 127 for ch in name):
            raise fail(path, f"malformed C3D parameter section (bad record name at byte {pos})")
        at = pos + 2 + nlen
        if at + 2 > end:
            raise fail(path, "malformed C3D parameter section (record past its end)")
        offset = struct.unpack(endian + "h", sec[at:at + 2])[0]
        if gid == 0:
            raise fail(path, f"malformed C3D parameter section (record {name.decode()!r} has group id 0)")
        if gid < 0:
            if at + 3 > end:
                raise fail(path, "malformed C3D parameter section (record past its end)")
            desc_end = at + 3 + sec[at + 2]
            if desc_end > end or (offset != 0 and at + offset < desc_end):
                raise fail(path, f"malformed C3D group {name.decode()!r} (description overlaps the next record)")
        else:
            body = at + 2
            if body + 2 > end:
                raise fail(path, "malformed C3D parameter section (record past its end)")
            ptype, ndim = struct.unpack("bB", sec[body:body + 2])
            if ptype not in (-1, 1, 2, 4) or ndim > 7:
                raise fail(path, f"malformed C3D parameter {name.decode()!r} (type {ptype}, {ndim} dimensions)")
            dims = sec[body + 2:body + 2 + ndim]
            count = int(np.prod(list(dims))) if ndim else 1
            data_end = body + 2 + ndim + count * abs(ptype)
            if len(dims) < ndim or data_end + 1 > end:
                raise fail(path, f"malformed C3D parameter {name.decode()!r} (data past the parameter section)")
            desc_end = data_end + 1 + sec[data_end]
            if desc_end > end or (offset != 0 and at + offset < desc_end):
                raise fail(path, f"malformed C3D parameter {name.decode()!r} (next record overlaps its data)")
        if offset == 0:
            break
        if offset < 2 or at + offset > end:
            raise fail(path, f"malformed C3D parameter section (record {name.decode()!r} points to byte {at + offset})")
        pos = at + offset
        n_records += 1
    if n_records == 0:
        raise fail(path, "malformed C3D file: empty parameter section")


def _param(params: dict, group: str, name: str, default=None):
    try:
        return params[group][name]["value"]
    except (KeyError, TypeError):
        return default


def _labels(params: dict, n: int) -> list[str]:
    labels: list[str] = list(_param(params, "POINT", "LABELS", []) or [])
    k = 2
    while len(labels) < n and _param(params, "POINT", f"LABELS{k}") is not None:
        labels += list(_param(params, "POINT", f"LABELS{k}"))
        k += 1
    labels = [str(s).strip() for s in labels[:n]]
    labels += [f"*{i}" for i in range(len(labels), n)]  # unnamed markers count as unlabelled
    return labels


def _up_axis(params: dict) -> tuple[int, str]:
    y_screen = _param(params, "POINT", "Y_SCREEN")
    if y_screen:
        s = str(y_screen[0] if isinstance(y_screen, (list, tuple)) else y_screen).strip().upper()
        if s and s[-1] in "XYZ":
            return "XYZ".index(s[-1]), f"POINT:Y_SCREEN {s}"
    return 2, "default (z up)"


def load_c3d(
    path: str | os.PathLike,
    *,
    zeros_as_missing: bool = True,
    drop_unobserved: bool = True,
    up_axis: int | None = None,
) -> Trajectories:
    """Load the 3D markers of a C3D file.

    Parameters
    ----------
    path : path-like
    zeros_as_missing : bool
        Treat samples at exactly (0, 0, 0) as gaps.
    drop_unobserved : bool
        Drop markers that are never observed (listed in ``meta["dropped_points"]``).
    up_axis : int, optional
        Override the vertical axis.

    Returns
    -------
    Trajectories
        Positions (P, F, 3) in the file's units, NaN in gaps, with ``names``,
        ``frame_rate``, ``labels_true``, ``part_names``, ``edges_true``, and
        ``meta`` keys ``source``, ``units``, ``unlabelled`` (P,), ``first_frame``.
    """
    import ezc3d

    path = check_file(path)
    _check_layout(path)
    try:
        c = ezc3d.c3d(str(path))
    except (RuntimeError, OSError, ValueError, IndexError, MemoryError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise fail(path, f"malformed C3D file ({msg})") from None
    params = c["parameters"]
    header = c["header"]["points"]
    pts = np.asarray(c["data"]["points"], dtype=float)  # (4, P, F)
    if pts.ndim != 3 or pts.shape[1] == 0:
        raise fail(path, "the C3D file holds no 3D points")
    P, F = pts.shape[1], pts.shape[2]
    declared = int(header["last_frame"]) - int(header["first_frame"]) + 1
    if 0 < F < declared and declared < 65535:
        raise fail(path, f"truncated C3D file: the header declares {declared} frames, the file holds {F}")
    if F < 2:
        raise fail(path, f"the C3D file holds {F} frame(s); at least 2 are needed")
    xyz = pts[:3].transpose(1, 2, 0).copy()
    res = c["data"].get("meta_points", {}).get("residuals")
    if res is not None and np.shape(res) == (1, P, F):
        xyz[np.asarray(res)[0] < 0] = np.nan
    if zeros_as_missing:
        xyz[np.all(xyz == 0, axis=2)] = np.nan

    raw = _labels(params, P)
    stripped = [strip_prefix(s) for s in raw]
    unlabelled = np.array([(not s) or s.startswith("*") or s.lower().startswith("unlabel") for s in stripped])
    prefixes = [s.rsplit(":", 1)[0].strip() if ":" in s else "" for s in raw]
    subjects = sorted({p for p, u in zip(prefixes, unlabelled) if p and not u})
    if len(subjects) > 1:
        names, groups = raw, [p if not u else "" for p, u in zip(prefixes, unlabelled)]
    else:
        names, groups = stripped, None
    names = [n if n else f"*{i}" for i, n in enumerate(names)]

    dropped: list[str] = []
    if drop_unobserved:
        xyz, names, dropped, (unlabelled, groups) = drop_never_observed(xyz, names, unlabelled, groups)
        if xyz.shape[0] == 0:
            raise fail(path, "no marker is ever observed")
    labels_true, part_names, edges, joint_names = segment_ground_truth(names, groups)
    labels_true[unlabelled] = -1

    rate = _param(params, "POINT", "RATE")
    frame_rate = float(rate[0]) if rate is not None and len(rate) and rate[0] > 0 else float(header["frame_rate"])
    units = _param(params, "POINT", "UNITS")
    units = str(units[0]).strip() if units is not None and len(units) else None
    axis, axis_source = _up_axis(params)
    n_analog = int(np.shape(c["data"].get("analogs", np.zeros((1, 0, 0))))[1])
    return Trajectories(
        xy=xyz,
        names=names,
        frame_rate=frame_rate if frame_rate > 0 else None,
        labels_true=labels_true,
        part_names=part_names,
        edges_true=edges,
        up_axis=axis if up_axis is None else up_axis,
        meta={
            "source": str(path),
            "format": "c3d",
            "units": units,
            "unlabelled": unlabelled,
            "first_frame": int(header["first_frame"]),
            "frame_offset": int(header["first_frame"]),  # 0-based index of row 0 in the capture
            "dropped_points": dropped,
            "subjects": subjects,
            # Labelled markers of named subjects (one when the labels carry no subject prefix);
            # None when no marker is labelled. EMSkeleton(max_trees="auto") reads it.
            "n_figures": max(len(subjects), 1) if not np.all(unlabelled) else None,
            "joint_names": joint_names,
            "up_axis_source": axis_source if up_axis is None else "argument",
            "analog_channels": n_analog,
        },
        allow_unobserved=not drop_unobserved,
    )
