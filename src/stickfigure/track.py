"""From a video to point trajectories: a KLT feature tracker (OpenCV).

The papers' real inputs were KLT feature tracks. :func:`track_video` produces
them from any video OpenCV can decode:

1. **Detection.** Shi–Tomasi corners (``cv2.goodFeaturesToTrack``) inside the
   region of interest, at least ``min_distance`` apart.
2. **Tracking.** Pyramidal Lucas–Kanade (``cv2.calcOpticalFlowPyrLK``) from each
   frame to the next, with a **forward–backward check** (Kalal et al. 2010): each
   point is tracked forward, the result tracked back, and the point is lost when it
   does not come back to within ``fb_threshold`` pixels of where it started (or
   LK reports failure, or it leaves the region of interest).
3. **Re-detection.** Every ``redetect_every`` frames, while fewer than
   ``max_points`` tracks are alive, new corners are detected where no live
   track is (a disc of radius ``min_distance`` around every live point is
   masked out). A re-detected feature always starts a *new* trajectory: a lost
   track is never resurrected, so a trajectory is observed on one contiguous run
   of frames and NaN outside it.
4. **Shot cuts.** A cut (an edited video jumping to another scene) ends every
   live track: it is detected when the Bhattacharyya distance between the colour
   histograms of consecutive frames (hue–saturation and value, on a small copy
   of the frame) exceeds ``cut_threshold``. Within a shot that distance stays
   small even under fast camera motion, while a cut changes the whole
   histogram. The first frame of every shot (video frame number) is in
   ``meta["shots"]``.
5. **Clean-up.** Tracks shorter than ``min_length`` and *static* tracks are
   removed. A track is static when its path, after removing the dominant
   (camera/background) motion, stays within ``min_motion`` of the image
   diagonal. The dominant motion between consecutive frames is the similarity
   transform (``cv2.estimateAffinePartial2D``, RANSAC) that most tracks agree on;
   with a fixed camera it is the identity and the test is plain "did not move".
   Set ``stabilize=False`` to measure motion in image coordinates instead (for a
   subject that fills most of the frame and would otherwise be taken for the
   background).

Default thresholds are relative, so they adapt to the video: ``min_distance``
is a fraction of sqrt(area) of the region of interest, ``min_motion`` a fraction
of its diagonal, ``min_length`` a fraction of the number of frames tracked (or
an absolute number of frames). See ``docs/tracking.md``.

Choosing what to learn from
---------------------------
Skeleton methods need points that are observed over a good part of the frames
they are fitted to, and that move relative to each other other than the way a
camera moving through a rigid scene makes them. :func:`best_window` takes each
shot's best-covered window (points observed in at least ``coverage`` of it),
sets aside the points one rigid scene explains where the camera moved
(``meta["camera"]``, recorded by :func:`track_video`), and keeps the window
with the most points moving on their own; ``meta["window"]["verdict"]`` says
when there are none, or when they move as one rigid body.
:func:`stickfigure.pipeline.learn` uses it on tracked videos.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .trajectories import Trajectories

__all__ = ["track_video", "best_window", "VIDEO_SUFFIXES"]

#: File suffixes treated as videos by :func:`stickfigure.pipeline.learn`.
VIDEO_SUFFIXES = frozenset({".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv",
                            ".ogv", ".3gp", ".ts", ".mts"})


def _cv2() -> Any:
    # FFmpeg prints its own complaints ("moov atom not found") on stderr before OpenCV
    # reports failure; the tracker's one-line error says it instead. A user's setting wins.
    # FFmpeg reads it once, at OpenCV's first use of it (the CLI sets it at start-up).
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    import cv2

    return cv2


def _open_video(path: str | os.PathLike) -> tuple[Any, Path]:
    cv2 = _cv2()
    p = Path(path).expanduser()
    if not p.exists():
        raise ValueError(f"video not found: {p}")
    if p.is_dir():
        raise ValueError(f"video path is a directory, not a video file: {p}")
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise ValueError(f"cannot read video {p}: OpenCV could not open it (unknown format or corrupt file)")
    return cap, p.resolve()


def _check_roi(roi: Any, width: int, height: int) -> tuple[int, int, int, int]:
    if roi is None:
        return 0, 0, width, height
    try:
        x, y, w, h = (int(round(float(v))) for v in roi)
    except (TypeError, ValueError):
        raise ValueError(f"roi must be (x, y, width, height) in pixels, got {roi!r}") from None
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + w, width), min(y + h, height)
    if w <= 0 or h <= 0 or x1 - x0 < 8 or y1 - y0 < 8:
        raise ValueError(f"roi {roi!r} leaves less than 8x8 pixels inside the {width}x{height} video")
    return x0, y0, x1 - x0, y1 - y0


def _relative(value: Any, scale: float, name: str) -> float:
    """A threshold given as a fraction of ``scale`` (value < 1) or as an absolute value (>= 1)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return v * scale if v < 1 else v


