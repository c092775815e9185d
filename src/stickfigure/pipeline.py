"""From a video, a tracks file or motion capture to a skeleton, a video of it and a report: :func:`learn`.

What :func:`learn` does, step by step
-------------------------------------
1. **Input.** A video (by file suffix, see :data:`stickfigure.track.VIDEO_SUFFIXES`)
   is tracked with :func:`stickfigure.track.track_video` and the tracks are
   written to ``tracks.npz``. Anything else is read with
   :func:`stickfigure.load` (tracks, C3D/BVH/ASF+AMC motion capture, Hopkins,
   SLEAP, CSV/NPZ); a :class:`~stickfigure.Trajectories` is used as it is.
   3D data are projected to 2D (``project``, default the isometric view of
   Ross et al.); ``project=None`` keeps them 3D for methods that accept 3D.
2. **Frames.** ``frames=(start, stop)`` restricts the input (for a video it
   is the tracked range, so only those frames are decoded).
3. **What to learn from.** Skeleton methods need points observed over most
   of the frames they are fitted to, while tracks from a video start and end
   all the time. For tracked input (and any input with more than
   ``max_missing`` of its entries missing) :func:`stickfigure.track.best_window`
   keeps, of each shot's best-covered window (points observed in at least
   80% of it, windows of at most 400 frames), the one with the most points
   moving on their own: where the camera moved, points that one rigid scene
   explains (depth parallax included) are set aside. At most ``max_points``
   points are kept, spread over the image. When no window has independent
   motion the best-covered window is used; then, and when the moving points
   move as one rigid body, a ``UserWarning`` says so (the report repeats it).
   Other input is used whole (points never observed are dropped).
   What was fitted is written to ``points.npz`` (the model's input: same
   points and frames, so ``stickfigure report model.json points.npz`` works).
4. **Fit** with :func:`stickfigure.fit` (``method``, ``random_state``,
   ``**params``), write ``model.json`` + ``model.npz``.
5. **Animation** of the skeleton over the video (or over the points) to
   ``skeleton.mp4`` (or ``.gif``), and **report.html**
   (:func:`stickfigure.report.write_report`).
"""

from __future__ import annotations

import inspect
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any


from .trajectories import Trajectories

__all__ = ["learn"]


def _say(progress: bool, msg: str) -> None:
    if progress:
        print(f"[stickfigure] {msg}", file=sys.stderr, flush=True)


def _frame_range(frames: Any) -> tuple[int, int | None]:
    if frames is None:
        return 0, None
    if isinstance(frames, slice):
        if frames.step not in (None, 1):
            raise ValueError(f"frames must be a contiguous range, got step {frames.step}")
        return int(frames.start or 0), (None if frames.stop is None else int(frames.stop))
    try:
        start, stop = frames
    except (TypeError, ValueError):
        raise ValueError(f"frames must be (start, stop) or a slice, got {frames!r}") from None
    start = int(start or 0)
    stop = None if stop is None else int(stop)
    if start < 0 or (stop is not None and stop <= start + 1):
        raise ValueError(f"frames must be (start, stop) with 0 <= start and stop >= start + 2, got {frames!r}")
    return start, stop


def _accepts(fn: Any, name: str) -> bool:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return False
    return name in sig.parameters or any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())


