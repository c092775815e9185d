"""SLEAP labels (``.slp``, HDF5): keypoints per animal with the skeleton's edges.

File layout (SLEAP >= 1.0, read with h5py): ``metadata`` attributes hold a JSON
document with ``nodes`` (all node names) and ``skeletons`` (networkx
node-link graphs whose ``nodes`` index into that list and whose ``links`` are
the edges; links of type 2 are symmetries, not bones); ``frames`` maps each
labelled frame to a video and frame index and to a range of ``instances``;
each instance has a ``track`` (-1: none), a type (0 user-labelled, 1
predicted) and a range of ``points`` (user) or ``pred_points`` (predicted) in
skeleton-node order; ``tracks_json`` names the tracks; ``videos_json`` gives
each video's file name. Files with ``format_id < 1.1`` store coordinates with
the pixel's corner at 0 and are shifted by -0.5, as SLEAP does.

Result
------
* Points: one per (track, node), named ``"<track>/<node>"``; P = tracks x nodes.
  Instances without a track get a pseudo-track per slot in their frame
  (``"instance0"``, ``"instance1"``... in the order they are stored).
* Frames: every frame index from the first to the last labelled frame of the
  chosen video; frames nobody labelled are all-NaN (so the frame axis keeps real
  time and ``frame_rate`` stays meaningful). ``meta["frame_offset"]`` is the
  first labelled frame index and ``meta["labelled_frames"]`` the labelled ones
  (relative indices).
* NaN where an instance, a frame or a node (invisible or never placed) is missing.
* ``instances="user"`` (default) reads user-labelled instances, ``"predicted"``
  the predictions, ``"all"`` both (a user instance wins over a prediction for
  the same track and frame).
* ``track=`` (name or index) or ``instance=`` (slot of an untracked instance)
  keeps one animal.
* Ground truth: every keypoint is its own part (``labels_true = arange(P)``) and
  ``edges_true`` holds the skeleton's edges within each track.
* ``image_size`` from the video when the file is found (relative names are
  resolved against the ``.slp``'s folder) and OpenCV can open it, or from the
  video's ``shape`` in the metadata; ``video`` is that path.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..trajectories import Trajectories
from ._common import OptionError, check_file, drop_never_observed, fail

__all__ = ["load_slp"]

_REQUIRED = ("metadata", "frames", "instances", "points")


def _edge_types(links: list[dict]) -> list[int]:
    """Edge type of each link: 1 a bone, 2 a symmetry (jsonpickle ``py/id`` references resolved)."""
    types, seen = [], {}
    for link in links:
        t = link.get("type", 1)
        if isinstance(t, dict) and "py/reduce" in t:
            value = int(t["py/reduce"][1]["py/tuple"][0])
            seen[len(seen) + 1] = value
        elif isinstance(t, dict) and "py/id" in t:
            value = seen.get(int(t["py/id"]), int(t["py/id"]))
        else:
            value = int(t) if isinstance(t, (int, float)) else 1
        types.append(value)
    return types


def _skeleton(path: Path, meta: dict, k: int) -> tuple[list[str], list[tuple[int, int]]]:
    node_names = [n["name"] if isinstance(n, dict) else str(n) for n in meta.get("nodes", [])]
    skels = meta.get("skeletons") or []
    if k >= len(skels):
        raise fail(path, f"instances use skeleton {k}, the file defines {len(skels)}")
    sk = skels[k]
    ids = [n["id"] if isinstance(n, dict) else n for n in sk.get("nodes", [])]
    ids = [i["py/id"] - 1 if isinstance(i, dict) and "py/id" in i else i for i in ids]
    try:
        names = [node_names[i] for i in ids]
        pos = {i: j for j, i in enumerate(ids)}
        links = sk.get("links", [])
        edges = [(pos[lk["source"]], pos[lk["target"]]) for lk, t in zip(links, _edge_types(links)) if t == 1]
    except (IndexError, KeyError, TypeError):
        raise fail(path, "malformed skeleton in the metadata") from None
    return names, edges


def _video_info(path: Path, meta: dict, f: Any, v: int) -> tuple[str | None, tuple[int, int] | None]:
    videos = []
    if "videos_json" in f:
        videos = [json.loads(s) for s in f["videos_json"][:]]
    elif meta.get("videos"):
        videos = meta["videos"]
    if v >= len(videos):
        return None, None
    info = videos[v]
    backend = info.get("backend", {}) if isinstance(info, dict) else {}
    name = (backend.get("filename") or info.get("filename")) if isinstance(info, dict) else None
    size = None
    shape = backend.get("shape")
    if isinstance(shape, (list, tuple)) and len(shape) >= 3:
        size = (int(shape[2]), int(shape[1]))  # (frames, height, width, channels)
    video = None
    if name:
        p = Path(name)
        candidates = [p] if p.is_absolute() else [path.parent / p, path.parent / p.name]
        if p.is_absolute():
            candidates.append(path.parent / p.name)
        found = next((c for c in candidates if c.is_file()), None)
        video = str(found) if found is not None else name
        if found is not None and size is None:
            try:
                import cv2

                cap = cv2.VideoCapture(str(found))
                w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
                cap.release()
                if w > 0 and h > 0:
                    size = (w, h)
            except Exception:  # noqa: BLE001 - the size is optional; an unreadable video leaves it unknown
                size = None
    return video, size


def load_slp(
    path: str | os.PathLike,
    *,
    instances: str = "user",
    track: str | int | None = None,
    instance: int | None = None,
    video_index: int = 0,
    drop_unobserved: bool = False,
) -> Trajectories:
    """Load keypoint tracks from a SLEAP ``.slp`` file.

    Parameters
    ----------
    path : path-like
    instances : {"user", "predicted", "all"}
        Which instances to read.
    track : str or int, optional
        Keep one track (by name or index in the file's track list).
    instance : int, optional
        Keep one untracked instance slot.
    video_index : int
        The video whose labelled frames are read (a project can hold several).
    drop_unobserved : bool
        Drop keypoints never observed (default: keep them as all-NaN points).

    Returns
    -------
    Trajectories
        2D pixel positions (P, F, 2), y down; ``labels_true`` one part per keypoint,
        ``edges_true`` the skeleton's edges per track.
    """
    import h5py

    path = check_file(path)
    if instances not in ("user", "predicted", "all"):
        raise OptionError(f"instances must be 'user', 'predicted' or 'all', got {instances!r}")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise fail(path, f"not a SLEAP file (HDF5) or truncated ({str(exc).splitlines()[0]})") from None
    with f:
        missing = [k for k in _REQUIRED if k not in f]
        if missing:
            raise fail(path, f"not a SLEAP labels file: missing {', '.join(missing)}")
        try:
            meta = json.loads(f["metadata"].attrs["json"])
            format_id = float(f["metadata"].attrs.get("format_id", 1.0))
            frames = f["frames"][:]
            inst = f["instances"][:]
            points = f["points"][:]
            pred = f["pred_points"][:] if "pred_points" in f else points[:0]
            tracks = [json.loads(t) for t in f["tracks_json"][:]] if "tracks_json" in f else []
        except (KeyError, OSError, ValueError, TypeError) as exc:
            raise fail(path, f"malformed SLEAP file ({str(exc).splitlines()[0]})") from None
        video, image_size = _video_info(path, meta, f, video_index)

    frames = frames[frames["video"] == video_index]
    if frames.size == 0:
        raise fail(path, f"no labelled frame in video {video_index}")
    want = {"user": (0,), "predicted": (1,), "all": (0, 1)}[instances]
    fid_to_idx = dict(zip(frames["frame_id"].tolist(), frames["frame_idx"].tolist()))
    keep = np.isin(inst["frame_id"], frames["frame_id"]) & np.isin(inst["instance_type"], want)
    inst = inst[keep]
    if inst.size == 0:
        raise fail(path, f"no {instances} instances in video {video_index}")
    skel_ids = np.unique(inst["skeleton"])
    if skel_ids.size != 1:
        raise fail(path, f"instances use {skel_ids.size} different skeletons; not supported")
    node_names, sk_edges = _skeleton(path, meta, int(skel_ids[0]))
    N = len(node_names)
    if N == 0:
        raise fail(path, "the skeleton has no nodes")

    track_names = [t[1] if isinstance(t, list) and len(t) > 1 else f"track{i}" for i, t in enumerate(tracks)]
    frame_idx = np.array([fid_to_idx[i] for i in inst["frame_id"].tolist()], np.int64)
    # Untracked instances: a pseudo-track per slot within their frame.
    slot = np.zeros(inst.size, np.int64)
    untracked = inst["track"] < 0
    if untracked.any():
        order = np.lexsort((np.arange(inst.size), frame_idx))
        seen: dict[int, int] = {}
        for i in order[untracked[order]]:
            slot[i] = seen.get(int(frame_idx[i]), 0)
            seen[int(frame_idx[i])] = slot[i] + 1
    n_named = len(track_names)
    if inst["track"].max() >= n_named:
        raise fail(path, f"an instance refers to track {inst['track'].max()}, the file names {n_named}")
    n_slots = int(slot[untracked].max()) + 1 if untracked.any() else 0
    col = np.where(untracked, n_named + slot, inst["track"]).astype(np.int64)
    all_names = track_names + [f"instance{k}" for k in range(n_slots)]
    used = np.unique(col)
    if track is not None:
        if isinstance(track, str):
            if track not in track_names:
                raise OptionError(f"track {track!r} is not in {path}; tracks: {', '.join(track_names) or 'none'}")
            sel = track_names.index(track)
        else:
            sel = int(track)
            if not 0 <= sel < n_named:
                raise OptionError(f"track must be in [0, {n_named}), got {track!r}")
        used = np.array([sel])
    elif instance is not None:
        if not 0 <= int(instance) < n_slots:
            raise OptionError(f"instance must be an untracked slot in [0, {n_slots}), got {instance!r}")
        used = np.array([n_named + int(instance)])
    col_pos = {c: k for k, c in enumerate(used.tolist())}
    T = len(used)

    first, last = int(frame_idx.min()), int(frame_idx.max())
    F = last - first + 1
    xy = np.full((T, N, F, 2), np.nan)
    c_of = np.array([col_pos.get(int(c), -1) for c in col.tolist()], np.int64)
    counts = (inst["point_id_end"] - inst["point_id_start"]).astype(np.int64)
    if np.any(counts != N):
        bad = int(np.flatnonzero(counts != N)[0])
        raise fail(path, f"instance {int(inst['instance_id'][bad])} has {counts[bad]} points for {N} nodes "
                         "(inconsistent file)")
    # Predictions first, then user instances, so that user labels win.
    for kind, src in ((1, pred), (0, points)):
        sel = np.flatnonzero((inst["instance_type"] == kind) & (c_of >= 0))
        if sel.size == 0:
            continue
        idx = inst["point_id_start"][sel].astype(np.int64)[:, None] + np.arange(N)  # (I, N)
        if idx.max() >= src.size:
            raise fail(path, f"instances point past the end of the {'points' if kind == 0 else 'pred_points'} "
                             "table (truncated file?)")
        p = src[idx]
        vals = np.stack([p["x"], p["y"]], axis=-1).astype(float)  # (I, N, 2)
        vals[~p["visible"].astype(bool)] = np.nan
        xy[c_of[sel][:, None], np.arange(N)[None, :], (frame_idx[sel] - first)[:, None]] = vals
    if format_id < 1.1:
        xy -= 0.5
    xy = xy.reshape(T * N, F, 2)
    names = [f"{all_names[c]}/{n}" for c in used.tolist() for n in node_names]
    labelled = np.unique(frame_idx - first)
    if F < 2:
        raise fail(path, "only one labelled frame; at least 2 are needed")
    edges = [(k * N + a, k * N + b) for k in range(T) for a, b in sk_edges]
    labels = np.arange(T * N)
    part_names = list(names)
    dropped: list[str] = []
    if drop_unobserved:
        keep_pts = ~np.isnan(xy).any(axis=2).all(axis=1)
        remap = -np.ones(T * N, np.int64)
        remap[keep_pts] = np.arange(int(keep_pts.sum()))
        xy, names, dropped, _ = drop_never_observed(xy, names)
        edges = [(int(remap[a]), int(remap[b])) for a, b in edges if keep_pts[a] and keep_pts[b]]
        labels = np.arange(len(names))
        part_names = list(names)
        if not names:
            raise fail(path, "no keypoint is ever observed")
    return Trajectories(
        xy=xy,
        names=names,
        image_size=image_size,
        labels_true=labels,
        part_names=part_names,
        edges_true=edges,
        video=video,
        meta={
            "source": str(path),
            "format": "slp",
            "units": "px",
            "frame_offset": first,
            "labelled_frames": labelled.tolist(),
            "tracks": [all_names[c] for c in used.tolist()],
            "n_figures": len(used),  # one animal per track
            "nodes": node_names,
            "skeleton_edges": [list(e) for e in sk_edges],
            "instances": instances,
            "dropped_points": dropped,
        },
        allow_unobserved=True,
    )
