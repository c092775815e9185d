"""The ``stickfigure`` command: learn, use and look at skeletons from the shell.

Every subcommand is a thin layer over the library: it parses its options,
calls one or two library functions and prints where the results went. Bad
input (a missing file, an unknown method, a malformed option, data that do not
match a model) ends with exit status 2 and one line ``stickfigure: error: ...``
on stderr; ``--debug`` shows the full traceback instead. See ``docs/cli.md``.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

__all__ = ["main", "build_parser"]

EPILOG = """\
examples:
  stickfigure demo -o demo/                        the whole pipeline on a built-in figure
  stickfigure methods                              what methods there are
  stickfigure fit walk.c3d --project isometric --method em -o walk.json
  stickfigure render walk.json walk.c3d --project isometric -o walk.gif
  stickfigure impute walk.json occluded.csv -o filled.csv
  stickfigure evaluate walk.json walk.c3d --project isometric
  stickfigure export-angles walk.json -o angles.csv
  stickfigure export-bvh walk.json -o walk.bvh
  stickfigure track clip.mp4 -o tracks.npz
  stickfigure learn clip.mp4 --method em -o clip-out/
  stickfigure report walk.json walk.c3d --project isometric -o walk.html

Run 'stickfigure COMMAND --help' for the options of a command.
"""

INPUT_HELP = ("trajectories: any file stickfigure.load reads (.c3d, .bvh, .amc, Hopkins .mat, .slp, .csv, .npz)")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``stickfigure: error: ...`` and exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sub = self.prog.split(" ", 1)[1] if " " in self.prog else ""
        hint = f" (see 'stickfigure {sub} --help')" if sub else " (see 'stickfigure --help')"
        self.exit(2, f"stickfigure: error: {message}{hint}\n")


# ------------------------------------------------------------- option values
def _value(text: str) -> Any:
    """A command-line value: JSON or a Python literal (numbers, true/false, lists), else the string."""
    for parse in (json.loads, ast.literal_eval):
        try:
            return parse(text)
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            pass
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    return text


def _key_values(items: Sequence[str] | None, what: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, val = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key.isidentifier():
            raise ValueError(f"{what} must look like name=value, got {item!r}")
        out[key] = _value(val.strip())
    return out


def _view(text: str | None) -> Any:
    if text is None:
        return None
    if "," in text:
        try:
            az, el = (float(v) for v in text.split(","))
        except ValueError:
            raise ValueError(f"--project must be a view name or AZIMUTH,ELEVATION in degrees, got {text!r}") from None
        return (az, el)
    return text


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


# ---------------------------------------------------------------- arguments
def _add_input_options(p: argparse.ArgumentParser, *, frames: bool = True) -> None:
    g = p.add_argument_group("reading the input")
    if frames:
        g.add_argument("--frames", metavar="A:B[:K]",
                       help="use only these frames of the input (Python slice, e.g. 0:300 or 100:)")
    g.add_argument("--subsample", type=_positive_int, metavar="K", help="keep every K-th frame (e.g. 120 Hz -> 30 Hz)")
    g.add_argument("--project", metavar="VIEW",
                   help="project 3D data to 2D: isometric (the Ross et al. view), front, side, top, "
                        "or AZIMUTH,ELEVATION in degrees")
    g.add_argument("--camera-distance", type=_positive_float, metavar="D",
                   help="with --project: a pinhole camera D from the scene centre, in the data's units "
                        "(default: orthographic)")
    g.add_argument("--drop-unobserved", action="store_true", help="drop points never observed in the frames used")
    g.add_argument("--load-option", action="append", metavar="NAME=VALUE", dest="load_options",
                   help="option for the file reader, repeatable (e.g. markers_per_bone=3 for BVH)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``stickfigure`` command."""
    from . import __version__

    parser = _Parser(
        prog="stickfigure",
        description="Learn articulated skeletons (stick figures) from the motion of tracked points: which points "
                    "move together (sticks), how the sticks are joined (a tree) and where the joints are.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"stickfigure {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars or progress messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")

    def cmd(name: str, help: str, description: str, examples: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help, description=description, epilog="examples:\n" + examples,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show full tracebacks on errors")
        p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="no progress bars or progress messages")
        return p

    p = cmd("demo", "run the whole pipeline on a built-in figure",
            "Make a synthetic articulated figure (a random tree of 5 sticks, or a walker) with some points hidden, learn its skeleton with the main "
            "method, and write the input, the model, a picture, an animation and a summary with scores against "
            "the known truth.",
            "  stickfigure demo\n  stickfigure demo -o demo/ --figure walker --seed 3\n")
    p.add_argument("-o", "--output", default="stickfigure-demo", metavar="DIR",
                   help="output folder (default: stickfigure-demo)")
    p.add_argument("--method", help="method to fit (default: em)")
    p.add_argument("--seed", type=int, default=0, help="seed of the figure and the method (default 0)")
    p.add_argument("--figure", choices=("walker", "random"), default=None,
                   help="the built-in figure: a random 3D tree of 5 sticks (default) or a walking person "
                        "(11 sticks; harder)")
    p.add_argument("--n-frames", type=_positive_int, default=None, help="number of frames")
    p.add_argument("--no-occlusion", action="store_true", help="do not hide any observations")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", help="method parameter, repeatable")
    p.set_defaults(run=_cmd_demo)

    p = cmd("methods", "list the skeleton-learning methods",
            "List the registered methods with a one-line description each.", "  stickfigure methods\n")
    p.set_defaults(run=_cmd_methods)

    p = cmd("fit", "learn a skeleton from trajectories",
            "Learn a skeleton from point trajectories and save it as MODEL.json + MODEL.npz.",
            "  stickfigure fit tracks.npz --method em -o model.json\n"
            "  stickfigure fit walk.c3d --project isometric --subsample 4 --method em -o walk.json\n"
            "  stickfigure fit arm.csv --method mcmc --param n_chains=2 --seed 1 -o arm.json\n")
    p.add_argument("input", metavar="INPUT", help=INPUT_HELP)
    p.add_argument("-m", "--method", default="em", help="method name (see 'stickfigure methods'; default em)")
    p.add_argument("-o", "--output", required=True, metavar="MODEL.json", help="where to save the model")
    p.add_argument("--param", action="append", metavar="NAME=VALUE",
                   help="method parameter, repeatable (e.g. --param n_iter=100)")
    p.add_argument("--seed", type=int, default=None, help="random seed (same seed, same skeleton)")
    _add_input_options(p)
    p.set_defaults(run=_cmd_fit)

    p = cmd("impute", "fill missing points with a learned skeleton",
            "Fill every missing entry of INPUT from the learned structure (the model's sticks are kept, their "
            "motions re-fitted to the visible points) and write the completed trajectories.",
            "  stickfigure impute model.json occluded.csv -o filled.csv\n")
    p.add_argument("model", metavar="MODEL", help="a model written by 'stickfigure fit'")
    p.add_argument("input", metavar="INPUT", help=INPUT_HELP + "; the same points as the model")
    p.add_argument("-o", "--output", required=True, metavar="OUT.csv|npz", help="completed trajectories")
    _add_input_options(p)
    p.set_defaults(run=_cmd_impute)

    p = cmd("render", "draw a skeleton over its trajectories (PNG, GIF or MP4)",
            "Draw the learned sticks and joints over the points: a grid of frames (.png, .pdf, .svg) or an "
            "animation (.gif, .mp4). Tracks from a video are drawn over the video's frames.",
            "  stickfigure render model.json tracks.npz -o skeleton.mp4\n"
            "  stickfigure render model.json walk.csv -o frames.png --frames 0:100 --n 8\n")
    p.add_argument("model", metavar="MODEL", help="a model written by 'stickfigure fit'")
    p.add_argument("input", metavar="INPUT", help=INPUT_HELP)
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="picture (.png/.pdf/.svg) or animation (.gif/.mp4)")
    p.add_argument("--frames", metavar="A:B[:K]|F1,F2,...",
                   help="frames to draw (a slice, or a list for pictures)")
    p.add_argument("--n", type=_positive_int, default=6, help="number of frames in a picture (default 6)")
    p.add_argument("--fps", type=_positive_float, help="animation frame rate (default: the data's)")
    p.add_argument("--max-frames", type=_positive_int, default=300,
                   help="longest animation; longer clips keep every k-th frame (default 300)")
    p.add_argument("--width", type=_positive_int, default=480, help="animation width in pixels (default 480)")
    p.add_argument("--imputed", action="store_true", help="draw missing points at their imputed positions")
    p.add_argument("--no-video", action="store_true", help="do not draw the video under tracked points")
    p.add_argument("--view", metavar="VIEW",
                   help="how to look at a 3D model: isometric, front, side, top or AZIMUTH,ELEVATION "
                        "(default: the first two coordinates)")
    _add_input_options(p, frames=False)
    p.set_defaults(run=_cmd_render)

    p = cmd("evaluate", "score a skeleton against the ground truth in the input",
            "Compare the model with the ground truth the input carries (synthetic figures, motion capture, "
            "Hopkins 155): adjusted Rand index, misclassification rate, edge precision/recall/F1 and exact "
            "structure. --protocol also runs the Ross et al. held-out imputation test.",
            "  stickfigure evaluate model.json truth.npz\n  stickfigure evaluate model.json walk.c3d --project "
            "isometric --json\n")
    p.add_argument("model", metavar="MODEL", help="a model written by 'stickfigure fit'")
    p.add_argument("input", metavar="INPUT", help=INPUT_HELP + ", with ground truth")
    p.add_argument("--protocol", action="store_true",
                   help="also run the held-out imputation protocol (learn on 70%% of frames with the model's "
                        "method, occlude the rest, impute, RMSE)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    _add_input_options(p)
    p.set_defaults(run=_cmd_evaluate)

    p = cmd("export-angles", "write per-frame joint angles as CSV",
            "Write the angle between the two sticks of every joint in every frame (columns frame, joint, "
            "parent_stick, child_stick, angle_deg). 2D: signed degrees in (-180, 180], 0 = straight on. "
            "Give INPUT to measure other frames, or for models without stick motions.",
            "  stickfigure export-angles model.json -o angles.csv\n"
            "  stickfigure export-angles model.json new_frames.csv -o angles.csv\n")
    p.add_argument("model", metavar="MODEL", help="a model written by 'stickfigure fit'")
    p.add_argument("input", metavar="INPUT", nargs="?", help=INPUT_HELP + " (default: the training frames)")
    p.add_argument("-o", "--output", required=True, metavar="ANGLES.csv")
    _add_input_options(p)
    p.set_defaults(run=_cmd_export_angles)

    p = cmd("export-bvh", "write the skeleton and its motion as BVH",
            "Write a Biovision Hierarchy file (one joint per stick, rotations per frame) that animation tools "
            "open; 2D skeletons lie in the z = 0 plane.",
            "  stickfigure export-bvh model.json -o motion.bvh\n"
            "  stickfigure export-bvh model.json tracks.npz -o motion.bvh --rigid\n")
    p.add_argument("model", metavar="MODEL", help="a model written by 'stickfigure fit'")
    p.add_argument("input", metavar="INPUT", nargs="?", help=INPUT_HELP + " (default: the training frames)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.bvh")
    p.add_argument("--fps", type=_positive_float, help="frame rate (default: the input's, else 30)")
    p.add_argument("--rigid", action="store_true",
                   help="rotations only, constant bone lengths (default: exact joint positions)")
    _add_input_options(p)
    p.set_defaults(run=_cmd_export_bvh)

    p = cmd("track", "track feature points through a video",
            "Detect corners and track them with pyramidal Lucas-Kanade (forward-backward checked, re-detected "
            "as they are lost); lost points become gaps. Writes trajectories that remember their video.",
            "  stickfigure track clip.mp4 -o tracks.npz\n"
            "  stickfigure track bikes.mp4 --roi 100,50,400,300 --start 20 --stop 200 -o tracks.npz\n")
    p.add_argument("video", metavar="VIDEO", help="any video OpenCV can decode")
    p.add_argument("-o", "--output", required=True, metavar="TRACKS.npz|csv")
    p.add_argument("--roi", metavar="X,Y,W,H", help="region of interest in pixels")
    p.add_argument("--start", type=int, default=0, help="first frame (default 0)")
    p.add_argument("--stop", type=int, default=None, help="frame to stop before (default: the end)")
    p.add_argument("--max-points", type=_positive_int, help="most tracks alive at once")
    p.add_argument("--option", action="append", metavar="NAME=VALUE", help="other tracker option, repeatable")
    p.set_defaults(run=_cmd_track)

    p = cmd("learn", "video, tracks or motion capture -> model, animation and report",
            "One command from a video (tracked first), a tracks file or motion capture to a learned skeleton: "
            "writes the model, a video of the skeleton over the input and an HTML report into DIR.",
            "  stickfigure learn clip.mp4 -o clip-out/\n  stickfigure learn walk.c3d --method em -o walk-out/\n"
            "  stickfigure learn bikes.mp4 --frames 76:137 --roi 330,0,310,272 --track-option min_motion=0.002 "
            "-o cyclist/\n")
    p.add_argument("source", metavar="VIDEO|TRACKS|MOCAP")
    p.add_argument("-m", "--method", default="em", help="method name (default em)")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="output folder")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", help="method parameter, repeatable")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--frames", metavar="A:B", help="frame range of the input")
    p.add_argument("--project", metavar="VIEW", default="isometric",
                   help="view for 3D input (default isometric; 'none' keeps 3D)")
    p.add_argument("--camera-distance", type=_positive_float, metavar="D",
                   help="3D input: a pinhole camera D from the scene centre, in the data's units "
                        "(default: orthographic)")
    p.add_argument("--roi", metavar="X,Y,W,H", help="video input: track only in this region (pixels)")
    p.add_argument("--track-option", action="append", metavar="NAME=VALUE",
                   help="video input: other tracker option (see 'stickfigure track'), repeatable, "
                        "e.g. min_motion=0.002 for a subject that barely moves")
    p.set_defaults(run=_cmd_learn)

    p = cmd("report", "write a self-contained HTML report",
            "One HTML page: the skeleton animated over the input, the tree, stick and joint tables, the method's "
            "diagnostics and, with ground truth, scores and imputation errors.",
            "  stickfigure report model.json tracks.npz -o report.html\n")
    p.add_argument("model", metavar="MODEL", help="a model written by 'stickfigure fit'")
    p.add_argument("input", metavar="INPUT", help=INPUT_HELP)
    p.add_argument("-o", "--output", required=True, metavar="REPORT.html")
    p.add_argument("--title", help="page title")
    _add_input_options(p)
    p.set_defaults(run=_cmd_report)
    return parser