def learn(
    source: str | os.PathLike | Trajectories,
    outdir: str | os.PathLike,
    *,
    method: str = "em",
    progress: bool = False,
    frames: Any = None,
    project: str | tuple[float, float] | None = "isometric",
    camera_distance: float | None = None,
    random_state: Any = 0,
    track_options: dict[str, Any] | None = None,
    max_points: int | None = 150,
    max_missing: float = 0.3,
    animation: str = "mp4",
    title: str | None = None,
    **params: Any,
) -> dict[str, Path]:
    """Learn a skeleton from a video, a tracks file or motion capture, and write everything a user looks at.

    Parameters
    ----------
    source : path or Trajectories
        A video file, any file :func:`stickfigure.load` reads, or trajectories.
    outdir : path
        Folder for the outputs (created if needed).
    method : str
        A registered method (see :func:`stickfigure.available_methods`).
    progress : bool
        Progress bars and one line per step on stderr.
    frames : (start, stop) or slice, optional
        Frame range of the input to use.
    project : "isometric", "front", "side", "top", (azimuth, elevation) or None
        View for projecting 3D input to 2D; None keeps 3D.
    camera_distance : float, optional
        3D input: project through a pinhole camera this far from the scene centre, in
        the data's units (:meth:`Trajectories.project`); None projects orthographically.
    random_state : None, int or Generator
        Seed of the method (the default 0 makes runs repeatable).
    track_options : dict, optional
        Extra keyword arguments of :func:`stickfigure.track.track_video`
        (e.g. ``roi``, ``max_points``, ``min_length``).
    max_points : int, optional
        Most points kept for fitting when a window is selected.
    max_missing : float
        Non-tracked input with more missing entries than this also goes
        through the window selection.
    animation : {"mp4", "gif"}
        Format of the skeleton video.
    title : str, optional
        Report title.
    **params
        Parameters of the method's estimator.

    Returns
    -------
    dict of str to Path
        ``tracks`` (videos only), ``points``, ``model``, ``model_arrays``,
        ``animation``, ``report``.

    Raises
    ------
    ValueError
        Unknown method, unreadable input, bad frame range, or nothing left to
        fit after the selection.
    """
    import stickfigure as sf

    from .models import get_method
    from .plot import animate
    from .report import write_report
    from .track import VIDEO_SUFFIXES, best_window, track_video

    cls = get_method(method)  # an unknown method fails before any tracking
    if animation not in ("mp4", "gif"):
        raise ValueError(f"animation must be 'mp4' or 'gif', got {animation!r}")
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise ValueError(f"outdir exists and is not a folder: {outdir}")
    # The folder is made once the input has been read, so a bad input leaves nothing behind.
    start, stop = _frame_range(frames)
    out: dict[str, Path] = {}
    t0 = time.perf_counter()

    tracked = False
    if isinstance(source, Trajectories):
        traj = source
        if frames is not None:
            traj = traj.slice(frames=slice(start, stop))
    else:
        src = Path(source)
        if src.suffix.lower() in VIDEO_SUFFIXES:
            _say(progress, f"tracking {src.name}")
            traj = track_video(src, start=start, stop=stop, progress=progress, **(track_options or {}))
            tr = traj.meta["tracking"]
            _say(progress, f"{tr['kept']} tracks over {traj.n_frames} frames "
                           f"({100 * traj.missing_fraction:.0f}% missing) in {tr['seconds']:.1f} s")
            outdir.mkdir(parents=True, exist_ok=True)
            out["tracks"] = Path(sf.save(traj, outdir / "tracks.npz") or outdir / "tracks.npz")
            tracked = True
        else:
            if not src.exists():
                raise ValueError(f"input not found: {src}")
            traj = sf.load(src)
            if frames is not None:
                traj = traj.slice(frames=slice(start, stop))
        traj.meta.setdefault("path", str(src))
    tracked = tracked or "tracker" in traj.meta

    if traj.n_dims == 3 and project is not None:
        traj = traj.project(project, distance=camera_distance)
        camera = "orthographic" if camera_distance is None else f"pinhole camera at {camera_distance:g}"
        _say(progress, f"projected 3D input to 2D ({project} view, {camera})")
    traj = traj.drop_unobserved()
    if tracked or traj.missing_fraction > max_missing:
        traj = best_window(traj, max_points=max_points, max_frames=400 if tracked else None)
        w = traj.meta["window"]
        off = traj.meta.get("frame_offset", 0)
        _say(progress, f"learning from {w['points']} of {w['of_points']} points over frames "
                       f"{off}-{off + traj.n_frames - 1}")
        for c in w.get("candidates", []) if len(w.get("candidates", [])) > 1 else []:
            _say(progress, f"  frames {c['first']}-{c['last']}: {c['points']} points, {c['independent']} moving "
                           f"independently of the scene/background{'  <- chosen' if c['chosen'] else ''}")
        if w.get("verdict", "independent motion") != "independent motion":
            # Said whether or not progress is shown: the skeleton is not a figure's.
            warnings.warn(w["message"], UserWarning, stacklevel=2)
        else:
            _say(progress, w["message"])
    outdir.mkdir(parents=True, exist_ok=True)
    out["points"] = Path(sf.save(traj, outdir / "points.npz") or outdir / "points.npz")

    _say(progress, f"fitting {method} to {traj.n_points} points x {traj.n_frames} frames")
    fit_params = dict(params)
    if _accepts(cls.__init__, "progress") and "progress" not in fit_params:
        fit_params["progress"] = progress
    t1 = time.perf_counter()
    skeleton = sf.fit(traj, method=method, random_state=random_state, **fit_params)
    _say(progress, f"{skeleton.n_sticks} sticks, {len(skeleton.edges)} joints in {time.perf_counter() - t1:.1f} s")
    out["model"] = skeleton.save(outdir / "model.json")
    out["model_arrays"] = out["model"].with_suffix(".npz")

    _say(progress, "drawing the animation")
    # Over the video at its own size (at most 960 px wide); missing points where the model puts them.
    width = min(int(traj.image_size[0]), 960) if traj.image_size else 640
    view = "isometric" if traj.n_dims == 3 else None
    # Points without an image (motion capture) are followed, so a figure walking away stays in view.
    follow = {"follow": True} if traj.image_size is None and _accepts(animate, "follow") else {}
    out["animation"] = animate(traj, skeleton, outdir / f"skeleton.{animation}", width=width, view=view,
                               imputed=True, progress=progress, **follow)
    _say(progress, "writing the report")
    out["report"] = write_report(skeleton, traj, outdir / "report.html", title=title)
    _say(progress, f"done in {time.perf_counter() - t0:.1f} s: {outdir}")
    return out
