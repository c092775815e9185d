"""What the report shows, computed from a skeleton and its data (no HTML here).

* :func:`player_data` — the JSON the page's player animates: points (observed
  and filled in), sticks, joints and stick labels, placed in every frame by
  :func:`stickfigure.export.pose` (the same placement the pictures of
  :mod:`stickfigure.plot` draw), and the video frames as JPEG data URIs;
* :func:`quality` — reconstruction and imputation errors, segmentation and
  structure scores when the data carry ground truth.
"""

from __future__ import annotations

import base64
import math
from typing import Any

import numpy as np

from ..geometry import articulation
from ..skeleton import Skeleton
from ..trajectories import ISOMETRIC_VIEW, Trajectories, view_rotation

__all__ = ["stick_colors", "flat_pose", "player_data", "video_frames", "quality", "impute"]

UNASSIGNED = "#9e9e9e"


def stick_colors(n: int) -> list[str]:
    """Hex colour of each stick, the same as :func:`stickfigure.plot.stick_colors`."""
    from ..plot import stick_colors as rgba

    return ["#%02x%02x%02x" % tuple(int(round(255 * c)) for c in col[:3]) for col in rgba(n)]


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    ok = ~np.isnan(a)
    n = ok.sum(axis=axis)
    s = np.where(ok, a, 0.0).sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def flat_pose(skeleton: Skeleton, traj: Trajectories) -> dict[str, np.ndarray]:
    """The skeleton placed in every frame (:func:`stickfigure.export.pose`), in 2D.

    3D data are seen in the isometric view of Ross et al. Returns ``points``
    (P, F, 2), ``observed`` (P, F), ``joints`` (E, F, 2) in the order of
    ``skeleton.edges``, ``segments`` (K, 2, F, 2), ``segment_stick`` (K,),
    ``centroids`` (S, F, 2), ``parent_stick`` / ``child_stick`` (E,).
    """
    from ..export import pose

    p = pose(skeleton, traj)
    R = None if p.points.shape[2] == 2 else view_rotation(*ISOMETRIC_VIEW, traj.up_axis)[:2].T

    def flat(x: np.ndarray) -> np.ndarray:
        return x if R is None else x @ R

    return {"points": flat(p.points), "observed": p.observed, "joints": flat(p.joints),
            "segments": flat(p.segments), "segment_stick": p.segment_stick, "centroids": flat(p.centroids),
            "parent_stick": p.parent_stick, "child_stick": p.child_stick}


def _rounded(a: np.ndarray, decimals: int) -> list:
    """Nested lists with NaN as None (JSON null), rounded."""
    r = np.round(a.astype(float), decimals)
    obj = r.astype(object)
    obj[np.isnan(r)] = None
    return obj.tolist()


def video_frames(traj: Trajectories, frames: np.ndarray, *, max_width: int = 640,
                 quality: int = 72) -> list[str] | None:
    """JPEG data URIs of the given frames (indices into ``traj``) of the video ``traj`` was tracked in.

    Returns None when there is no video or it cannot be read. Frames are
    decoded in one pass over the video (no seeking).
    """
    if not traj.video:
        return None
    import cv2

    cap = cv2.VideoCapture(str(traj.video))
    if not cap.isOpened():
        return None
    offset = int(traj.meta.get("frame_offset", 0))
    wanted = sorted(set(int(f) + offset for f in frames))
    got: dict[int, str] = {}
    try:
        i = 0
        k = 0
        while k < len(wanted):
            if i < wanted[k]:
                if not cap.grab():
                    break
                i += 1
                continue
            ok, img = cap.read()
            if not ok:
                break
            h, w = img.shape[:2]
            if w > max_width:
                img = cv2.resize(img, (max_width, int(round(h * max_width / w))), interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
            if ok:
                got[i] = "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii")
            i += 1
            k += 1
    finally:
        cap.release()
    if len(got) != len(wanted):
        return None
    return [got[int(f) + offset] for f in frames]


def _focus_box(xy: np.ndarray, width: int, height: int, *, max_share: float = 0.4) -> list[float] | None:
    """The box (x, y, w, h) around the figure, with a margin, when it covers less than ``max_share`` of the frame.

    The player starts zoomed to it, so a small figure in a large frame (two
    flies in a 1024² arena) is not a speck.
    """
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not xy.size:
        return None
    lo = np.percentile(xy, 1, axis=0)
    hi = np.percentile(xy, 99, axis=0)
    margin = 0.15 * float(np.max(hi - lo)) + 10.0
    x0, y0 = max(0.0, lo[0] - margin), max(0.0, lo[1] - margin)
    x1, y1 = min(float(width), hi[0] + margin), min(float(height), hi[1] + margin)
    # Keep the frame's aspect ratio loosely: never thinner than 1:3.
    w, h = x1 - x0, y1 - y0
    if w <= 0 or h <= 0 or w * h > max_share * width * height:
        return None
    if w < h / 3:
        grow = (h / 3 - w) / 2
        x0, x1 = max(0.0, x0 - grow), min(float(width), x1 + grow)
    if h < w / 3:
        grow = (w / 3 - h) / 2
        y0, y1 = max(0.0, y0 - grow), min(float(height), y1 + grow)
    return [round(x0, 1), round(y0, 1), round(x1 - x0, 1), round(y1 - y0, 1)]