# ------------------------------------------------------------------ helpers
def _say(args: argparse.Namespace, msg: str) -> None:
    if not args.quiet:
        print(msg, file=sys.stderr, flush=True)


def _load_input(args: argparse.Namespace, path: str, *, frames: bool = True) -> Any:
    """Load INPUT and apply --frames, --subsample, --project, --drop-unobserved."""
    import stickfigure as sf

    from .plot import parse_frame_range

    opts = _key_values(getattr(args, "load_options", None), "--load-option")
    traj = sf.load(path, **opts)
    if frames and getattr(args, "frames", None):
        sel = parse_frame_range(args.frames)
        if not isinstance(sel, slice):
            raise ValueError(f"--frames must be a range A:B[:K] here, got {args.frames!r}")
        traj = traj.slice(frames=sel)
    if getattr(args, "subsample", None):
        traj = traj.subsample(args.subsample)
    view = _view(getattr(args, "project", None))
    distance = getattr(args, "camera_distance", None)
    if distance is not None and view is None:
        raise ValueError("--camera-distance places the camera of --project: give --project too")
    if view is not None:
        if traj.n_dims != 3:
            raise ValueError(f"--project applies to 3D data, but {Path(path).name} is {traj.n_dims}D")
        traj = traj.project(view, distance=distance)
    if getattr(args, "drop_unobserved", False):
        traj = traj.drop_unobserved()
    return traj


