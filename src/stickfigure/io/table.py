"""stickfigure's own files: a long-format ``.csv`` and a ``.npz`` archive.

CSV (long format)
-----------------
One row per observation, header ``point,frame,x,y`` (2D) or ``point,frame,x,y,z``
(3D), optionally followed by ``label_true``::

    # stickfigure-csv 1
    # frame_rate: 120
    # image_size: 640 480
    point,frame,x,y,label_true
    LFHD,0,12.5,40.25,2
    LFHD,1,12.75,40.5,2
    RFHD,0,,,2

* ``point``: the point's name (any string; CSV quoting applies). Points are
  numbered in order of first appearance.
* ``frame``: integer frame number. Frames run from ``# first_frame`` (default:
  the smallest frame in the file) for ``# n_frames`` frames (default: up to the
  largest frame); a frame nobody observed is all-NaN.
* ``x``, ``y`` (``z``): coordinates. A missing observation is simply absent, or
  a row with empty (or ``nan``) coordinates.
* ``label_true`` (optional): the point's true part (integer, -1 for none); it
  must be the same on all rows of a point.
* Lines starting with ``#`` before the header are comments; those of the form
  ``# key: value`` set ``frame_rate``, ``image_size`` (width height),
  ``up_axis``, ``first_frame``, ``n_frames``, ``part_names`` (JSON list),
  ``edges_true`` (JSON list of pairs), ``video`` and ``units``. Unknown keys are
  ignored.

The writer emits every observed entry with the shortest decimal that reads back
to the same float (exact round trip), one empty row for a point that is never
observed (so that it survives), and the comment keys above. ``joints_true`` and
other ``meta`` are not stored in CSV; use ``.npz`` for a full copy.

NPZ
---
A NumPy archive without pickled objects (``allow_pickle=False``): ``xy``,
``names`` (unicode), ``frame_rate``, ``image_size``, ``labels_true``,
``edges_true`` (E, 2), ``part_names``, ``joints_true``, ``video``, ``up_axis``,
``allow_unobserved``, ``meta_json`` (the JSON-serialisable part of ``meta``) and
``meta__<key>`` for each array-valued ``meta`` entry; absent fields are absent.
``format`` holds ``"stickfigure-npz"`` and ``version`` the format version.
"""

from __future__ import annotations

import csv
import io as _io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .._atomic import atomic_path
from ..trajectories import Trajectories
from ._common import check_file, fail

__all__ = ["load_csv", "save_csv", "load_npz", "save_npz"]

_CSV_VERSION = 1
_NPZ_VERSION = 1


# ----------------------------------------------------------------------- CSV
def _comment_header(traj: Trajectories) -> list[str]:
    lines = [f"# stickfigure-csv {_CSV_VERSION}"]
    if traj.frame_rate is not None:
        lines.append(f"# frame_rate: {traj.frame_rate!r}")
    if traj.image_size is not None:
        lines.append(f"# image_size: {traj.image_size[0]} {traj.image_size[1]}")
    if traj.n_dims == 3:
        lines.append(f"# up_axis: {traj.up_axis}")
    offset = int(traj.meta.get("frame_offset", 0) or 0)
    lines.append(f"# first_frame: {offset}")
    lines.append(f"# n_frames: {traj.n_frames}")
    if traj.part_names is not None:
        lines.append(f"# part_names: {json.dumps(traj.part_names)}")
    if traj.edges_true is not None:
        lines.append(f"# edges_true: {json.dumps([list(e) for e in traj.edges_true])}")
    if traj.video:
        lines.append(f"# video: {traj.video}")
    if traj.meta.get("units"):
        lines.append(f"# units: {traj.meta['units']}")
    return lines


def _quote(field: str) -> str:
    """CSV quoting (RFC 4180) when the field needs it; the csv module of Python 3.11 leaves a bare CR unquoted."""
    if any(ch in field for ch in ',"\r\n') or field != field.strip():
        return '"' + field.replace('"', '""') + '"'
    return field


