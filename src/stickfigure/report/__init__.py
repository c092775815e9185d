"""One self-contained HTML page about a learned skeleton.

:func:`write_report` writes a single ``.html`` file that needs nothing else: its
style sheet, script, figures (PNG) and video frames (JPEG) are embedded as text
and data URIs, and a Content-Security-Policy forbids any network request. It
shows

* the skeleton animated over the input: a player (play/pause, frame slider,
  speed, layers) drawing points coloured by stick, sticks, joints and the
  points the model fills in where tracking lost them, over the video frames
  when the input came from a video;
* the learned tree as a graph, a table of sticks (points, parent, length) and
  of joints (position, range of motion, joint angles);
* the method's own diagnostics: figures from its plot module
  (``stickfigure.plot.<method>``) and a readable view of ``skeleton.info``
  (objective per merge stage for ``em``, traces / R-hat / posterior over the
  number of sticks for ``mcmc``, the mutual-information matrix for ``mi-tree``);
* how well it explains the data: reconstruction error, a held-out imputation
  check against linear interpolation, and segmentation/structure scores when
  the input has ground truth.

The page checks itself when it loads: it sets ``data-selfcheck="ok"`` on the
``<html>`` element once every image has decoded and the player has drawn, or
``"fail"`` with the reasons in ``data-errors`` (the browser tests read these).
"""

from __future__ import annotations

import json
import os
import warnings
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .._atomic import atomic_write_text
from ..skeleton import Skeleton
from ..trajectories import Trajectories
from . import _data, _figures
from ._html import esc, figure, fmt, info_view, kpis, section, table

__all__ = ["write_report", "render_report"]


def _asset(name: str) -> str:
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def _source_name(traj: Trajectories) -> str:
    if traj.video:
        return Path(traj.video).name
    for k in ("path", "file", "source_path"):
        if traj.meta.get(k):
            return Path(str(traj.meta[k])).name
    src = traj.meta.get("source")
    return str(src) if src else "trajectories"


def _check_inputs(skeleton: Any, traj: Any) -> Trajectories:
    if not isinstance(skeleton, Skeleton):
        raise TypeError(f"skeleton must be a stickfigure.Skeleton, got {type(skeleton).__name__}")
    if isinstance(traj, np.ndarray):
        traj = Trajectories(traj, allow_unobserved=True)
    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories or an array of shape (P, F, D), got {type(traj).__name__}")
    if traj.n_points != skeleton.n_points:
        raise ValueError(f"traj has {traj.n_points} points but the skeleton was fitted to {skeleton.n_points}; "
                         "pass the trajectories the model was learned from")
    for name in ("joints", "motions"):
        arr = getattr(skeleton, name)
        if arr is not None and arr.shape[1] != traj.n_frames:
            raise ValueError(f"traj has {traj.n_frames} frames but the skeleton's {name} have {arr.shape[1]}; "
                             "pass the trajectories the model was learned from")
    return traj


def _joint_angles(skeleton: Skeleton, traj: Trajectories) -> tuple[np.ndarray | None, str | None]:
    """Per-frame joint angles in degrees, (F, E), from :func:`stickfigure.export.joint_angles`, or why not.

    Signed 2D angles are unwrapped over time, so a joint swinging through
    ±180° shows its real range instead of jumping from one end to the other.
    """
    from ..export import joint_angles

    try:
        angles, _ = joint_angles(skeleton, traj)
    except Exception as exc:
        return None, f"joint angles unavailable: {type(exc).__name__}: {exc}"
    angles = np.asarray(angles, dtype=float).T  # (F, E)
    for e in range(angles.shape[1]):
        ok = np.isfinite(angles[:, e])
        if ok.sum() > 1:
            angles[ok, e] = np.degrees(np.unwrap(np.radians(angles[ok, e])))
            # Put the series' middle in (-180, 180].
            mid = 0.5 * (angles[ok, e].min() + angles[ok, e].max())
            angles[ok, e] -= 360.0 * np.round(mid / 360.0)
    return angles, None


