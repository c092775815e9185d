"""Figures and animations: generic drawing here, one module per method's diagnostics.

Generic pictures of a learned :class:`~stickfigure.skeleton.Skeleton` over its
trajectories (matplotlib; any backend, Agg is enough):

* :func:`draw_frame` draws one frame on an Axes: points coloured by stick
  (unassigned points grey), sticks as lines, joints as white circles, missing
  points as hollow markers at their imputed positions when those are given,
  and the true positions of hidden points when given.
* :func:`plot_frames` a grid of chosen frames, to a Figure or a PNG.
* :func:`animate` a GIF or MP4 over the frames, over the video frames when the
  trajectories came from a video (``traj.video``).
* :func:`draw_tree` the stick tree as a graph.

How a stick is drawn
--------------------
Each stick is drawn through its *anchors* (see :mod:`stickfigure.export`,
which computes them in :func:`stickfigure.export.pose`): a stick with two or
more joints is the minimum spanning tree of its joints (a chain link is the
line between its two joints; a torso joins neck, shoulders and hips); a stick
with one joint runs from the joint through its points' centroid to its
farthest point's projection (a hand, a head); a stick without joints is the
segment of its principal axis its points span. This is what a stick figure
looks like: the lines meet at the joints.

Axes follow the data: image data (``traj.image_size`` set) are drawn with the
y axis pointing down over the image's extent, other 2D data with y up; the
aspect is always equal. 3D data are drawn in their first two coordinates
unless a ``view`` is given (an azimuth/elevation for
:meth:`Trajectories.project`).

Method diagnostics: :mod:`stickfigure.plot.mitree` (and ``em``, ``mcmc``
modules where those methods are installed).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .._atomic import atomic_path
from ..skeleton import Skeleton, as_trajectories_unobserved
from ..trajectories import Trajectories

__all__ = ["stick_colors", "draw_frame", "plot_frames", "animate", "draw_tree", "select_frames"]

UNASSIGNED = (0.62, 0.62, 0.62, 1.0)


def stick_colors(n_sticks: int) -> np.ndarray:
    """Distinct RGBA colours for ``n_sticks`` sticks, shape (n_sticks, 4)."""
    from matplotlib import colormaps

    n = max(int(n_sticks), 0)
    if n <= 10:
        return np.asarray(colormaps["tab10"](np.arange(n)))
    if n <= 20:
        return np.asarray(colormaps["tab20"](np.arange(n)))
    return np.asarray(colormaps["hsv"](np.linspace(0, 1, n, endpoint=False)))


def select_frames(frames: Any, n_frames: int, *, default_count: int | None = None) -> np.ndarray:
    """Frame indices from an int, a slice, an iterable of ints, a bool mask or a ``"a:b[:k]"`` string.

    ``None`` gives all frames, or ``default_count`` evenly spaced ones when that is set.
    Negative indices count from the end.

    Raises
    ------
    ValueError
        An index out of range, an empty selection or a malformed string.
    """
    if frames is None:
        if default_count is not None and default_count < n_frames:
            return np.unique(np.linspace(0, n_frames - 1, default_count).round().astype(np.int64))
        return np.arange(n_frames)
    if isinstance(frames, str):
        frames = parse_frame_range(frames)
    if isinstance(frames, slice):
        idx = np.arange(n_frames)[frames]
    else:
        arr = np.atleast_1d(np.asarray(frames))
        if arr.dtype == bool:
            if arr.shape != (n_frames,):
                raise ValueError(f"a frame mask must have shape ({n_frames},), got {arr.shape}")
            idx = np.flatnonzero(arr)
        else:
            if arr.size and not np.issubdtype(arr.dtype, np.integer):
                raise ValueError(f"frames must be integers, got {arr.dtype}")
            idx = arr.astype(np.int64)
            if idx.size and (idx.min() < -n_frames or idx.max() >= n_frames):
                raise ValueError(f"frame index out of range: the data have {n_frames} frames (0..{n_frames - 1})")
            idx = np.where(idx < 0, idx + n_frames, idx)
    if idx.size == 0:
        raise ValueError(f"the frame selection {frames!r} is empty (the data have {n_frames} frames)")
    return idx


def parse_frame_range(text: str) -> slice | list[int]:
    """Parse ``"a:b"``, ``"a:b:k"``, ``":b"`` (a Python slice) or ``"3,10,20"`` (a list of frames)."""
    t = text.strip()
    try:
        if ":" in t:
            parts = t.split(":")
            if len(parts) > 3:
                raise ValueError
            vals = [int(p) if p.strip() else None for p in parts]
            if len(vals) == 3 and vals[2] is not None and vals[2] <= 0:
                raise ValueError
            return slice(*vals)
        return [int(p) for p in t.split(",") if p.strip()]
    except ValueError:
        raise ValueError(f"frames must look like 'a:b', 'a:b:step' or '3,10,20', got {text!r}") from None


# ------------------------------------------------------------------ drawing
def _as_traj(traj: Any) -> Trajectories:
    if isinstance(traj, Trajectories):
        return traj
    if isinstance(traj, (np.ndarray, list, tuple)):
        return as_trajectories_unobserved(traj)
    raise TypeError(f"traj must be a Trajectories or an array of shape (P, F, D), got {type(traj).__name__}")


class _Scene:
    """Everything needed to draw any frame of one clip: colours, pose, limits.

    Built once, then :meth:`draw` creates the artists on an Axes and
    :meth:`update` moves them to another frame, so animations do not rebuild
    the figure for every frame.
    """

    def __init__(self, traj: Any, skeleton: Skeleton | None = None, *, imputed: Any = None, truth: Any = None,
                 pose: Any = None, view: Any = None, point_size: float = 18.0, line_width: float = 3.0,
                 joint_size: float = 45.0, follow: bool = False):
        traj = _as_traj(traj)
        if skeleton is not None and not isinstance(skeleton, Skeleton):
            raise TypeError(f"skeleton must be a stickfigure Skeleton, got {type(skeleton).__name__}")
        if skeleton is not None and skeleton.n_points != traj.n_points:
            raise ValueError(f"traj has {traj.n_points} points, but the skeleton was fitted to {skeleton.n_points}")
        P, F, D = traj.shape
        self.traj = traj
        self.point_size, self.line_width, self.joint_size = point_size, line_width, joint_size
        self.projector = None
        if D == 3:
            if view is not None:
                flat = traj.project(view)
                M = flat.meta["projection"]
                from ..trajectories import view_rotation

                self.projector = view_rotation(M["azimuth"], M["elevation"], traj.up_axis)[:2].T
            else:
                self.projector = np.eye(3)[:, :2]
        self.image_size = traj.image_size
        if skeleton is not None and pose is None:
            from ..export import pose as _pose

            pose = _pose(skeleton, traj)
        self.pose = pose
        if skeleton is not None:
            labels, n = skeleton.labels, skeleton.n_sticks
        elif traj.labels_true is not None:
            labels, n = traj.labels_true, int(traj.n_parts_true or 0)
        else:
            labels, n = np.zeros(P, np.int64), 1
        self.colors = stick_colors(n)
        self.point_colors = np.array([self.colors[l] if l >= 0 else UNASSIGNED for l in labels]).reshape(P, 4)
        self.xy = self._flat(traj.xy)
        self.obs = traj.observed
        if imputed is True:
            if pose is None:
                raise ValueError("imputed=True needs a skeleton (its predictions fill the missing points)")
            imputed = pose.points
        self.imputed = None if imputed is None else self._flat(self._check(imputed, traj, "imputed"))
        self.truth = None if truth is None else self._flat(self._check(truth, traj, "truth"))
        if pose is not None:
            self.segments = self._flat(pose.segments)  # (K, 2, F, 2)
            self.seg_colors = self.colors[pose.segment_stick] if pose.segment_stick.size else np.zeros((0, 4))
            self.joints = self._flat(pose.joints)
            self.frame_numbers = pose.frames
        else:
            self.segments = self.joints = None
            self.frame_numbers = int(traj.meta.get("frame_offset", 0)) + np.arange(F)
        self.limits = self._limits()
        self.centres = None
        if follow and self.image_size is None:
            self.centres, self.limits = self._follow()

    @staticmethod
    def _check(a: Any, traj: Trajectories, name: str) -> np.ndarray:
        a = np.asarray(a, float)
        if a.shape != traj.shape:
            raise ValueError(f"{name} must have the shape of the trajectories {traj.shape}, got {a.shape}")
        return a

    def _flat(self, X: np.ndarray) -> np.ndarray:
        return X if self.projector is None else X @ self.projector

    def _limits(self) -> tuple[float, float, float, float]:
        if self.image_size is not None:
            w, h = self.image_size
            return 0.0, float(w), float(h), 0.0
        stacks = [self.xy.reshape(-1, 2)]
        if self.segments is not None:
            stacks += [self.segments.reshape(-1, 2), self.joints.reshape(-1, 2)]
        if self.imputed is not None:
            stacks.append(self.imputed.reshape(-1, 2))
        pts = np.concatenate(stacks)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if not pts.size:
            return -1.0, 1.0, -1.0, 1.0
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = 0.06 * max(float((hi - lo).max()), 1e-9)
        return lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad

    def _follow(self) -> tuple[np.ndarray, tuple[float, float, float, float]]:
        """Per-frame centres (F, 2) of the figure, and limits around 0 that fit it in every frame."""
        X = self.xy if self.imputed is None else np.where(np.isnan(self.xy), self.imputed, self.xy)
        with np.errstate(invalid="ignore"):
            lo = np.fmin.reduce(X, axis=0)  # (F, 2), NaN only where a frame shows nothing
            hi = np.fmax.reduce(X, axis=0)
        centres = 0.5 * (lo + hi)
        known = np.isfinite(centres).all(axis=1)
        if not known.any():
            return np.zeros((X.shape[1], 2)), self.limits
        f = np.arange(X.shape[1])
        centres = np.column_stack([np.interp(f, f[known], centres[known, k]) for k in range(2)])
        half = np.nanmax(hi[known] - lo[known], axis=0) / 2
        half = half + 0.12 * max(float(half.max()), 1e-9)
        return centres, (-half[0], half[0], -half[1], half[1])

    def _set_limits(self, frame: int) -> None:
        x0, x1, y0, y1 = self.limits
        if self.centres is not None:
            cx, cy = self.centres[frame]
            x0, x1, y0, y1 = x0 + cx, x1 + cx, y0 + cy, y1 + cy
        self.ax.set_xlim(x0, x1)
        self.ax.set_ylim(y0, y1)  # y0 > y1 for image data: y points down

    # -- artists
    def draw(self, ax: Any, frame: int, *, background: Any = None, title: bool | str = True) -> None:
        from matplotlib.collections import LineCollection

        self.ax = ax
        self.bg = None
        if background is not None and self.image_size is not None:
            w, h = self.image_size
            self.bg = ax.imshow(background, extent=(0, w, h, 0), zorder=0, interpolation="bilinear")
        self.gap_lines = LineCollection([], colors=[(0.1, 0.1, 0.1, 0.7)], linewidths=0.8, zorder=2)
        ax.add_collection(self.gap_lines)
        self.sticks = LineCollection([], linewidths=self.line_width, capstyle="round", zorder=3, alpha=0.9)
        ax.add_collection(self.sticks)
        edge = "white" if self.bg is not None else "none"
        self.pts = ax.scatter([], [], s=self.point_size, zorder=4, edgecolors=edge, linewidths=0.4)
        self.holes = ax.scatter([], [], s=self.point_size, zorder=4, facecolors="none", linewidths=1.0)
        self.crosses = ax.scatter([], [], s=self.point_size * 0.8, zorder=5, marker="x", c="black", linewidths=0.9)
        self.joint_art = ax.scatter([], [], s=self.joint_size, zorder=6, facecolors="white",
                                    edgecolors="black", linewidths=1.3)
        self.title = title
        self._set_limits(frame)
        ax.set_aspect("equal", adjustable="box")
        self.update(frame)

    def update(self, frame: int, background: Any = None) -> None:
        f = int(frame)
        if self.centres is not None:
            self._set_limits(f)
        if background is not None and self.bg is not None:
            self.bg.set_data(background)
        obs = self.obs[:, f]
        xy = self.xy[:, f]
        self.pts.set_offsets(xy[obs] if obs.any() else np.zeros((0, 2)))
        self.pts.set_facecolors(self.point_colors[obs])
        miss = ~obs
        if self.imputed is not None:
            ok = miss & np.isfinite(self.imputed[:, f]).all(axis=1)
            self.holes.set_offsets(self.imputed[ok, f] if ok.any() else np.zeros((0, 2)))
            self.holes.set_edgecolors(self.point_colors[ok])
        if self.truth is not None:
            ok = miss & np.isfinite(self.truth[:, f]).all(axis=1)
            self.crosses.set_offsets(self.truth[ok, f] if ok.any() else np.zeros((0, 2)))
            if self.imputed is not None:
                both = ok & np.isfinite(self.imputed[:, f]).all(axis=1)
                self.gap_lines.set_segments(np.stack([self.truth[both, f], self.imputed[both, f]], axis=1))
        if self.segments is not None:
            seg = self.segments[:, :, f]  # (K, 2, 2)
            ok = np.isfinite(seg).all(axis=(1, 2))
            self.sticks.set_segments(seg[ok])
            self.sticks.set_color(self.seg_colors[ok])
            J = self.joints[:, f]
            okj = np.isfinite(J).all(axis=1)
            self.joint_art.set_offsets(J[okj] if okj.any() else np.zeros((0, 2)))
        if self.title:
            text = self.title if isinstance(self.title, str) else f"frame {int(self.frame_numbers[f])}"
            self.ax.set_title(text, fontsize=9)


def draw_frame(ax: Any, traj: Trajectories | np.ndarray, skeleton: Skeleton | None = None, frame: int = 0, *,
               imputed: Any = None, truth: Any = None, pose: Any = None, background: Any = None,
               view: Any = None, title: bool | str = True, point_size: float = 18.0,
               line_width: float = 3.0, joint_size: float = 45.0, follow: bool = False) -> Any:
    """Draw one frame: points coloured by stick, sticks as lines, joints as circles.

    Parameters
    ----------
    ax : matplotlib Axes
    traj : Trajectories or ndarray, shape (P, F, D)
    skeleton : Skeleton, optional
        Without it the points are coloured by ``traj.labels_true`` (when known)
        and no sticks are drawn.
    frame : int
        Index into the frames of ``traj``.
    imputed : ndarray (P, F, D) or True, optional
        Positions for the missing points, drawn as hollow markers; ``True``
        uses the skeleton's predictions.
    truth : ndarray (P, F, D), optional
        True positions of the missing points (e.g. before occlusion), drawn as
        crosses joined to their imputed positions.
    pose : Pose, optional
        A precomputed :func:`stickfigure.export.pose` of ``skeleton`` on ``traj``.
    background : ndarray (H, W, 3), optional
        An image drawn under image data (e.g. the video frame).
    view : "isometric", (azimuth, elevation), ...; optional
        How 3D data are seen (default: their first two coordinates).
    title : bool or str
        ``True`` writes the frame number.
    point_size, line_width, joint_size : float
    follow : bool
        Centre the view on the figure in each frame (same scale in every frame),
        for figures that travel far; image data always show the whole image.

    Returns
    -------
    matplotlib Axes
    """
    scene = _Scene(traj, skeleton, imputed=imputed, truth=truth, pose=pose, view=view,
                   point_size=point_size, line_width=line_width, joint_size=joint_size, follow=follow)
    F = scene.traj.n_frames
    if not -F <= int(frame) < F:
        raise ValueError(f"frame {frame} is out of range: the data have {F} frames")
    scene.draw(ax, int(frame) % F, background=background, title=title)
    return ax


def _grid(n: int, ncols: int | None) -> tuple[int, int]:
    ncols = ncols or min(n, 4)
    return math.ceil(n / ncols), ncols


def plot_frames(traj: Trajectories | np.ndarray, skeleton: Skeleton | None = None, frames: Any = None,
                path: str | os.PathLike | None = None, *, n: int = 6, ncols: int | None = None,
                panel_size: float = 3.0, dpi: int = 100, video: Any = None, **draw_kw: Any) -> Any:
    """A grid of frames with the skeleton drawn over them.

    Parameters
    ----------
    traj : Trajectories or ndarray, shape (P, F, D)
    skeleton : Skeleton, optional
    frames : int, slice, sequence of int or "a:b[:k]", optional
        Frame indices into ``traj``; default ``n`` evenly spaced frames.
    path : path-like, optional
        Write the figure there (PNG, PDF, SVG: by extension).
    n : int
        Number of frames when ``frames`` is not given.
    ncols : int, optional
        Panels per row (default up to 4).
    panel_size : float
        Panel size in inches.
    dpi : int
    video : path, False or None
        Video to draw under image data; default ``traj.video`` when that file
        exists, ``False`` for none.
    **draw_kw
        Passed to :func:`draw_frame` (``imputed``, ``truth``, ``view``, ...).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    scene = _Scene(traj, skeleton, **draw_kw)
    idx = select_frames(frames, scene.traj.n_frames, default_count=int(n))
    rows, cols = _grid(idx.size, ncols)
    x0, x1, y0, y1 = scene.limits
    aspect = abs(y1 - y0) / max(abs(x1 - x0), 1e-12)
    fig = Figure(figsize=(panel_size * cols, panel_size * rows * min(max(aspect, 0.3), 3.0) + 0.3), dpi=dpi)
    reader = _open_video(scene.traj, video)
    try:
        for k, f in enumerate(idx):
            ax = fig.add_subplot(rows, cols, k + 1)
            bg = reader.frame(int(scene.frame_numbers[f])) if reader is not None else None
            scene.draw(ax, int(f), background=bg)
            ax.tick_params(labelsize=7)
    finally:
        if reader is not None:
            reader.close()
    fig.tight_layout()
    if path is not None:
        _save_figure(fig, path)
    return fig