class _CutDetector:
    """Shot-cut test on colour histograms of consecutive frames (see the module docstring)."""

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)
        self.prev: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, frame: np.ndarray) -> bool:
        cv2 = _cv2()
        h, w = frame.shape[:2]
        small = cv2.resize(frame, (160, max(1, int(round(160 * h / w)))), interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
        hs = cv2.calcHist([hsv], [0, 1], None, [16, 16], [0, 180, 0, 256])
        v = cv2.calcHist([hsv], [2], None, [32], [0, 256])
        cv2.normalize(hs, hs, 1, 0, cv2.NORM_L1)
        cv2.normalize(v, v, 1, 0, cv2.NORM_L1)
        cut = False
        if self.prev is not None and self.threshold > 0:
            # Grey videos have an empty hue-saturation histogram: the value histogram decides.
            d = max(cv2.compareHist(self.prev[0], hs, cv2.HISTCMP_BHATTACHARYYA),
                    cv2.compareHist(self.prev[1], v, cv2.HISTCMP_BHATTACHARYYA))
            cut = d > self.threshold
        self.prev = (hs, v)
        return cut


def track_video(
    path: str | os.PathLike,
    *,
    roi: tuple[int, int, int, int] | None = None,
    start: int = 0,
    stop: int | None = None,
    max_points: int = 500,
    progress: bool = False,
    min_length: float = 0.05,
    min_motion: float = 0.01,
    min_distance: float = 0.01,
    quality: float = 0.01,
    block_size: int = 7,
    window: int = 15,
    levels: int = 3,
    fb_threshold: float = 1.0,
    min_ncc: float = 0.8,
    redetect_every: int = 5,
    cut_threshold: float = 0.3,
    stabilize: bool = True,
) -> Trajectories:
    """Track corner features through a video.

    Parameters
    ----------
    path : str or path-like
        Any video OpenCV can decode.
    roi : (x, y, width, height), optional
        Region of interest in pixels: features are detected in it and a track
        ends when it leaves it. Positions stay in full-frame pixel coordinates.
    start, stop : int
        Frame range ``[start, stop)`` to track (``stop=None``: to the end).
    max_points : int
        Most tracks alive at once.
    progress : bool
        Show a progress bar over frames.
    min_length : float
        Shortest track kept: a fraction of the frames tracked (< 1; at least 10
        frames, at most all of them) or a number of frames (>= 1).
    min_motion : float
        Tracks whose stabilised path fits in a box of diagonal smaller than this
        are static and removed: a fraction of the region's diagonal (< 1) or
        pixels (>= 1). 0 keeps static tracks.
    min_distance : float
        Least distance between features: a fraction of sqrt(area) of the
        region (< 1; at least 3 px) or pixels (>= 1).
    quality : float
        Shi–Tomasi quality level (fraction of the best corner's response).
    block_size : int
        Corner detector neighbourhood in pixels.
    window : int
        Lucas–Kanade window size in pixels.
    levels : int
        Pyramid levels above the full resolution.
    fb_threshold : float
        Forward–backward error (pixels) above which a point is lost.
    min_ncc : float
        Least normalised cross-correlation between a point's neighbourhood
        (side ``2 * (window // 3) + 1``) now and when it was detected, best over
        in-plane rotations (10-degree steps); below it the point is lost. Catches points sliding along an occluding edge, which
        the forward-backward check lets through. -1 disables the test.
    redetect_every : int
        Frames between re-detections.
    cut_threshold : float
        Histogram distance (0..1) above which consecutive frames are a shot
        cut; 0 disables cut detection.
    stabilize : bool
        Measure static-ness after removing the dominant motion (camera pan);
        ``False`` measures it in image coordinates.

    Returns
    -------
    Trajectories
        ``xy`` (P, F, 2) in pixels (y down), NaN outside each track's lifetime,
        with ``image_size``, ``frame_rate``, ``video`` (absolute path) and
        ``meta``: ``frame_offset`` (= ``start``), ``shots`` (first frame of
        each shot, as a frame number of the video, like ``frame_offset``), ``roi``, ``tracker`` (the settings)
        and ``tracking`` (counts: detected, too short, static, kept, seconds).

    Raises
    ------
    ValueError
        Unreadable, missing or empty video, a frame range outside it, a bad
        parameter, or no track surviving the clean-up.
    """
    import time

    cv2 = _cv2()
    from tqdm.auto import tqdm

    start = int(start)
    if start < 0:
        raise ValueError(f"start must be >= 0, got {start}")
    if stop is not None:
        stop = int(stop)
        if stop <= start + 1:
            raise ValueError(f"stop must be at least start + 2 (= {start + 2}) to track 2 frames, got {stop}")
    max_points = int(max_points)
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    redetect_every = max(1, int(redetect_every))
    window = int(window)
    if window < 3:
        raise ValueError(f"window must be >= 3 pixels, got {window}")
    fb_threshold = float(fb_threshold)
    if not fb_threshold > 0:
        raise ValueError(f"fb_threshold must be > 0 pixels, got {fb_threshold}")

    t0 = time.perf_counter()
    cap, vpath = _open_video(path)
    try:
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        n_total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        for i in range(start):  # grab() skips without decoding; more reliable than seeking
            if not cap.grab():
                raise ValueError(f"start frame {start} is beyond the end of {vpath.name} ({i} frames)")
        ok, frame = cap.read()
        if not ok or frame is None:
            if start:
                raise ValueError(f"start frame {start} is beyond the end of {vpath.name}")
            raise ValueError(f"cannot read video {vpath}: it has no decodable frames")
        height, width = frame.shape[:2]
        rx, ry, rw, rh = _check_roi(roi, width, height)
        md = max(3.0, _relative(min_distance, float(np.sqrt(rw * rh)), "min_distance"))
        motion_px = _relative(min_motion, float(np.hypot(rw, rh)), "min_motion")
        roi_mask = np.zeros((height, width), np.uint8)
        roi_mask[ry:ry + rh, rx:rx + rw] = 255
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(md) + 1, 2 * int(md) + 1))
        lk = dict(winSize=(window, window), maxLevel=int(levels),
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        cuts = _CutDetector(cut_threshold)

        expected = None
        if n_total > 0:
            expected = max(0, (min(stop, n_total) if stop is not None else n_total) - start)
        bar = tqdm(total=expected, disable=not progress, unit="frame", desc=f"tracking {vpath.name}",
                   leave=False)

        rec_f: list[np.ndarray] = []  # per frame: frame index, track ids, positions
        rec_id: list[np.ndarray] = []
        rec_xy: list[np.ndarray] = []
        steps: list[np.ndarray] = []  # (F-1) dominant motion from frame f to f+1, 3x3
        # Where the ROI's corners and centre go under each step: how far the camera moved.
        probe = np.array([[rx, ry, 1.0], [rx + rw, ry, 1.0], [rx, ry + rh, 1.0], [rx + rw, ry + rh, 1.0],
                          [rx + rw / 2, ry + rh / 2, 1.0]])
        shots = [0]
        ids = np.zeros(0, np.int64)
        pts = np.zeros((0, 2), np.float32)
        next_id = 0
        n_fb_lost = 0
        n_ncc_lost = 0
        ncc_radius = max(2, window // 3)
        tmpl = np.zeros((0, (2 * ncc_radius + 1) ** 2))
        prev_gray = None
        last_detect = -redetect_every
        k = 0
        while True:
            gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
            color = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
            is_cut = cuts(color)
            if k > 0:
                A = np.eye(3)
                if is_cut:
                    shots.append(k)
                    ids, pts, tmpl = ids[:0], pts[:0], tmpl[:0]
                elif ids.size:
                    old = pts
                    nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, old.reshape(-1, 1, 2), None, **lk)
                    back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray, prev_gray, nxt, None, **lk)
                    nxt = nxt.reshape(-1, 2)
                    fb = np.linalg.norm(back.reshape(-1, 2) - old, axis=1)
                    inside = ((nxt[:, 0] >= rx) & (nxt[:, 0] <= rx + rw - 1)
                              & (nxt[:, 1] >= ry) & (nxt[:, 1] <= ry + rh - 1))
                    good = (st.ravel() == 1) & (st_b.ravel() == 1) & (fb < fb_threshold) & inside
                    n_fb_lost += int((~good).sum())
                    if min_ncc > -1 and good.any():
                        # Compare with the feature's first appearance: a point sliding along an
                        # occluding edge changes its neighbourhood slowly, step by step.
                        ncc = np.full(len(old), -1.0)
                        ncc[good] = _template_ncc(gray, nxt[good], tmpl[good], ncc_radius, min_ncc)
                        similar = ncc >= min_ncc
                        n_ncc_lost += int((good & ~similar).sum())
                        good &= similar
                    A = _dominant_motion(old[good], nxt[good], 2 * fb_threshold, (rx, ry, rw, rh))
                    ids, pts, tmpl = ids[good], nxt[good].astype(np.float32), tmpl[good]
                steps.append(A)
            if ids.size < max_points and (k - last_detect >= redetect_every or ids.size == 0 or is_cut):
                last_detect = k
                mask = roi_mask
                if ids.size:
                    taken = np.zeros_like(roi_mask)
                    xi = np.clip(np.round(pts[:, 0]).astype(int), 0, width - 1)
                    yi = np.clip(np.round(pts[:, 1]).astype(int), 0, height - 1)
                    taken[yi, xi] = 255
                    mask = cv2.bitwise_and(roi_mask, cv2.bitwise_not(cv2.dilate(taken, disc)))
                new = cv2.goodFeaturesToTrack(gray, maxCorners=max_points - ids.size, qualityLevel=float(quality),
                                              minDistance=md, mask=mask, blockSize=int(block_size))
                if new is not None and len(new):
                    new = new.reshape(-1, 2).astype(np.float32)
                    ids = np.concatenate([ids, np.arange(next_id, next_id + len(new))])
                    pts = np.concatenate([pts, new])
                    tmpl = np.concatenate([tmpl, _neighbourhoods(gray, new, ncc_radius)])
                    next_id += len(new)
            rec_f.append(np.full(ids.size, k, np.int64))
            rec_id.append(ids.copy())
            rec_xy.append(pts.copy())
            prev_gray = gray
            k += 1
            bar.update(1)
            if stop is not None and start + k >= stop:
                break
            ok, frame = cap.read()
            if not ok or frame is None:
                break
        bar.close()
    finally:
        cap.release()

    F = k
    if F < 2:
        raise ValueError(f"video {vpath.name} has only {F} frame(s) from frame {start}; need at least 2")
    fr = np.concatenate(rec_f)
    tid = np.concatenate(rec_id)
    xy_obs = np.concatenate(rec_xy).astype(float)
    n_detected = next_id
    if n_detected == 0:
        raise ValueError(f"no trackable features found in {vpath.name} (featureless frames or region of interest)")

    # Order observations by (track, frame): each track is one contiguous run of frames.
    order = np.lexsort((fr, tid))
    fr, tid, xy_obs = fr[order], tid[order], xy_obs[order]
    first = np.r_[True, tid[1:] != tid[:-1]]
    starts = np.flatnonzero(first)
    lengths = np.diff(np.r_[starts, tid.size])
    track_ids = tid[starts]

    min_len = _min_length_frames(min_length, F)
    long_enough = lengths >= min_len

    # Static test: cumulative residual after the dominant motion, per track.
    A = np.stack(steps) if steps else np.zeros((0, 3, 3))
    camera_shift = np.zeros(F)
    if steps:
        moved = probe @ A.transpose(0, 2, 1)  # (F-1, 5, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.linalg.norm(moved[..., :2] / moved[..., 2:] - probe[:, :2], axis=2).mean(axis=1)
        camera_shift[1:] = np.where(np.isfinite(d), d, 0.0)
    if not stabilize:
        A = np.broadcast_to(np.eye(3), (F - 1, 3, 3))
    step_res = np.zeros_like(xy_obs)
    cont = ~first  # the row continues the previous row's track at the previous frame
    if cont.any():
        prev_xy = xy_obs[np.flatnonzero(cont) - 1]
        Af = A[fr[cont] - 1]  # motion from frame f-1 to f
        ph = np.einsum("nij,nj->ni", Af[:, :, :2], prev_xy) + Af[:, :, 2]
        pred = ph[:, :2] / ph[:, 2:]
        step_res[cont] = xy_obs[cont] - pred
    path = np.cumsum(step_res, axis=0)
    path -= np.repeat(path[starts] - step_res[starts], lengths, axis=0)  # restart at each track
    extent = np.hypot(*(np.maximum.reduceat(path, starts, axis=0) - np.minimum.reduceat(path, starts, axis=0)).T)
    moving = extent >= motion_px

    keep = long_enough & moving
    n_keep = int(keep.sum())
    if n_keep == 0:
        raise ValueError(
            f"no track of {vpath.name} survived the clean-up ({n_detected} detected, "
            f"{int((~long_enough).sum())} shorter than {min_len} frames, {int((long_enough & ~moving).sum())} static "
            f"under {motion_px:.1f} px); lower min_length or min_motion"
        )
    new_index = -np.ones(track_ids.size, np.int64)
    new_index[keep] = np.arange(n_keep)
    row_track = np.repeat(new_index, lengths)
    sel = row_track >= 0
    xy = np.full((n_keep, F, 2), np.nan)
    xy[row_track[sel], fr[sel]] = xy_obs[sel]

    shot_of_frame = np.searchsorted(np.asarray(shots), np.arange(F), side="right") - 1
    first_frame = fr[starts][keep]
    elapsed = time.perf_counter() - t0
    meta: dict[str, Any] = {
        "source": "track",
        "frame_offset": start,
        "shots": [start + int(s) for s in shots],  # video frame numbers: they survive slicing
        "roi": [rx, ry, rw, rh],
        "track_start": first_frame.astype(np.int64),
        "track_shot": shot_of_frame[first_frame].astype(np.int64),
        "track_motion": extent[keep].astype(float),
        # Camera motion per frame (pixels, mean over the ROI's corners and centre) from the previous
        # frame, 0 where the camera was taken to be still and at cuts; video frames from first_frame.
        "camera": {"first_frame": start, "shift_px": [round(float(v), 3) for v in camera_shift]},
        "tracker": {
            "max_points": max_points, "min_length_frames": int(min_len), "min_motion_px": float(motion_px),
            "min_distance_px": float(md), "quality": float(quality), "block_size": int(block_size),
            "window": window, "levels": int(levels), "fb_threshold": fb_threshold,
            "redetect_every": redetect_every, "cut_threshold": float(cut_threshold), "stabilize": bool(stabilize),
        },
        "tracking": {
            "frames": F, "detected": int(n_detected), "too_short": int((~long_enough).sum()),
            "static": int((long_enough & ~moving).sum()), "kept": n_keep, "fb_lost": n_fb_lost, "ncc_lost": n_ncc_lost,
            "seconds": round(elapsed, 3),
        },
    }
    return Trajectories(
        xy=xy,
        names=[f"track{int(t)}" for t in track_ids[keep]],
        frame_rate=fps if fps > 0 else None,
        image_size=(width, height),
        video=str(vpath),
        meta=meta,
    )