def save_csv(traj: Trajectories, path: str | os.PathLike) -> Path:
    """Write trajectories as a long-format CSV (atomically).

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    P, F, D = traj.shape
    offset = int(traj.meta.get("frame_offset", 0) or 0)
    names = traj.names if traj.names is not None else [str(p) for p in range(P)]
    if len(set(names)) != len(names):
        raise ValueError("points must have unique names to be written as CSV")
    obs = traj.observed
    p_idx, f_idx = np.nonzero(obs)  # row-major: grouped by point, frames ascending
    coords = traj.xy[p_idx, f_idx]
    label = traj.labels_true
    lines = [line.replace("\n", " ").replace("\r", " ") for line in _comment_header(traj)]
    header = ["point", "frame", "x", "y"] + (["z"] if D == 3 else []) + (["label_true"] if label is not None else [])
    lines.append(",".join(header))
    qnames = [_quote(n) for n in names]
    lab = [f",{int(v)}" for v in label] if label is not None else [""] * P
    # repr() of a Python float is the shortest string that reads back exactly.
    rows_by_point: dict[int, list[str]] = {}
    for p, f, c in zip(p_idx.tolist(), f_idx.tolist(), coords.tolist()):
        rows_by_point.setdefault(p, []).append(f"{qnames[p]},{f + offset},{','.join(map(repr, c))}{lab[p]}")
    for p in range(P):
        lines += rows_by_point.get(p) or [f"{qnames[p]},{offset}{',' * D}{lab[p]}"]  # never observed: empty row
    text = "\n".join(lines) + "\n"
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
    return path


def _parse_comment(path: Path, line: str, opts: dict[str, Any]) -> None:
    body = line[1:].strip()
    key, sep, value = body.partition(":")
    if not sep:
        return
    key, value = key.strip().lower(), value.strip()
    try:
        if key == "frame_rate":
            opts[key] = float(value)
        elif key == "image_size":
            w, h = value.replace(",", " ").split()
            opts[key] = (int(w), int(h))
        elif key in ("up_axis", "first_frame", "n_frames"):
            opts[key] = int(value)
        elif key in ("part_names", "edges_true"):
            opts[key] = json.loads(value)
        elif key in ("video", "units"):
            opts[key] = value
    except (ValueError, json.JSONDecodeError):
        raise fail(path, f"bad '# {key}:' line: {value!r}") from None


def load_csv(path: str | os.PathLike) -> Trajectories:
    """Read a long-format CSV (see the module docstring)."""
    path = check_file(path)
    try:
        # newline="" keeps quoted line breaks inside names for the csv module.
        with open(path, encoding="utf-8-sig", newline="") as fh:
            text = fh.read()
    except UnicodeDecodeError:
        raise fail(path, "not a UTF-8 text file") from None
    opts: dict[str, Any] = {}
    pos = 0
    n_comment_lines = 0
    while pos < len(text):
        nl = text.find("\n", pos)
        end = len(text) if nl < 0 else nl + 1
        line = text[pos:end].strip()
        if line and not line.startswith("#"):
            break
        if line:
            _parse_comment(path, line, opts)
        n_comment_lines += 1
        pos = end
    if pos >= len(text):
        raise fail(path, "no header line (expected 'point,frame,x,y[,z]')")
    reader = csv.reader(_io.StringIO(text[pos:], newline=""))
    start = n_comment_lines
    header = [h.strip().lower() for h in next(reader)]
    if header[:4] != ["point", "frame", "x", "y"]:
        raise fail(path, f"header must start with 'point,frame,x,y', got {','.join(header)!r}")
    D = 3 if len(header) > 4 and header[4] == "z" else 2
    cols = {h: i for i, h in enumerate(header)}
    if len(cols) != len(header):
        raise fail(path, "duplicate column names in the header")
    lab_col = cols.get("label_true")
    need = max(cols["x"], cols["y"], cols.get("z", 0), lab_col if lab_col is not None else 0) + 1
    point_index: dict[str, int] = {}
    pts, frames, vals, labels = [], [], [], {}
    for row in reader:
        lineno = start + reader.line_num
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) < need:
            raise fail(path, f"line {lineno}: {len(row)} columns, expected {len(header)} (truncated file?)")
        name = row[0]
        p = point_index.setdefault(name, len(point_index))
        try:
            fr = int(row[1])
        except ValueError:
            raise fail(path, f"line {lineno}: frame {row[1]!r} is not an integer") from None
        coord = []
        for k in ("x", "y", "z")[:D]:
            c = row[cols[k]].strip()
            try:
                coord.append(float(c) if c else np.nan)
            except ValueError:
                raise fail(path, f"line {lineno}: {k} = {c!r} is not a number") from None
        if lab_col is not None:
            c = row[lab_col].strip()
            try:
                lab = int(c) if c else -1
            except ValueError:
                raise fail(path, f"line {lineno}: label_true = {c!r} is not an integer") from None
            if labels.setdefault(p, lab) != lab:
                raise fail(path, f"line {lineno}: point {name!r} has two different label_true values")
        pts.append(p)
        frames.append(fr)
        vals.append(coord)
    if not pts:
        raise fail(path, "no data rows")
    pts_a = np.asarray(pts, np.int64)
    fr_a = np.asarray(frames, np.int64)
    v = np.asarray(vals, float)
    if np.isinf(v).any():
        raise fail(path, "infinite coordinates; use an empty field for a missing observation")
    first = int(opts.get("first_frame", fr_a.min()))
    if fr_a.min() < first:
        raise fail(path, f"frame {fr_a.min()} is before '# first_frame: {first}'")
    F = int(opts.get("n_frames", fr_a.max() - first + 1))
    if fr_a.max() - first >= F:
        raise fail(path, f"frame {fr_a.max()} is past '# n_frames: {F}' (from frame {first})")
    P = len(point_index)
    xy = np.full((P, F, D), np.nan)
    ok = ~np.isnan(v).any(axis=1)
    # Two rows for the same observed (point, frame) are ambiguous.
    key = pts_a[ok] * F + (fr_a[ok] - first)
    uniq, counts = np.unique(key, return_counts=True)
    if np.any(counts > 1):
        k = int(uniq[counts > 1][0])
        raise fail(path, f"point {list(point_index)[k // F]!r} has several rows for frame {k % F + first}")
    xy[pts_a[ok], fr_a[ok] - first] = v[ok]
    label_arr = None
    if lab_col is not None:
        label_arr = np.array([labels.get(p, -1) for p in range(P)], np.int64)
    meta = {"source": str(path), "format": "csv", "frame_offset": first}
    if "units" in opts:
        meta["units"] = opts["units"]
    try:
        return Trajectories(
            xy=xy,
            names=list(point_index),
            frame_rate=opts.get("frame_rate"),
            image_size=opts.get("image_size") if D == 2 else None,
            labels_true=label_arr,
            part_names=opts.get("part_names"),
            edges_true=[tuple(e) for e in opts["edges_true"]] if "edges_true" in opts else None,
            video=opts.get("video"),
            up_axis=opts.get("up_axis", 2),
            meta=meta,
            allow_unobserved=True,
        )
    except (ValueError, TypeError) as exc:
        raise fail(path, str(exc)) from None


# ----------------------------------------------------------------------- NPZ
def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except (TypeError, ValueError):
        return False


def save_npz(traj: Trajectories, path: str | os.PathLike) -> Path:
    """Write trajectories, ground truth and metadata to a ``.npz`` archive (atomically, no pickle)."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {
        "format": np.array("stickfigure-npz"),
        "version": np.array(_NPZ_VERSION),
        "xy": np.asarray(traj.xy, float),
        "up_axis": np.array(traj.up_axis),
        "allow_unobserved": np.array(bool(traj.allow_unobserved)),
    }
    if traj.names is not None:
        arrays["names"] = np.array(traj.names, dtype=str) if traj.names else np.zeros(0, "U1")
    if traj.frame_rate is not None:
        arrays["frame_rate"] = np.array(traj.frame_rate, float)
    if traj.image_size is not None:
        arrays["image_size"] = np.array(traj.image_size, np.int64)
    if traj.labels_true is not None:
        arrays["labels_true"] = np.asarray(traj.labels_true, np.int64)
    if traj.edges_true is not None:
        arrays["edges_true"] = np.array(traj.edges_true, np.int64).reshape(-1, 2)
    if traj.part_names is not None:
        arrays["part_names"] = np.array(traj.part_names, dtype=str) if traj.part_names else np.zeros(0, "U1")
    if traj.joints_true is not None:
        arrays["joints_true"] = np.asarray(traj.joints_true, float)
    if traj.video is not None:
        arrays["video"] = np.array(str(traj.video))
    meta_json: dict[str, Any] = {}
    skipped = []
    for k, v in traj.meta.items():
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                skipped.append(k)
                continue
            arrays[f"meta__{k}"] = v
        elif _jsonable(v):
            meta_json[k] = v
        else:
            skipped.append(k)
    if skipped:
        meta_json["_not_saved"] = skipped
    arrays["meta_json"] = np.array(json.dumps(meta_json))
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