def _load_model(path: str) -> Any:
    from .skeleton import Skeleton

    return Skeleton.load(path)


def _check_match(skeleton: Any, traj: Any, path: str) -> None:
    """A model and its INPUT must have the same points and dimension; say how to fix it."""
    name = Path(path).name
    if skeleton.n_dims == 2 and traj.n_dims == 3:
        raise ValueError(f"the model was fitted to 2D data but {name} is 3D: add --project with the view used for fit")
    if skeleton.n_dims != traj.n_dims:
        raise ValueError(f"the model was fitted to {skeleton.n_dims}D data but {name} is {traj.n_dims}D")
    if skeleton.n_points != traj.n_points:
        raise ValueError(f"the model has {skeleton.n_points} points but {name} has {traj.n_points}: use the same "
                         "input and reading options as for fit")


def _check_suffix(path: str, allowed: Sequence[str], what: str) -> Path:
    p = Path(path)
    if p.suffix.lower() not in allowed:
        raise ValueError(f"{what} must end in {', '.join(allowed)}, got {p.name!r}")
    return p


def _method_params(args: argparse.Namespace, method: str) -> dict[str, Any]:
    from .models import get_method

    params = _key_values(args.param, "--param")
    cls = get_method(method)
    try:  # a wrong parameter name fails here, before any work
        cls(**params)
    except TypeError as exc:
        raise TypeError(f"bad parameter for method {method!r}: {exc}") from None
    if not args.quiet and "progress" in cls().get_params() and "progress" not in params:
        params["progress"] = True
    return params