def _neighbourhoods(img: np.ndarray, p: np.ndarray, r: int, angle: float = 0.0) -> np.ndarray:
    """The (2r+1)^2 neighbourhoods of points ``p`` (n, 2), zero-mean and unit-norm, shape (n, (2r+1)^2).

    Sampled bilinearly (sub-pixel) on a grid turned by ``angle`` (radians),
    with one ``cv2.remap`` for all points, so the dot product of two rows is
    their normalised cross-correlation. A flat neighbourhood becomes all zeros.
    """
    cv2 = _cv2()
    off = np.arange(-r, r + 1, dtype=np.float64)
    gx, gy = np.meshgrid(off, off)
    c, s = np.cos(angle), np.sin(angle)
    gx, gy = c * gx - s * gy, s * gx + c * gy
    k = 2 * r + 1
    mx = (p[:, 0, None, None] + gx[None]).reshape(-1, k).astype(np.float32)
    my = (p[:, 1, None, None] + gy[None]).reshape(-1, k).astype(np.float32)
    v = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    v = v.reshape(len(p), k * k).astype(np.float64)
    v -= v.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 1e-6)


def _template_ncc(img: np.ndarray, p: np.ndarray, tmpl: np.ndarray, r: int, threshold: float) -> np.ndarray:
    """Correlation of each point's neighbourhood with its template, best over in-plane rotations, shape (n,).

    Points on a turning limb keep their appearance up to a rotation, so a
    point below ``threshold`` is tried again at rotations in 10-degree steps
    before it is declared lost.
    """
    ncc = (_neighbourhoods(img, p, r) * tmpl).sum(axis=1)
    low = np.flatnonzero(ncc < threshold)
    for ang in np.radians(np.r_[np.arange(10, 181, 10), -np.arange(10, 180, 10)]):
        if not low.size:
            break
        c = (_neighbourhoods(img, p[low], r, ang) * tmpl[low]).sum(axis=1)
        ncc[low] = np.maximum(ncc[low], c)
        low = low[c < threshold]
    return ncc