def _save_figure(fig: Any, path: str | os.PathLike) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or "png")
    return path


# ------------------------------------------------------------------- video
class _VideoReader:
    """Sequential reader of a video's frames (OpenCV), seeking only when it must."""

    def __init__(self, path: str | os.PathLike):
        import cv2

        self.cv2 = cv2
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise ValueError(f"cannot open the video {path}")
        self.next = 0

    def frame(self, k: int) -> np.ndarray | None:
        """RGB frame number ``k`` (None past the end)."""
        cv2 = self.cv2
        if k < self.next or k - self.next > 60:
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, k)
            self.next = k
        while self.next < k:
            if not self.cap.grab():
                return None
            self.next += 1
        ok, img = self.cap.read()
        if not ok:
            return None
        self.next += 1
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self.cap.release()


def _open_video(traj: Trajectories, video: Any) -> _VideoReader | None:
    if video is False or traj.image_size is None:
        return None
    path = video if video not in (None, True) else traj.video
    if path is None:
        return None
    if not Path(path).is_file():
        if video not in (None, True):
            raise FileNotFoundError(f"no such video: {path}")
        return None  # the tracks remember a video that has moved: draw without it
    return _VideoReader(path)


def animate(traj: Trajectories | np.ndarray, skeleton: Skeleton | None, path: str | os.PathLike,
            fps: float | None = None, frames: Any = None, *, max_frames: int = 300, width: int = 480,
            dpi: int = 100, video: Any = None, progress: bool = False, **draw_kw: Any) -> Path:
    """Write an animation of the skeleton over the frames, as GIF or MP4 (by extension).

    Frames are rendered one at a time and streamed to the file (MP4 through
    imageio-ffmpeg; GIF through Pillow, which keeps each frame palettised, one
    byte per pixel), so long clips need little memory; ``max_frames`` bounds
    the length by keeping every k-th frame, and the frame rate is divided by
    k so the clip still plays in real time.

    Parameters
    ----------
    traj : Trajectories or ndarray, shape (P, F, D)
    skeleton : Skeleton or None
    path : path-like
        ``.gif`` or ``.mp4`` (written atomically).
    fps : float, optional
        Playback rate; default ``traj.frame_rate``, else 15.
    frames : int, slice, sequence of int or "a:b[:k]", optional
        Frames to show (indices into ``traj``); default all.
    max_frames : int
        Most frames written.
    width : int
        Width of the animation in pixels (the height follows the data's aspect).
    dpi : int
    video : path, False or None
        Video under image data; default ``traj.video`` when that file exists
        (frame ``f`` of ``traj`` is video frame ``f + meta["frame_offset"]``).
    progress : bool
        Show a progress bar.
    **draw_kw
        Passed to :func:`draw_frame`.

    Returns
    -------
    Path
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    kind = path.suffix.lower()
    if kind not in (".gif", ".mp4"):
        raise ValueError(f"animation path must end in .gif or .mp4, got {path.name!r}")
    max_frames = int(max_frames)
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    scene = _Scene(traj, skeleton, **draw_kw)
    idx = select_frames(frames, scene.traj.n_frames)
    step = max(1, math.ceil(idx.size / max_frames))
    idx = idx[::step]
    if fps is None:
        fps = scene.traj.frame_rate or 15.0
    fps = float(fps) / step
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    x0, x1, y0, y1 = scene.limits
    aspect = abs(y1 - y0) / max(abs(x1 - x0), 1e-12)
    W = max(16 * round(int(width) / 16), 64)
    H = max(16 * round(W * min(max(aspect, 0.25), 4.0) / 16), 64)  # multiples of 16 suit video codecs
    fig = Figure(figsize=(W / dpi, H / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.9))
    ax.set_xticks([])
    ax.set_yticks([])
    reader = _open_video(scene.traj, video)

    def rendered() -> Iterable[np.ndarray]:
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=idx.size, desc="render", unit="frame")
        try:
            for k, f in enumerate(idx):
                bg = reader.frame(int(scene.frame_numbers[f])) if reader is not None else None
                if k == 0:
                    scene.draw(ax, int(f), background=bg)
                    ax.set_xticks([])
                    ax.set_yticks([])
                else:
                    scene.update(int(f), background=bg)
                canvas.draw()
                yield np.asarray(canvas.buffer_rgba())[..., :3].copy()
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()

    try:
        with atomic_path(path) as tmp:
            if kind == ".gif":
                from PIL import Image

                images = (Image.fromarray(a) for a in rendered())
                first = next(images)
                first.save(tmp, format="GIF", save_all=True, append_images=images,
                           duration=max(int(round(1000.0 / fps)), 20), loop=0, optimize=False)
            else:
                import imageio.v2 as imageio

                with imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                        macro_block_size=16, quality=7, pixelformat="yuv420p") as w:
                    for a in rendered():
                        w.append_data(a)
    finally:
        if reader is not None:
            reader.close()
    return path


# -------------------------------------------------------------------- tree
def _tree_layout(skeleton: Skeleton) -> dict[int, tuple[float, float]]:
    """Top-down layout: each tree's root on top, children one level below, leaves spread evenly."""
    parents = skeleton.parents()
    S = skeleton.n_sticks
    kids: dict[int, list[int]] = {s: [] for s in range(S)}
    for s, p in enumerate(parents):
        if p >= 0:
            kids[int(p)].append(s)
    pos: dict[int, tuple[float, float]] = {}
    cursor = [0.0]

    def place(s: int, depth: int) -> float:
        if not kids[s]:
            x = cursor[0]
            cursor[0] += 1.0
        else:
            xs = [place(c, depth + 1) for c in kids[s]]
            x = 0.5 * (min(xs) + max(xs))
        pos[s] = (x, -float(depth))
        return x

    for r in [s for s in range(S) if parents[s] < 0]:
        place(r, 0)
        cursor[0] += 0.5  # a gap between the trees of a forest
    return pos