def player_data(skeleton: Skeleton, traj: Trajectories, *, max_frames: int = 150,
                pose: dict[str, np.ndarray] | None = None, with_video: bool = True) -> dict[str, Any]:
    """The JSON the page's player draws.

    At most ``max_frames`` frames are shown (evenly spaced); positions are
    rounded to a precision a screen can show. ``pose`` is :func:`flat_pose`
    when the caller already has it.
    """
    pz = flat_pose(skeleton, traj) if pose is None else pose
    obs = pz["observed"]
    shown = np.where(obs[..., None], pz["points"], np.nan)
    filled = np.where(obs[..., None], np.nan, pz["points"])
    P, F, _ = shown.shape
    step = max(1, math.ceil(F / max_frames))
    fidx = np.arange(0, F, step)
    pixels = traj.image_size is not None
    focus = None
    if pixels:
        width, height = traj.image_size  # type: ignore[misc]
        xmin, ymax, decimals = 0.0, 0.0, 1
        focus = _focus_box(np.concatenate([pz["points"].reshape(-1, 2), pz["segments"].reshape(-1, 2),
                                           pz["joints"].reshape(-1, 2)]), width, height)
    else:
        allxy = np.concatenate([pz["points"].reshape(-1, 2), pz["segments"].reshape(-1, 2),
                                pz["joints"].reshape(-1, 2)])
        allxy = allxy[np.isfinite(allxy).all(axis=1)]
        lo, hi = allxy.min(axis=0), allxy.max(axis=0)
        span = max(float(np.max(hi - lo)), 1e-9)
        lo, hi = lo - 0.05 * span, hi + 0.05 * span
        xmin, ymax = float(lo[0]), float(hi[1])
        width, height = float(hi[0] - lo[0]), float(hi[1] - lo[1])
        decimals = max(0, 3 - int(math.floor(math.log10(span))))
    # Stick labels: at the middle of the stick's first segment, else at its points' centroid.
    label_xy = []
    for s in range(skeleton.n_sticks):
        k = np.flatnonzero(pz["segment_stick"] == s)
        where = pz["segments"][k[0]].mean(axis=0) if k.size else pz["centroids"][s]
        label_xy.append(_rounded(where[fidx], decimals))
    d: dict[str, Any] = {
        "n_frames": int(len(fidx)),
        "fps": (traj.frame_rate or 25.0) / step,
        "frame_numbers": (fidx + int(traj.meta.get("frame_offset", 0))).tolist(),
        "pixels": pixels,
        "width": width,
        "height": height,
        "xmin": xmin,
        "ymax": ymax,
        "labels": skeleton.labels.tolist(),
        "colors": stick_colors(skeleton.n_sticks),
        "unassigned": UNASSIGNED,
        "stick_names": [f"S{s}" for s in range(skeleton.n_sticks)],
        "points": _rounded(shown[:, fidx].transpose(1, 0, 2).reshape(len(fidx), -1), decimals),
        "imputed": (_rounded(filled[:, fidx].transpose(1, 0, 2).reshape(len(fidx), -1), decimals)
                    if np.isfinite(filled).any() else None),
        "segments": [{"stick": int(st), "xy": _rounded(seg[:, fidx].transpose(1, 0, 2).reshape(len(fidx), 4),
                                                       decimals)}
                     for st, seg in zip(pz["segment_stick"], pz["segments"])],
        "joints": [_rounded(j[fidx], decimals) for j in pz["joints"]],
        "stick_label_xy": label_xy,
        "step": step,
        "focus": focus,
    }
    if pixels and with_video:
        uris = video_frames(traj, fidx)
        if uris:
            d["backgrounds"] = uris
            d["background_index"] = list(range(len(uris)))
    return d


def impute(skeleton: Skeleton, traj: Trajectories) -> np.ndarray:
    """``skeleton.impute(traj)``.

    Workaround: ``Skeleton.impute`` in skeleton.py calls the estimator's
    ``impute`` instead of the classmethod ``impute_skeleton``; until that is
    fixed there, call the method's ``impute_skeleton`` here and keep the
    observed entries, which is what ``Skeleton.impute`` documents.
    """
    from ..models import get_method

    try:
        return skeleton.impute(traj)
    except ValueError as exc:
        if "not fitted yet" not in str(exc):
            raise
    filled = np.asarray(get_method(skeleton.method).impute_skeleton(skeleton, traj), dtype=float)
    obs = traj.observed
    filled[obs] = traj.xy[obs]
    return filled