def _cell_medians(src: np.ndarray, dst: np.ndarray, roi: tuple[int, int, int, int],
                  grid: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """One representative match per occupied cell of a ``grid`` x ``grid`` division of the region.

    Each is the median position and median displacement of the cell's points,
    so a region counts by its area, not by how many features it has.
    """
    rx, ry, rw, rh = roi
    cx = np.clip(((src[:, 0] - rx) * grid / rw).astype(int), 0, grid - 1)
    cy = np.clip(((src[:, 1] - ry) * grid / rh).astype(int), 0, grid - 1)
    cell = cy * grid + cx
    order = np.argsort(cell, kind="stable")
    cell, s_, d_ = cell[order], src[order], dst[order] - src[order]
    starts = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    groups = np.split(np.arange(cell.size), starts[1:])
    rep_src = np.array([np.median(s_[g], axis=0) for g in groups])
    rep_d = np.array([np.median(d_[g], axis=0) for g in groups])
    return rep_src, rep_src + rep_d


def _dominant_motion(src: np.ndarray, dst: np.ndarray, threshold: float,
                     roi: tuple[int, int, int, int]) -> np.ndarray:
    """The camera's motion between two frames, as a 3x3 homography (the identity for a still camera).

    The camera's motion is the one *most of the frame* follows, not most of
    the features: a figure in front of a still camera can carry more features
    than the background. So the region is divided into 8 x 8 cells, each
    occupied cell gives one representative match (median position and
    displacement of its points), and a homography is fitted to those with
    RANSAC (a similarity with fewer than 12 cells; the identity with fewer
    than 3). A homography is exact for a camera that only turns (pan, tilt,
    zoom) and for a planar background.

    It is kept only if it explains the cells clearly better than no motion
    (median residual at least 0.1 px smaller; chaining per-frame estimates
    integrates their errors, which for a still camera would make the
    background drift) and the cells it explains to half a pixel cover at least
    a quarter of the grid (against a plain background the only features may
    be on the figure; removing *its* motion would make it look static). When
    in doubt the camera is taken to be still, which at worst keeps some
    background tracks.
    """
    cv2 = _cv2()
    src, dst = _cell_medians(src, dst, roi)
    n = len(src)
    thr = max(1.0, float(threshold))
    H = None
    if n >= 12:
        H, _ = cv2.findHomography(src, dst, cv2.RANSAC, thr)
    if H is None and n >= 3:
        M, _ = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=thr)
        if M is not None:
            H = np.vstack([M, [0.0, 0.0, 1.0]])
    if H is None or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
        return np.eye(3)
    H = H / H[2, 2]
    hp = np.c_[src, np.ones(n)] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        res_h = np.linalg.norm(hp[:, :2] / hp[:, 2:] - dst, axis=1)
    res_i = np.linalg.norm(dst - src, axis=1)
    if not np.all(np.isfinite(res_h)) or np.median(res_i) <= np.median(res_h) + 0.1:
        return np.eye(3)
    if (res_h < 0.5).sum() < 16:  # a quarter of the 64 cells
        return np.eye(3)
    return H