def _overview(skeleton: Skeleton, traj: Trajectories, q: dict[str, Any]) -> str:
    P, F, D = traj.shape
    items: list[tuple[str, Any]] = [("method", skeleton.method), ("sticks", skeleton.n_sticks),
                                    ("joints", len(skeleton.edges)), ("points", P), ("frames", F)]
    if skeleton.log_likelihood is not None:
        items.append(("objective", skeleton.log_likelihood))
    if "impute" in q and q["impute"].get("rmse") is not None:
        items.append((f"imputation RMSE ({'px' if traj.image_size else 'units'})", q["impute"]["rmse"]))
    rows = [("source", _source_name(traj))]
    if traj.video:
        rows.append(("video", traj.video))
    if traj.image_size:
        rows.append(("image size", f"{traj.image_size[0]} × {traj.image_size[1]} px"))
    if traj.frame_rate:
        rows.append(("frame rate", f"{fmt(traj.frame_rate)} fps ({fmt(F / traj.frame_rate)} s shown)"))
    off = int(traj.meta.get("frame_offset", 0))
    rows.append(("frames", f"{off} … {off + F - 1}" + (" of the video" if traj.video else "")))
    rows.append(("missing", f"{100 * traj.missing_fraction:.1f}% of the (point, frame) observations"))
    if "articulation" in q:
        rows.append(("articulation", f"{100 * q['articulation']:.1f}% of the motion departs from one rigid body "
                                     "(the less the figure bends in these frames, the less they tell its parts apart)"))
    if D == 3:
        rows.append(("dimensions", "3D (drawn in an isometric projection)"))
    if "projection" in traj.meta:
        pr = traj.meta["projection"]
        camera = ("orthographic camera" if pr.get("distance") is None
                  else f"pinhole camera {fmt(pr['distance'])} from the scene centre")
        rows.append(("projection", f"3D data seen from azimuth {fmt(pr.get('azimuth'))}°, "
                                   f"elevation {fmt(pr.get('elevation'))}°, {camera}"))
    if "window" in traj.meta:
        w = traj.meta["window"]
        how = ("the shot window with the most independently moving points"
               if w.get("select", "coverage") == "motion" and w.get("verdict") == "independent motion"
               else "the best-covered window")
        see = " (see “What it was learned from”)" if w.get("candidates") else ""
        rows.append(("selection", f"{how}: {w.get('points')} of {w.get('of_points')} tracks, each observed in "
                                  f"≥ {100 * w.get('coverage', 0):.0f}% of its frames{see}"))
    tr = traj.meta.get("tracking")
    if isinstance(tr, dict):
        rows.append(("tracking", f"{tr.get('detected')} features detected, {tr.get('kept')} tracks kept "
                                 f"({tr.get('too_short')} too short, {tr.get('static')} static), "
                                 f"{fmt(tr.get('seconds'))} s"))
    shots = traj.meta.get("shots")
    if isinstance(shots, list) and len(shots) > 1:
        rows.append(("shot cuts", "the video cuts to another shot at frames " + ", ".join(str(s) for s in shots[1:])
                      + "; no track crosses a cut"))
    return kpis(items) + table(["input", ""], rows)


def _sentence(text: Any) -> str:
    text = str(text)
    return text[:1].upper() + text[1:]


def _banner(traj: Trajectories) -> str:
    """A warning at the top of the page when the window holds no articulated motion."""
    w = traj.meta.get("window")
    if not isinstance(w, dict) or w.get("verdict", "independent motion") == "independent motion":
        return ""
    return (f'<div class="banner" role="alert"><strong>Not a figure\'s skeleton?</strong> '
            f'{esc(_sentence(w.get("message", "")))}. Read the skeleton below with that in mind; to learn from another part '
            'of the video, pass <code>--frames A:B</code> and/or <code>--roi X,Y,W,H</code>.</div>')