# ----------------------------------------------------------------- commands
def _cmd_methods(args: argparse.Namespace) -> int:
    from .models import available_methods, get_method

    names = available_methods()
    if not names:
        print("no methods are installed")
        return 0
    width = max(len(n) for n in names)
    for name in names:
        doc = (get_method(name).__doc__ or "").strip().splitlines()
        print(f"{name:<{width}}  {doc[0] if doc else ''}")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    import stickfigure as sf

    out = Path(args.output)
    traj = _load_input(args, args.input)
    params = _method_params(args, args.method)
    _say(args, f"fitting {args.method!r} to {traj!r}")
    t0 = time.perf_counter()
    skeleton = sf.fit(traj, method=args.method, random_state=args.seed, **params)
    dt = time.perf_counter() - t0
    path = skeleton.save(out)
    print(skeleton.summary())
    print(f"fitted in {dt:.1f} s; model written to {path} (+ {path.with_suffix('.npz').name})")
    return 0


def _cmd_impute(args: argparse.Namespace) -> int:
    import stickfigure as sf

    out = _check_suffix(args.output, (".csv", ".npz"), "the output")
    skeleton = _load_model(args.model)
    traj = _load_input(args, args.input)
    _check_match(skeleton, traj, args.input)
    filled = skeleton.impute(traj)
    n_missing = int((~traj.observed).sum())
    path = sf.save(traj.with_xy(filled), out) or out
    print(f"filled {n_missing} missing observations ({100 * traj.missing_fraction:.1f}%); written to {path}")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from . import plot
    from .export import pose

    out = _check_suffix(args.output, (".png", ".pdf", ".svg", ".gif", ".mp4"), "the output")
    skeleton = _load_model(args.model)
    traj = _load_input(args, args.input, frames=False)
    _check_match(skeleton, traj, args.input)
    frames = plot.parse_frame_range(args.frames) if args.frames else None
    if frames is not None:
        plot.select_frames(frames, traj.n_frames)  # a bad selection fails before any work
    p = pose(skeleton, traj)
    kw: dict[str, Any] = {"pose": p}
    if args.view is not None:
        if traj.n_dims != 3:
            raise ValueError("--view applies to 3D models; 2D data are drawn as they are")
        kw["view"] = _view(args.view)
    if args.imputed:
        kw["imputed"] = p.points
    video = False if args.no_video else None
    if out.suffix.lower() in (".gif", ".mp4"):
        plot.animate(traj, skeleton, out, fps=args.fps, frames=frames, max_frames=args.max_frames,
                     width=args.width, video=video, progress=not args.quiet, **kw)
    else:
        plot.plot_frames(traj, skeleton, frames=frames, path=out, n=args.n, video=video, **kw)
    print(f"written to {out}")
    return 0