def _min_length_frames(min_length: Any, n_frames: int) -> int:
    try:
        v = float(min_length)
    except (TypeError, ValueError):
        raise ValueError(f"min_length must be a fraction of the frames (< 1) or a number of frames, "
                         f"got {min_length!r}") from None
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"min_length must be >= 0, got {min_length!r}")
    if v < 1:
        return int(min(n_frames, max(10, int(np.ceil(v * n_frames)))))
    return int(np.ceil(v))


def best_window(
    traj: Trajectories,
    *,
    min_frames: float = 0.1,
    max_frames: int | None = 400,
    coverage: float = 0.8,
    min_points: int = 10,
    max_points: int | None = 150,
    select: str = "motion",
    scene_tolerance: float = 0.005,
    random_state: Any = 0,
) -> Trajectories:
    """Choose the frame window and the points to learn a skeleton from.

    1. **Coverage, per shot.** For every window ``[a, b)`` (lengths from
       ``min_frames`` to ``max_frames``, every start, never across a shot cut,
       ``meta["shots"]``) the points observed in at least ``coverage`` of its
       frames are counted; each shot's window maximising
       ``min(n_points, max_points) * sqrt(length)`` is its candidate (ties: the
       longer, then the earlier). Points count more than frames: a skeleton
       needs its parts covered by points, while beyond a few dozen frames more
       frames add little.
    2. **Independent motion, per candidate.** Points only tell a skeleton
       apart where they move relative to each other *other than the way a
       camera moving through a rigid scene makes them*. Where the camera moved
       during the window (``meta["camera"]``, written by :func:`track_video`:
       the camera's travel exceeds the tracker's ``min_motion``), the rigid
       scene is fitted: one rank-4 affine motion (a rigid 3D scene under an
       affine camera, so depth parallax is explained) chosen by RANSAC over
       the points, scored by how many cells of an 8 x 8 grid of the image its
       inliers cover (the camera is what most of the *frame* follows). Points
       it explains to within ``scene_tolerance`` (RMS over the window) are the
       scene and are left out; the rest move independently. Where the camera
       was still, the tracker's static test has already removed the
       background, so every point counts.
    3. **Choice.** With ``select="motion"`` the candidate with the most
       independently moving points (``min(n, max_points) * sqrt(length)``,
       at least ``min_points`` of them) wins, and only those points are kept.
       If no candidate has ``min_points`` independently moving points, the
       best-covered window is used and ``meta["window"]["verdict"]`` is
       ``"no independent motion"``. ``select="coverage"`` always takes the
       best-covered window with all its points (the choice before scene
       fitting existed; also what data without camera information get).

    The kept points are also tested for articulation: the share of them that
    a single rigid motion of a plane (rank-3 affine subspace, tolerance half
    ``scene_tolerance``) explains. At 80% or more the verdict is
    ``"one rigid body"`` (e.g. a car driving past a still camera): nothing for
    a skeleton to split. Otherwise it is ``"independent motion"``.
    If more than ``max_points`` points qualify, those observed longest are
    kept, and among equally covered ones a spatially spread subset
    (farthest-point sampling on their mean positions).

    Parameters
    ----------
    traj : Trajectories
    min_frames : float
        Shortest window: a fraction of F (< 1; at least 10 frames) or frames.
    max_frames : int, optional
        Longest window (None: F).
    coverage : float in (0, 1]
        Share of the window's frames a point must be observed in.
    min_points : int
        Windows with fewer qualifying (or, with ``select="motion"``,
        independently moving) points are not chosen unless no window has that
        many.
    max_points : int, optional
        Most points kept.
    select : {"motion", "coverage"}
        Rank candidate windows by independently moving points or by all points.
    scene_tolerance : float
        RMS distance within which the rigid scene explains a point: a fraction
        of the image (or region of interest) diagonal (< 1; at least 1 px) or
        pixels (>= 1).
    random_state : None, int or Generator
        Seed of the RANSAC sampling.

    Returns
    -------
    Trajectories
        ``traj.slice(frames=..., points=...)``; ``meta["window"]`` records the
        choice: ``start``, ``stop`` (relative to ``traj``), ``points`` kept
        of ``of_points``, ``coverage``, ``verdict``, ``message`` (one line
        for a user), ``select`` and ``candidates`` (one dict per shot:
        video frames ``first``/``last``, ``points``, ``scene_points``,
        ``independent``, ``camera_px``, ``rigid_share``, ``score``,
        ``chosen``). Complete data come back whole.
    """
    from ._validation import check_random_state

    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories, got {type(traj).__name__}")
    if not 0 < float(coverage) <= 1:
        raise ValueError(f"coverage must be in (0, 1], got {coverage!r}")
    if select not in ("motion", "coverage"):
        raise ValueError(f"select must be 'motion' or 'coverage', got {select!r}")
    rng = check_random_state(random_state)
    P, F = traj.n_points, traj.n_frames
    obs = traj.observed
    Lmin = min(F, _min_length_frames(min_frames, F)) if float(min_frames) < 1 else min(F, int(min_frames))
    Lmin = max(Lmin, 2)
    Lmax = F if max_frames is None else max(Lmin, min(F, int(max_frames)))
    cap = None if max_points is None else int(max_points)
    cs = np.zeros((P, F + 1), np.int32)
    np.cumsum(obs, axis=1, out=cs[:, 1:])
    # Shot starts are video frame numbers; make them relative to this (possibly sliced) trajectory.
    offset = int(traj.meta.get("frame_offset", 0))
    shots = np.asarray(traj.meta.get("shots", [offset]), np.int64) - offset
    shots = np.unique(np.r_[0, shots[(shots > 0) & (shots < F)]])
    shot_id = np.searchsorted(shots, np.arange(F), side="right") - 1
    S = shots.size
    none = (-1.0, 0, 0, 0, 0)  # (score, length, -start, start, n)
    best = [none] * S  # per shot, among windows with at least min_points points
    best_any = [none] * S

    def scan(lengths: np.ndarray, wanted: np.ndarray) -> None:
        for L in lengths:
            a = np.arange(0, F - L + 1)
            a = a[(shot_id[a] == shot_id[a + L - 1]) & wanted[shot_id[a]]]
            if not a.size:
                continue
            need = int(np.ceil(coverage * L))
            # Points qualifying per start, chunked so memory stays O(P * chunk).
            n = np.empty(a.size, np.int64)
            for c in range(0, a.size, 256):
                aa = a[c:c + 256]
                n[c:c + 256] = ((cs[:, aa + L] - cs[:, aa]) >= need).sum(axis=0)
            # Points beyond max_points would not be kept: they add nothing to a window.
            score = (n if cap is None else np.minimum(n, cap)) * np.sqrt(L)
            sid = shot_id[a]
            for s in np.unique(sid):
                idx = np.flatnonzero(sid == s)
                i = idx[int(np.argmax(score[idx]))]  # first maximum: the earliest start
                cand = (round(float(score[i]), 9), int(L), -int(a[i]), int(a[i]), int(n[i]))
                if cand[:3] > best_any[s][:3]:
                    best_any[s] = cand
                if n[i] >= min_points and cand[:3] > best[s][:3]:
                    best[s] = cand

    # A geometric grid of lengths, then every length between each shot's winner's grid neighbours.
    grid = np.unique(np.round(np.geomspace(Lmin, Lmax, num=min(40, Lmax - Lmin + 1))).astype(int))
    scan(grid, np.ones(S, bool))
    extra: dict[int, set[int]] = {}
    for s in range(S):
        for ref in {best[s][1], best_any[s][1]} - {0}:
            k = int(np.searchsorted(grid, ref))
            lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
            for L in np.setdiff1d(np.arange(lo, hi + 1), grid):
                extra.setdefault(int(L), set()).add(s)
    for L, ss in sorted(extra.items()):
        wanted = np.zeros(S, bool)
        wanted[list(ss)] = True
        scan(np.array([L]), wanted)
    cands = [best[s] if best[s][0] >= 0 else best_any[s] for s in range(S)]
    cands = [(s, c) for s, c in enumerate(cands) if c[0] > 0]
    if not cands:
        raise ValueError(f"no window of at least {Lmin} frames has a point observed in {coverage:.0%} of its frames")

    # Independent motion of each shot's candidate.
    diag = _diagonal(traj)
    tol = _relative(scene_tolerance, diag, "scene_tolerance")
    tol = max(tol, 1.0) if traj.image_size is not None else max(tol, 1e-9)
    cam = _camera_shift(traj)
    travel_min = float(traj.meta.get("tracker", {}).get("min_motion_px", 0.01 * diag))
    rows = []
    for s, (score, L, _, a0, n) in cands:
        need = int(np.ceil(coverage * L))
        qual = np.flatnonzero((cs[:, a0 + L] - cs[:, a0]) >= need)
        travel = None if cam is None else float(cam[a0 + 1:a0 + L].sum())
        scene = np.zeros(qual.size, bool)
        if travel is not None and travel >= travel_min and qual.size > 5 and traj.n_dims == 2:
            res = _rigid_residuals(traj.xy[qual, a0:a0 + L], 4, tol, rng, cells=_cells(traj, qual, a0, L))
            scene = res < tol
        indep = qual[~scene]
        rigid = None
        if indep.size > 4 and traj.n_dims == 2:
            res = _similarity_residuals(traj.xy[indep, a0:a0 + L], 0.5 * tol, rng)
            rigid = float(np.mean(res < 0.5 * tol)) if np.isfinite(res).any() else None
        m = indep.size if cap is None else min(indep.size, cap)
        rows.append({"shot": s, "start": a0, "stop": a0 + L, "first": offset + a0, "last": offset + a0 + L - 1,
                     "points": int(qual.size), "scene_points": int(scene.sum()), "independent": int(indep.size),
                     "camera_px": None if travel is None else round(travel, 1),
                     "rigid_share": None if rigid is None else round(rigid, 3),
                     "coverage_score": round(float(score), 3), "score": round(float(m * np.sqrt(L)), 3),
                     "chosen": False, "_qual": qual, "_indep": indep})

    enough = min(int(min_points), P)
    by_cov = max(rows, key=lambda r: (r["points"] >= enough, r["coverage_score"], r["stop"] - r["start"],
                                      -r["start"]))
    movers = [r for r in rows if r["independent"] >= enough]
    if select == "coverage" or not movers:
        pick = by_cov
    else:
        pick = max(movers, key=lambda r: (r["score"], r["stop"] - r["start"], -r["start"]))
    pick["chosen"] = True
    span = f"frames {pick['first']}-{pick['last']}"
    if pick["independent"] < enough:
        verdict = "no independent motion"
        keep = pick["_qual"]
        most = max(rows, key=lambda r: (r["independent"], -r["start"]))
        message = (f"no independent motion found: no shot has {enough} tracked points that move on their own"
                   + (f" (the most: {most['independent']}, frames {most['first']}-{most['last']})"
                      if most["independent"] else "")
                   + f"; the skeleton is learned from the best-covered window, {span}")
        if pick["scene_points"]:
            message += (f", where one rigid scene seen by the moving camera explains {pick['scene_points']} of its "
                        f"{pick['points']} points, so its sticks divide that scene, not a figure")
    else:
        keep = pick["_indep"] if select == "motion" else pick["_qual"]
        if pick["rigid_share"] is not None and pick["rigid_share"] >= 0.8:
            verdict = "one rigid body"
            message = (f"no articulated motion found: the {pick['independent']} moving points of {span} move as "
                       f"one rigid body (one rigid motion explains {pick['rigid_share']:.0%} of them), so a "
                       "skeleton has nothing to split")
        else:
            verdict = "independent motion"
            where = "a rigid scene seen by the moving camera" if pick["scene_points"] else "the background"
            message = (f"{pick['independent']} points of {span} move independently of {where}"
                       + ("" if pick["rigid_share"] is None else
                          f"; one rigid motion explains only {pick['rigid_share']:.0%} of them"))
    a0, L = pick["start"], pick["stop"] - pick["start"]
    counts = obs[keep, a0:a0 + L].sum(axis=1)
    if cap is not None and keep.size > cap:
        keep = _spread_subset(traj.xy[keep, a0:a0 + L], counts, cap, keep)
    out = traj.slice(frames=slice(a0, a0 + L), points=np.sort(keep))
    for r in rows:
        del r["_qual"], r["_indep"]
    out.meta["window"] = {"start": a0, "stop": a0 + L, "points": int(keep.size), "of_points": P,
                          "coverage": float(coverage), "select": select, "verdict": verdict, "message": message,
                          "scene_tolerance_px": round(float(tol), 3), "candidates": rows}
    return out