def _selection(traj: Trajectories) -> str:
    """Why this window: one row per shot's candidate window (see :func:`stickfigure.track.best_window`)."""
    w = traj.meta.get("window")
    if not isinstance(w, dict) or not w.get("candidates"):
        return ""
    rows = []
    for c in w["candidates"]:
        rows.append(["✔" if c.get("chosen") else "", f"{c['first']}–{c['last']}", c["points"],
                     c.get("camera_px") if c.get("camera_px") is not None else "unknown",
                     c["scene_points"], c["independent"],
                     "" if c.get("rigid_share") is None else f"{100 * c['rigid_share']:.0f}%", c["score"]])
    head = ["chosen", "frames", "points", "camera travel (px)", "rigid scene", "moving on their own",
            "one rigid motion explains", "score"]
    tol = w.get("scene_tolerance_px")
    body = (f'<p>{esc(_sentence(w.get("message", "")))}.</p>'
            + table(head, rows, numeric=[False, False, True, True, True, True, True, True])
            + '<p class="note">One candidate per shot: the window whose points, each observed in at least '
            f'{100 * w.get("coverage", 0):.0f}% of its frames, cover it best. Where the camera moved, one rigid '
            'scene (a rank-4 affine motion: a 3D scene under an affine camera, depth parallax included) is fitted '
            f'by RANSAC; the points it explains to within {fmt(tol)} px are the scene, not a figure. Where the '
            'camera was still, the tracker has already removed the static background. The window with the most '
            'points moving on their own (score: their number × √frames) is learned from, with only those '
            'points. “One rigid motion explains” is the share of them one 2D similarity per frame (one body '
            'turning, moving, nearing the camera) explains; '
            'at 80% or more they move as one body and there is nothing for a skeleton to split.</p>')
    return body


def _player(skeleton: Skeleton, traj: Trajectories) -> str:
    colors = _data.stick_colors(skeleton.n_sticks)
    sizes = skeleton.stick_sizes()
    legend = "".join(f'<span><span class="swatch" style="background:{c}"></span>S{s} ({sizes[s]} pts)</span>'
                     for s, c in enumerate(colors))
    if (skeleton.labels < 0).any():
        legend += (f'<span><span class="swatch" style="background:{_data.UNASSIGNED}"></span>'
                   f'unassigned ({int((skeleton.labels < 0).sum())} pts)</span>')
    layers = [("video", "video"), ("points", "points"), ("imputed", "filled-in points"), ("sticks", "sticks"),
              ("joints", "joints"), ("labels", "labels"), ("trails", "trails"), ("zoom", "zoom to the figure")]
    boxes = "".join(f'<label><input type="checkbox" data-layer="{k}"> {esc(t)}</label>' for k, t in layers)
    return f"""
<div class="player" data-player="main">
  <div class="stage"></div>
  <div class="controls">
    <button class="play" type="button">Play</button>
    <button class="prev" type="button" title="previous frame">◀</button>
    <button class="next" type="button" title="next frame">▶</button>
    <input class="seek" type="range" min="0" value="0" aria-label="frame">
    <span class="frame"></span>
    <label>speed <select class="speed"><option value="0.25">¼×</option><option value="0.5">½×</option>
      <option value="1" selected>1×</option><option value="2">2×</option></select></label>
  </div>
  <div class="controls">{boxes}</div>
  <div class="legend">{legend}</div>
</div>
<p class="note">Filled circles are tracked/observed positions, hollow circles the positions the model fills in
where a point is missing; white discs are joints. Click the picture and use space / arrow keys to play and step.</p>"""