def _format_table(rows: dict[str, Any]) -> str:
    width = max((len(k) for k in rows), default=0)
    lines = []
    for k, v in rows.items():
        if isinstance(v, float):
            text = f"{v:.4f}"
        elif isinstance(v, (dict, list)):
            text = json.dumps(v)
        else:
            text = str(v)
        lines.append(f"{k:<{width}}  {text}")
    return "\n".join(lines)


def _jsonable(v: Any) -> Any:
    import numpy as np

    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .metrics import score_skeleton

    skeleton = _load_model(args.model)
    traj = _load_input(args, args.input)
    _check_match(skeleton, traj, args.input)
    if traj.labels_true is None:
        raise ValueError(f"{Path(args.input).name} has no ground truth (labels_true) to score against")
    scores = _jsonable(score_skeleton(skeleton, traj))
    if args.protocol:
        from .evaluation import imputation_protocol

        # The held-out test re-learns the model's method (default parameters) on the first 70% of frames.
        result = imputation_protocol(traj, method=skeleton.method, random_state=0)
        scores["protocol"] = _jsonable({k: v for k, v in result.items() if k not in ("skeleton", "imputed")})
    if args.json:
        print(json.dumps(scores, indent=1))
    else:
        flat = {k: v for k, v in scores.items() if k != "protocol"}
        print(_format_table(flat))
        if "protocol" in scores:
            print("held-out imputation protocol:")
            print("\n".join("  " + line for line in _format_table(scores["protocol"]).splitlines()))
    return 0