def _diagonal(traj: Trajectories) -> float:
    """Diagonal of the tracked region (ROI) or image in pixels; of the data's extent without an image."""
    roi = traj.meta.get("roi")
    if roi is not None and len(roi) == 4:
        return float(np.hypot(roi[2], roi[3]))
    if traj.image_size is not None:
        return float(np.hypot(*traj.image_size))
    flat = traj.xy.reshape(-1, traj.n_dims)
    flat = flat[np.isfinite(flat).all(axis=1)]
    return float(np.linalg.norm(np.ptp(flat, axis=0))) if len(flat) else 1.0


def _camera_shift(traj: Trajectories) -> np.ndarray | None:
    """Camera motion into each frame of ``traj`` (pixels), from ``meta["camera"]``; None when unknown."""
    cam = traj.meta.get("camera")
    if not isinstance(cam, dict) or "shift_px" not in cam:
        return None
    shift = np.asarray(cam["shift_px"], float)
    first = int(traj.meta.get("frame_offset", 0)) - int(cam.get("first_frame", 0))
    if first < 0 or first + traj.n_frames > shift.size:
        return None
    out = shift[first:first + traj.n_frames].copy()
    out[0] = 0.0
    return out


def _cells(traj: Trajectories, points: np.ndarray, a0: int, L: int, grid: int = 8) -> np.ndarray:
    """Cell of a ``grid`` x ``grid`` division of the region that each point's mean position falls in."""
    mean = np.nanmean(traj.xy[points, a0:a0 + L], axis=1)
    roi = traj.meta.get("roi")
    if roi is not None and len(roi) == 4:
        x0, y0, w, h = (float(v) for v in roi)
    elif traj.image_size is not None:
        x0, y0, (w, h) = 0.0, 0.0, traj.image_size
    else:
        x0, y0 = np.min(mean, axis=0)[:2]
        w, h = np.ptp(mean[:, :2], axis=0) + 1e-9
    cx = np.clip(((mean[:, 0] - x0) * grid / w).astype(int), 0, grid - 1)
    cy = np.clip(((mean[:, 1] - y0) * grid / h).astype(int), 0, grid - 1)
    return cy * grid + cx