def _structure(skeleton: Skeleton, traj: Trajectories, player: dict[str, Any],
               pz: dict[str, np.ndarray]) -> tuple[str, list[str]]:
    notes: list[str] = []
    parts = []
    try:
        parts.append(figure(_figures.to_data_uri(_figures.tree_figure(skeleton)),
                            "The learned tree: one node per stick, one edge per joint."))
    except Exception as exc:
        notes.append(f"tree figure failed: {type(exc).__name__}: {exc}")
    parent = skeleton.parents()
    sizes = skeleton.stick_sizes()
    colors = _data.stick_colors(skeleton.n_sticks)
    names = skeleton.point_names
    # Drawn length of each stick (median over frames of its first segment).
    seg_len = {}
    for seg in player["segments"]:
        s = seg["stick"]
        if s in seg_len:
            continue
        xy = np.array([[np.nan] * 4 if e is None or None in e else e for e in seg["xy"]], float)
        seg_len[s] = float(np.nanmedian(np.hypot(xy[:, 2] - xy[:, 0], xy[:, 3] - xy[:, 1]))) if np.isfinite(xy).any() else None
    obs = traj.observed
    rows = []
    for s in range(skeleton.n_sticks):
        members = np.flatnonzero(skeleton.labels == s)
        shown = [names[p] if names else str(p) for p in members[:12]]
        more = f" … (+{members.size - 12})" if members.size > 12 else ""
        rows.append([f'<span class="swatch" style="background:{colors[s]}"></span>S{s}', int(sizes[s]),
                     f"S{parent[s]}" if parent[s] >= 0 else "root",
                     seg_len.get(s), float(obs[members].mean()) if members.size else None,
                     esc(", ".join(shown) + more)])
    if (skeleton.labels < 0).any():
        un = np.flatnonzero(skeleton.labels < 0)
        rows.append(["unassigned", int(un.size), "", None, float(obs[un].mean()),
                     esc(", ".join(names[p] if names else str(p) for p in un[:12]))])
    unit = "px" if traj.image_size else "units"
    parts.append("<h3>Sticks</h3>" + table(["stick", "points", "parent", f"length ({unit})", "observed", "points on it"],
                                           rows, numeric=[False, True, False, True, True, False],
                                           raw=[True, False, False, False, False, True], cls="sticks"))
    # Joints.
    if skeleton.edges:
        angles, why = _joint_angles(skeleton, traj)
        rows = []
        for k in range(len(skeleton.edges)):
            row: list[Any] = [f"S{pz['parent_stick'][k]} – S{pz['child_stick'][k]}"]
            j = pz["joints"][k]
            ok = np.isfinite(j).all(axis=1)
            if ok.any():
                m, sd = j[ok].mean(axis=0), j[ok].std(axis=0)
                row += [f"({fmt(m[0])}, {fmt(m[1])})", f"({fmt(sd[0])}, {fmt(sd[1])})"]
            else:
                row += [None, None]
            if angles is not None:
                a_k = angles[:, k]
                ok = np.isfinite(a_k)
                row += [float(np.min(a_k[ok])) if ok.any() else None, float(np.max(a_k[ok])) if ok.any() else None,
                        float(np.mean(a_k[ok])) if ok.any() else None]
            rows.append(row)
        head = ["joint (parent – child)", f"mean position ({unit})", f"spread (std, {unit})"]
        if angles is not None:
            head += ["angle min (°)", "angle max (°)", "angle mean (°)"]
        parts.append("<h3>Joints</h3>" + table(head, rows, numeric=[False, False, False] + [True] * (len(head) - 3)))
        if skeleton.joints is None:
            parts.append(f'<p class="note">The {esc(skeleton.method)} method gives the tree but no joint positions.</p>')
        if angles is not None:
            fnum = np.arange(angles.shape[0]) + int(traj.meta.get("frame_offset", 0))
            try:
                names = [f"S{a}–S{b}" for a, b in zip(pz["parent_stick"], pz["child_stick"])]
                fig = _figures.joint_angle_figure(angles, names, fnum, traj.frame_rate)
                parts.append(figure(_figures.to_data_uri(fig), "Joint angles over time."))
            except Exception as exc:
                notes.append(f"joint-angle figure failed: {type(exc).__name__}: {exc}")
        elif why:
            parts.append(f'<p class="note">{esc(why)}.</p>')
    else:
        parts.append('<p class="note">No joints: the sticks move independently (a forest of single sticks).</p>')
    return "".join(parts), notes