def draw_tree(ax: Any, skeleton: Skeleton, *, names: list[str] | None = None, node_size: float = 600.0,
              show_sizes: bool = True) -> Any:
    """Draw the stick tree as a graph: one node per stick (coloured as in the frames), one edge per joint.

    The tree hangs from its root (the stick :meth:`Skeleton.parents` roots it
    at) with the children of each stick one level below; a forest is drawn as
    several trees side by side. Drawn with networkx.

    Parameters
    ----------
    ax : matplotlib Axes
    skeleton : Skeleton
    names : list of str, optional
        Node labels (default ``S0``, ``S1``, ...).
    node_size : float
    show_sizes : bool
        Add each stick's number of points to its label.

    Returns
    -------
    matplotlib Axes
    """
    import networkx as nx

    if not isinstance(skeleton, Skeleton):
        raise TypeError(f"skeleton must be a stickfigure Skeleton, got {type(skeleton).__name__}")
    S = skeleton.n_sticks
    if names is not None and len(names) != S:
        raise ValueError(f"names must have one entry per stick ({S}), got {len(names)}")
    g = nx.Graph()
    g.add_nodes_from(range(S))
    g.add_edges_from(skeleton.edges)
    pos = _tree_layout(skeleton)
    sizes = skeleton.stick_sizes()
    labels = {s: (names[s] if names else f"S{s}") + (f"\n{sizes[s]} pts" if show_sizes else "") for s in range(S)}
    colors = stick_colors(S)
    nx.draw_networkx_edges(g, pos, ax=ax, width=2.0, edge_color="0.3")
    nx.draw_networkx_nodes(g, pos, ax=ax, node_color=colors, node_size=node_size, edgecolors="black")
    nx.draw_networkx_labels(g, pos, labels=labels, ax=ax, font_size=8)
    ax.set_axis_off()
    if pos:
        xs = [p[0] for p in pos.values()]
        ys = [p[1] for p in pos.values()]
        ax.set_xlim(min(xs) - 0.7, max(xs) + 0.7)
        ax.set_ylim(min(ys) - 0.6, max(ys) + 0.6)
    return ax