def _subspace_rms(B: np.ndarray, X: np.ndarray, M: np.ndarray, full: np.ndarray) -> np.ndarray:
    """RMS distance (per observed frame) of each row of ``X`` from the column span of ``B``.

    ``X`` (n, 2L) stacks x then y coordinates (0 where missing), ``M`` the
    matching mask, ``full`` marks complete rows (projected with one QR; the
    others by masked least squares).
    """
    n_obs = np.maximum(M.sum(axis=1) / 2, 1)
    r2 = np.empty(X.shape[0])
    Q, _ = np.linalg.qr(B)
    Xf = X[full]
    r2[full] = np.maximum((Xf ** 2).sum(axis=1) - ((Xf @ Q) ** 2).sum(axis=1), 0.0)
    part = ~full
    if part.any():
        Bm = M[part, :, None] * Q[None]
        G = np.einsum("nkr,nks->nrs", Bm, Bm) + 1e-9 * np.eye(Q.shape[1])
        c = np.linalg.solve(G, np.einsum("nkr,nk->nr", Bm, X[part])[..., None])[..., 0]
        r2[part] = (((X[part] - c @ Q.T) * M[part]) ** 2).sum(axis=1)
    return np.sqrt(r2 / n_obs)


def _similarity_residuals(xy: np.ndarray, tol: float, rng: np.random.Generator, *,
                          n_hypotheses: int = 200) -> np.ndarray:
    """RMS residual of each trajectory under the dominant 2D similarity motion, shape (n,).

    One body moving in the image (turning, moving, nearing the camera) moves
    its points by one similarity per frame, ``x_pf = s_f R_f c_p + t_f``.
    Hypotheses come from two complete trajectories drawn at random (their
    positions in the first frame fix the gauge, each frame's similarity is
    the one taking them there); each point's ``c_p`` is its least-squares
    position in that gauge. The hypothesis with most points within ``tol`` is
    refitted to them (each frame's least-squares similarity) once. Unlike an
    affine motion, a similarity cannot map two bodies moving apart.
    """
    n, L, _ = xy.shape
    obs = np.isfinite(xy).all(axis=2)
    z = np.where(obs, xy[..., 0] + 1j * xy[..., 1], 0)  # (n, L) complex positions
    complete = np.flatnonzero(obs.all(axis=1))
    if complete.size < 3:
        return np.full(n, np.inf)

    def residuals(m: np.ndarray, t: np.ndarray) -> np.ndarray:
        # z_pf ~ m_f c_p + t_f with complex m (scale and rotation): c_p by least squares.
        w = obs * np.abs(m) ** 2
        c = (np.conj(m) * (z - t) * obs).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-12)
        r = np.abs(z - (m * c[:, None] + t)) ** 2 * obs
        return np.sqrt(r.sum(axis=1) / np.maximum(obs.sum(axis=1), 1))

    best, best_n = None, -1
    for _ in range(int(n_hypotheses)):
        p, q = rng.choice(complete, 2, replace=False)
        d0 = z[q, 0] - z[p, 0]
        if abs(d0) < 1e-6:
            continue
        m = (z[q] - z[p]) / d0
        t = z[p] - m * z[p, 0]
        res = residuals(m, t)
        k = int((res < tol).sum())
        if k > best_n:
            best, best_n = res, k
    if best is None:
        return np.full(n, np.inf)
    inl = np.flatnonzero((best < tol) & obs.all(axis=1))
    if inl.size >= 3:  # each frame's least-squares similarity from the inliers' frame-0 positions
        c = z[inl, 0]
        cm, zm = c.mean(), z[inl].mean(axis=0)
        m = (np.conj(c - cm)[:, None] * (z[inl] - zm)).sum(axis=0) / max((np.abs(c - cm) ** 2).sum(), 1e-12)
        best = residuals(m, zm - m * cm)
    return best