def _optional_input(args: argparse.Namespace, skeleton: Any) -> Any:
    if args.input is None:
        for opt in ("frames", "subsample", "project", "load_options"):
            if getattr(args, opt, None):
                raise ValueError(f"--{opt.replace('_', '-')} needs an INPUT file")
        return None
    traj = _load_input(args, args.input)
    _check_match(skeleton, traj, args.input)
    return traj


def _cmd_export_angles(args: argparse.Namespace) -> int:
    from .export import write_angles_csv

    out = _check_suffix(args.output, (".csv",), "the output")
    skeleton = _load_model(args.model)
    path = write_angles_csv(skeleton, out, traj=_optional_input(args, skeleton))
    print(f"joint angles of {len(skeleton.edges)} joints written to {path}")
    return 0


def _cmd_export_bvh(args: argparse.Namespace) -> int:
    from .export import write_bvh

    out = _check_suffix(args.output, (".bvh",), "the output")
    skeleton = _load_model(args.model)
    path = write_bvh(skeleton, out, traj=_optional_input(args, skeleton), frame_rate=args.fps,
                     lengths="rigid" if args.rigid else "exact")
    print(f"BVH with {skeleton.n_sticks} sticks written to {path}")
    return 0


def _roi(text: str) -> tuple[int, ...]:
    try:
        roi = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--roi must be X,Y,W,H in pixels, got {text!r}") from None
    if len(roi) != 4:
        raise ValueError(f"--roi must be X,Y,W,H in pixels, got {text!r}")
    return roi