def load_npz(path: str | os.PathLike) -> Trajectories:
    """Read a ``.npz`` written by :func:`save_npz` (or any archive with an ``xy`` array)."""
    path = check_file(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "pickle" in msg.lower():
            raise fail(path, "the archive holds pickled objects, which are not read (allow_pickle=False)") from None
        raise fail(path, f"not a readable .npz archive or truncated ({msg})") from None
    if "xy" not in data:
        raise fail(path, f"no 'xy' array in the archive (found {', '.join(sorted(data)) or 'nothing'})")

    def scalar(key: str, kind: type) -> Any:
        return kind(data[key].item()) if key in data else None

    try:
        meta = json.loads(str(data["meta_json"].item())) if "meta_json" in data else {}
    except json.JSONDecodeError:
        raise fail(path, "meta_json is not valid JSON") from None
    for k, v in data.items():
        if k.startswith("meta__"):
            meta[k[len("meta__"):]] = v
    meta["source"] = str(path)
    meta.setdefault("format", "npz")
    try:
        return Trajectories(
            xy=data["xy"],
            names=data["names"].tolist() if "names" in data else None,
            frame_rate=scalar("frame_rate", float),
            image_size=tuple(int(v) for v in data["image_size"]) if "image_size" in data else None,
            labels_true=data.get("labels_true"),
            edges_true=[tuple(int(a) for a in e) for e in data["edges_true"]] if "edges_true" in data else None,
            part_names=data["part_names"].tolist() if "part_names" in data else None,
            joints_true=data.get("joints_true"),
            video=scalar("video", str),
            up_axis=int(data["up_axis"].item()) if "up_axis" in data else 2,
            meta=meta,
            allow_unobserved=bool(data["allow_unobserved"].item()) if "allow_unobserved" in data else True,
        )
    except (ValueError, TypeError) as exc:
        raise fail(path, str(exc).splitlines()[0]) from None