def _rigid_residuals(xy: np.ndarray, rank: int, tol: float, rng: np.random.Generator, *,
                     cells: np.ndarray | None = None, n_hypotheses: int = 200, max_frames: int = 60) -> np.ndarray:
    """RMS residual of each trajectory under the dominant rigid motion, shape (n,).

    Trajectories of one rigid body under an affine camera span a ``rank``-4
    affine subspace (rank 4 for a 3D body, depth parallax included; rank 3 for
    a plane moving in 2D). Hypotheses are the spans of ``rank`` complete
    trajectories drawn at random (scored on at most ``max_frames`` evenly
    spaced frames); the best, by the number of distinct ``cells`` holding an
    inlier (within ``tol``) and then by the number of inliers, is refitted to
    its complete inliers by SVD and applied to every trajectory over all frames.
    """
    n, L, _ = xy.shape
    obs = np.isfinite(xy[..., 0])
    X = np.concatenate([np.nan_to_num(xy[..., 0]), np.nan_to_num(xy[..., 1])], axis=1)
    M = np.concatenate([obs, obs], axis=1).astype(float)
    full = obs.all(axis=1)
    complete = np.flatnonzero(full)
    if complete.size < rank + 1:
        return np.full(n, np.inf)
    sub = np.unique(np.round(np.linspace(0, L - 1, min(L, max_frames))).astype(int))
    cols = np.r_[sub, sub + L]
    Xs, Ms, fulls = X[:, cols], M[:, cols], full
    best_key, best_in = (-1, -1), None
    for _ in range(int(n_hypotheses)):
        s = rng.choice(complete, rank, replace=False)
        inl = _subspace_rms(Xs[s].T, Xs, Ms, fulls) < tol
        key = (int(np.unique(cells[inl]).size) if cells is not None else 0, int(inl.sum()))
        if key > best_key:
            best_key, best_in = key, inl
    res = np.full(n, np.inf)
    inl = best_in
    for _ in range(2):  # refit to the complete inliers, then re-select them
        use = np.flatnonzero(inl & full)
        if use.size < rank:
            break
        U, _, _ = np.linalg.svd(X[use].T, full_matrices=False)
        res = _subspace_rms(U[:, :rank], X, M, full)
        inl = res < tol
    return res


def _spread_subset(xy: np.ndarray, counts: np.ndarray, k: int, index: np.ndarray) -> np.ndarray:
    """Keep ``k`` points: the best observed first; ties broken by farthest-point sampling."""
    order = np.argsort(-counts, kind="stable")
    cutoff = counts[order[k - 1]]
    sure = order[counts[order] > cutoff]
    pool = order[counts[order] == cutoff]
    need = k - sure.size
    mean = np.nanmean(xy, axis=1)  # (n, 2); every candidate is observed in the window
    chosen = list(sure)
    if need > 0:
        pm = mean[pool]
        if sure.size:
            d = np.min(np.linalg.norm(pm[:, None] - mean[sure][None], axis=2), axis=1)
        else:  # start next to the centre, then spread out
            j0 = int(np.argmin(np.linalg.norm(pm - pm.mean(axis=0), axis=1)))
            chosen.append(pool[j0])
            need -= 1
            d = np.linalg.norm(pm - pm[j0], axis=1)
            d[j0] = -np.inf
        for _ in range(need):
            j = int(np.argmax(d))
            chosen.append(pool[j])
            d = np.minimum(d, np.linalg.norm(pm - pm[j], axis=1))
            d[j] = -np.inf
    return index[np.asarray(chosen, np.int64)]