def _diagnostics(skeleton: Skeleton, traj: Trajectories) -> str:
    figs, notes = _figures.method_figures(skeleton, traj)
    parts = [figure(uri, cap) for cap, uri in figs]
    parts += [f'<p class="note">{esc(n)}</p>' for n in notes]
    if skeleton.info:
        view = info_view(skeleton.info)
        if figs:
            parts.append(f"<details><summary>all of the method's diagnostics (skeleton.info)</summary>{view}</details>")
        else:
            parts.append(view)
    elif not figs:
        parts.append('<p class="note">The method recorded no diagnostics.</p>')
    if skeleton.log_likelihood is not None:
        parts.append(f'<p>Objective at the returned solution: <b>{esc(fmt(skeleton.log_likelihood))}</b></p>')
    return "".join(parts)


def _quality(q: dict[str, Any]) -> str:
    unit = "px" if q.get("units") == "pixels" else "data units"
    rows = []
    if "fit_rmse" in q:
        rows.append(("reconstruction RMSE of the observed positions", q["fit_rmse"], unit))
    imp = q.get("impute")
    if imp:
        rows.append((f"imputation RMSE, {100 * imp['hidden_fraction']:.0f}% of observations hidden "
                     f"({imp['n_hidden']} entries)", imp["rmse"], unit))
        rows.append(("the same entries by linear interpolation in time (baseline)", imp["interp_rmse"], unit))
        if imp.get("filled_fraction", 1.0) < 1:
            rows.append(("share of hidden entries the model could fill", imp["filled_fraction"], ""))
    hid = q.get("hidden")
    if hid:
        rows.append((f"error on the {hid['n_hidden']} entries missing from the input (true positions given)",
                     hid["rmse"], unit))
        rows.append(("the same entries by linear interpolation in time (baseline)", hid["interp_rmse"], unit))
        if hid.get("filled_fraction", 1.0) < 1:
            rows.append(("share of them the model could fill", hid["filled_fraction"], ""))
    tr = q.get("truth")
    if tr:
        for key, label in (("ari", "adjusted Rand index against the true parts"),
                           ("misclassification", "misclassification rate (best matching of sticks to parts)"),
                           ("edge_precision", "tree vs true tree: edge precision"),
                           ("edge_recall", "tree vs true tree: edge recall"),
                           ("edge_f1", "tree vs true tree: edge F1"),
                           ("exact", "exact structure (sticks one-to-one with parts, same tree)"),
                           ("joint_error", "mean distance of learned joints from the true ones")):
            if key in tr:
                rows.append((label, tr[key], unit if key == "joint_error" else ""))
    body = table(["measure", "value", ""], rows, numeric=[False, True, False]) if rows else ""
    for k in ("fit_rmse_error", "impute_error", "hidden_error", "articulation_error"):
        if k in q:
            body += f'<p class="warn">{esc(k.split("_")[0])}: {esc(q[k])}</p>'
    if tr and "error" in tr:
        body += f'<p class="warn">scores against the truth: {esc(tr["error"])}</p>'
    if imp:
        better = imp["rmse"] is not None and imp["rmse"] < imp["interp_rmse"]
        body += ('<p class="note">Hidden entries are chosen at random (seeded) among the observed ones; the model keeps '
                 'its structure and re-fits the motions to the remaining entries. '
                 + ("It beats interpolation." if better else "It does not beat interpolation here.") + "</p>")
    return body or '<p class="note">No quality measure applies to this model and data.</p>'


def _params(skeleton: Skeleton, traj: Trajectories) -> str:
    import stickfigure

    rows = [(k, json.dumps(v, default=str) if not isinstance(v, (int, float, str)) or isinstance(v, bool) else v)
            for k, v in sorted(skeleton.params.items())]
    out = table(["parameter", "value"], rows) if rows else '<p class="note">No parameters recorded.</p>'
    tk = traj.meta.get("tracker")
    if isinstance(tk, dict):
        out += "<h3>Tracker settings</h3>" + table(["setting", "value"], sorted(tk.items()))
    out += f'<p class="note">stickfigure {esc(stickfigure.__version__)}</p>'
    return out