def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def _interpolate_in_time(xy: np.ndarray) -> np.ndarray:
    """Each point's missing positions by linear interpolation over frames (held constant at the ends)."""
    out = xy.copy()
    F = xy.shape[1]
    t = np.arange(F)
    for p in range(xy.shape[0]):  # P is small; np.interp is per series
        ok = ~np.isnan(xy[p, :, 0])
        if ok.sum() == 0:
            continue
        for d in range(xy.shape[2]):
            out[p, ~ok, d] = np.interp(t[~ok], t[ok], xy[p, ok, d])
    return out


def quality(skeleton: Skeleton, traj: Trajectories, *, hide: float = 0.1, seed: int = 0,
            truth: np.ndarray | None = None) -> dict[str, Any]:
    """How well the skeleton explains its data.

    * ``fit_rmse``: RMS distance between the observed positions and those the
      stick motions predict (training frames), when the method has motions.
    * ``impute``: a held-out check on the same frames: ``hide`` of the
      observed entries (chosen at random, seeded) are hidden, the model's
      :meth:`Skeleton.impute` fills them, and the RMS error on them is compared
      with filling them by linear interpolation in time, a model-free baseline.
    * ``hidden``: with ``truth`` (P, F, D), the true positions of entries
      missing from ``traj`` (e.g. the data before an occlusion), the RMS
      error of the model's fill-in on those entries, beside linear
      interpolation in time.
    * ``truth``: with ground-truth labels, the adjusted Rand index and the
      misclassification rate of the sticks, and edge precision/recall/F1 when
      the true tree is known.
    * ``articulation``: :func:`stickfigure.geometry.articulation` of the data, how far
      their motion departs from one rigid body (a property of the clip, not of
      the skeleton: the less the figure bends, the less the data tell its parts apart).

    Distances are in the data's units (pixels for video). Errors inside any
    step are reported as text, not raised: a report is still written.
    """
    out: dict[str, Any] = {"units": "pixels" if traj.image_size is not None else "data units"}
    obs = traj.observed
    true_xy = truth
    if skeleton.motions is not None and skeleton.local is not None and skeleton.n_points == traj.n_points:
        try:
            pred = skeleton.predict()
            if pred.shape == traj.xy.shape:
                m = obs & ~np.isnan(pred[..., 0])
                if m.any():
                    out["fit_rmse"] = _rmse(pred[m], traj.xy[m])
        except Exception as exc:  # a method without predict: say so
            out["fit_rmse_error"] = f"{type(exc).__name__}: {exc}"
    if 0 < hide < 1 and skeleton.n_points == traj.n_points and obs.sum() >= 20:
        try:
            held, hidden = traj.missing_at_random(hide, random_state=seed)
            filled = impute(skeleton, held)
            truth = traj.xy[hidden]
            base = _interpolate_in_time(held.xy)[hidden]
            ok = ~np.isnan(filled[hidden][:, 0])
            out["impute"] = {
                "hidden_fraction": hide,
                "n_hidden": int(hidden.sum()),
                "rmse": _rmse(filled[hidden][ok], truth[ok]) if ok.any() else None,
                "filled_fraction": float(ok.mean()),
                "interp_rmse": _rmse(base, truth),
            }
        except Exception as exc:
            out["impute_error"] = f"{type(exc).__name__}: {exc}"
    if true_xy is not None:
        true_xy = np.asarray(true_xy.xy if isinstance(true_xy, Trajectories) else true_xy, dtype=float)
        if true_xy.shape != traj.xy.shape:
            raise ValueError(f"truth must have the shape of the trajectories {traj.xy.shape}, got {true_xy.shape}")
        hidden = ~obs & np.isfinite(true_xy).all(axis=2)
        if hidden.any():
            try:
                filled = impute(skeleton, traj)[hidden]
                ok = np.isfinite(filled).all(axis=1)
                out["hidden"] = {
                    "n_hidden": int(hidden.sum()),
                    "rmse": _rmse(filled[ok], true_xy[hidden][ok]) if ok.any() else None,
                    "filled_fraction": float(ok.mean()),
                    "interp_rmse": _rmse(_interpolate_in_time(traj.xy)[hidden], true_xy[hidden]),
                }
            except Exception as exc:
                out["hidden_error"] = f"{type(exc).__name__}: {exc}"
    if traj.labels_true is not None and traj.n_points == skeleton.n_points:
        out["truth"] = _truth_scores(skeleton, traj)
    try:
        a = articulation(traj.xy[obs.any(axis=1)])  # a point never seen tells nothing of the motion
        if np.isfinite(a):
            out["articulation"] = a
    except Exception as exc:  # like the steps above: said in the report, not raised
        out["articulation_error"] = f"{type(exc).__name__}: {exc}"
    return out


def _truth_scores(skeleton: Skeleton, traj: Trajectories) -> dict[str, Any]:
    """Segmentation, structure and joint scores against the data's ground truth (:func:`metrics.score_skeleton`)."""
    from ..metrics import score_skeleton

    try:
        return score_skeleton(skeleton, traj)
    except ValueError as exc:  # e.g. joints over other frames than the truth's
        return {"n_parts_true": traj.n_parts_true, "error": str(exc)}