def _cmd_track(args: argparse.Namespace) -> int:
    import stickfigure as sf

    from .track import track_video

    out = _check_suffix(args.output, (".npz", ".csv"), "the output")
    opts = _key_values(args.option, "--option")
    if args.roi:
        opts["roi"] = _roi(args.roi)
    if args.max_points:
        opts["max_points"] = args.max_points
    if not Path(args.video).is_file():
        raise FileNotFoundError(f"no such video: {args.video}")
    traj = track_video(args.video, start=args.start, stop=args.stop, progress=not args.quiet, **opts)
    path = sf.save(traj, out) or out
    print(f"{traj.n_points} tracks over {traj.n_frames} frames ({100 * traj.missing_fraction:.0f}% missing) "
          f"written to {path}")
    return 0


def _cmd_learn(args: argparse.Namespace) -> int:
    from .pipeline import learn
    from .plot import parse_frame_range

    params = _key_values(args.param, "--param")
    frames = None
    if args.frames:
        frames = parse_frame_range(args.frames)
        if not isinstance(frames, slice):
            raise ValueError(f"--frames must be a range A:B, got {args.frames!r}")
    project = None if str(args.project).lower() == "none" else _view(args.project)
    if not Path(args.source).exists():
        raise FileNotFoundError(f"no such input: {args.source}")
    kw: dict[str, Any] = {"progress": not args.quiet, "random_state": args.seed, "project": project}
    if args.camera_distance is not None:
        if project is None:
            raise ValueError("--camera-distance places the camera of --project: it cannot go with --project none")
        kw["camera_distance"] = args.camera_distance
    if frames is not None:
        kw["frames"] = frames
    track_options = _key_values(args.track_option, "--track-option")
    if args.roi:
        track_options["roi"] = _roi(args.roi)
    if track_options:
        from .track import VIDEO_SUFFIXES

        if Path(args.source).suffix.lower() not in VIDEO_SUFFIXES:
            raise ValueError("--roi and --track-option apply to video input only")
        kw["track_options"] = track_options
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        paths = learn(args.source, args.output, method=args.method, **kw, **params)
    for what, path in paths.items():
        print(f"{what}: {path}")
    for w in caught:  # e.g. no articulated motion in the video: said last, where a user looks
        if issubclass(w.category, UserWarning):
            print(f"warning: {w.message}")
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from .report import write_report

    out = _check_suffix(args.output, (".html", ".htm"), "the output")
    skeleton = _load_model(args.model)
    traj = _load_input(args, args.input)
    _check_match(skeleton, traj, args.input)
    path = write_report(skeleton, traj, out, title=args.title)
    print(f"report written to {path}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    params = _key_values(args.param, "--param")
    t0 = time.perf_counter()
    paths = run_demo(args.output, method=args.method, seed=args.seed, n_frames=args.n_frames, figure=args.figure,
                     occlusion=not args.no_occlusion, progress=not args.quiet,
                     say=lambda m: _say(args, m), **params)
    print(Path(paths["summary"]).read_text(encoding="utf-8").rstrip())
    print()
    print(f"demo finished in {time.perf_counter() - t0:.1f} s; files in {Path(args.output)}/:")
    for what in ("picture", "animation", "summary", "model", "input"):
        print(f"  {what:<9} {paths[what]}")
    print(f"try: stickfigure render {paths['model']} {paths['input']} -o frames.png")
    return 0


# --------------------------------------------------------------------- main
def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, KeyError):
        text = f"missing {text}"
    return text or type(exc).__name__


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``stickfigure`` command; returns the exit status.

    Exit status: 0 on success, 2 on bad input (one line on stderr), 1 when an
    output cannot be written, 130 on Ctrl-C.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, argparse errors
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    # FFmpeg reads its log level once, when OpenCV first uses it: set it before any video is
    # touched, so a broken video gives our one error line and not FFmpeg's complaints too.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    try:
        import matplotlib

        matplotlib.use("Agg")  # files only: never open a window
        return int(args.run(args) or 0)
    except (ValueError, FileNotFoundError, TypeError, KeyError, IsADirectoryError, NotADirectoryError) as exc:
        if args.debug:
            raise
        print(f"stickfigure: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:
        if args.debug:
            raise
        print(f"stickfigure: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stickfigure: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