def render_report(skeleton: Skeleton, traj: Trajectories | np.ndarray, *, title: str | None = None,
                  max_frames: int = 150, impute_check: bool = True, truth: Any = None) -> str:
    """The report's HTML as a string (see :func:`write_report`)."""
    import matplotlib

    import stickfigure

    traj = _check_inputs(skeleton, traj)
    if title is None:
        title = f"{skeleton.method} skeleton of {_source_name(traj)}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with matplotlib.rc_context({"figure.max_open_warning": 0}):
            q = _data.quality(skeleton, traj, hide=0.1 if impute_check else 0, truth=truth)
            pz = _data.flat_pose(skeleton, traj)
            player = _data.player_data(skeleton, traj, max_frames=max_frames, pose=pz)
            structure, notes = _structure(skeleton, traj, player, pz)
            sections = [
                ("overview", "Overview", _banner(traj) + _overview(skeleton, traj, q)),
                ("animation", "The skeleton over the input", _player(skeleton, traj)
                 + ("" if player.get("backgrounds") or not traj.video else
                    f'<p class="warn">The video {esc(traj.video)} could not be read; the points are drawn alone.</p>')),
                *([("selection", "What it was learned from", _selection(traj))] if _selection(traj) else []),
                ("structure", "Structure", structure + "".join(f'<p class="warn">{esc(n)}</p>' for n in notes)),
                ("diagnostics", f"How {skeleton.method} got there", _diagnostics(skeleton, traj)),
                ("quality", "How well it fits", _quality(q)),
                ("parameters", "Parameters", _params(skeleton, traj)),
            ]
    body = "\n".join(section(a, t, b) for a, t, b in sections)
    toc = "".join(f'<a href="#{a}">{esc(t)}</a>' for a, t, _ in sections)
    subtitle = (f"{skeleton.n_sticks} sticks, {len(skeleton.edges)} joints from {traj.n_points} points over "
                f"{traj.n_frames} frames")
    data = json.dumps({"players": {"main": player}}, separators=(",", ":"), allow_nan=False)
    data = data.replace("</", "<\\/")  # never close the <script> early
    page = _asset("template.html")
    for key, value in (("css", _asset("report.css")), ("js", _asset("player.js")), ("title", esc(title)),
                       ("subtitle", esc(subtitle)), ("toc", toc), ("version", esc(stickfigure.__version__)),
                       ("body", body)):
        page = page.replace("{{" + key + "}}", value)
    return page.replace("{{data}}", data)


def write_report(skeleton: Skeleton, traj: Trajectories | np.ndarray, path: str | os.PathLike, *,
                 title: str | None = None, max_frames: int = 150, impute_check: bool = True,
                 truth: Any = None) -> Path:
    """Write the skeleton's report as one self-contained HTML file.

    Parameters
    ----------
    skeleton : Skeleton
        A fitted model.
    traj : Trajectories or ndarray, shape (P, F, D)
        The data it was learned from (same points and frames). When it
        remembers a video (``traj.video``, ``meta["frame_offset"]``), the
        player draws over the video's frames.
    path : str or path-like
        Output file (``.html``); written atomically.
    title : str, optional
        Page title (default: method and input name).
    max_frames : int
        Most frames in the player (evenly spaced), which bounds the file size.
    impute_check : bool
        Run the held-out imputation check (hides 10% of the observations and
        asks the model to fill them).
    truth : Trajectories or ndarray, shape (P, F, D), optional
        True positions of the entries missing from ``traj`` (e.g. the data
        before :func:`stickfigure.synthetic.occlude`): the report scores the
        model's fill-in on them.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ValueError
        ``traj`` does not match the skeleton (points or frames).
    """
    path = Path(path)
    if path.exists() and path.is_dir():
        raise ValueError(f"report path is a directory: {path}")
    html = render_report(skeleton, traj, title=title, max_frames=max_frames, impute_check=impute_check,
                         truth=truth)
    atomic_write_text(path, html)
    return path
