"""The ``stickfigure`` command as a user types it: in-process through ``main([...])`` and once as a subprocess."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import stickfigure as sf
from stickfigure.cli import build_parser, main

COMMANDS = ["demo", "methods", "fit", "impute", "render", "evaluate", "export-angles", "export-bvh", "track",
            "learn", "report"]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A small 3D figure seen from a random view: clean (with truth) and occluded, as files."""
    d = tmp_path_factory.mktemp("cli")
    fig = sf.synthetic.random_figure(n_sticks=3, frames=40, noise=0.01, seed=7)
    occ, _ = sf.synthetic.occlude(fig, seed=0)
    sf.save(fig, d / "fig.npz")
    sf.save(occ, d / "occ.csv")
    return d, fig


@pytest.fixture(scope="module")
def model(work):
    """A real model: mi-tree given the true segmentation (--param with a list value), fitted by the CLI."""
    d, fig = work
    labels = json.dumps(fig.labels_true.tolist())
    rc = main(["-q", "fit", str(d / "fig.npz"), "--method", "mi-tree", "--param", f"labels={labels}",
               "-o", str(d / "model.json")])
    assert rc == 0
    return d / "model.json"


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err  # one line, no traceback
    assert err[0].startswith("stickfigure: error: ")
    return err[0]


# --------------------------------------------------------------------- help
@pytest.mark.parametrize("command", COMMANDS)
def test_help_for_every_command(command, capsys):
    assert main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: stickfigure {command}") and "examples:" in out


def test_top_level_help_lists_commands(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for command in COMMANDS:
        assert command in out
    assert main([]) == 0  # no command: the help
    assert "commands" in capsys.readouterr().out
    sub = build_parser()._subparsers._group_actions[0].choices  # every command is documented
    assert sorted(sub) == sorted(COMMANDS)


def test_methods_lists_registered_methods(capsys):
    assert main(["methods"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split()[0] for line in lines] == sf.available_methods()
    assert all(len(line.split()) > 2 for line in lines)  # a description on each line


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("argv, message", [
    (["fit", "no/such/file.csv", "-o", "m.json"], "no such file"),
    (["fit", "{fig}", "--method", "nonsense", "-o", "{d}/m.json"], "unknown method 'nonsense'"),
    (["fit", "{fig}", "--method", "mi-tree", "--param", "bogus=1", "-o", "{d}/m.json"], "bogus"),
    (["fit", "{fig}", "--method", "mi-tree", "--param", "novalue", "-o", "{d}/m.json"], "name=value"),
    (["fit", "{fig}", "--frames", "x:y", "-o", "{d}/m.json"], "frames"),
    (["fit", "{fig}", "--project", "isometric", "-o", "{d}/m.json"], "3D"),
    (["fit", "{fig}", "--subsample", "0", "-o", "{d}/m.json"], "positive integer"),
    (["fit", "{fig}"], "required"),
    (["render", "{model}", "{fig}", "-o", "{d}/out.txt"], "must end in"),
    (["render", "{model}", "{fig}", "-o", "{d}/out.png", "--frames", "100:200"], "empty"),
    (["render", "{d}/missing.json", "{fig}", "-o", "{d}/out.png"], "no such model file"),
    (["render", "{fig}", "{fig}", "-o", "{d}/out.png"], "not a stickfigure model"),
    (["export-angles", "{model}", "-o", "{d}/a.csv", "--frames", "0:5"], "needs an INPUT"),
    (["export-bvh", "{model}", "{other}", "-o", "{d}/a.bvh"], "the model has 24 points but other.npz has"),
    (["track", "{d}/missing.mp4", "-o", "{d}/t.npz"], "no such video"),
    (["track", "{fig}", "-o", "{d}/t.npz", "--roi", "1,2"], "X,Y,W,H"),
    (["nonsense"], "invalid choice"),
])
def test_bad_input_exits_2_with_one_line(argv, message, work, model, tmp_path, capsys):
    d, _ = work
    other = tmp_path / "other.npz"
    sf.save(sf.synthetic.random_figure(n_sticks=2, frames=10, seed=1), other)
    subs = {"fig": str(d / "fig.npz"), "d": str(tmp_path), "model": str(model), "other": str(other)}
    argv = [a.format(**subs) for a in argv]
    assert main(argv) == 2
    assert message in _error_line(capsys)
    assert not any(p.name.startswith(("m.", "out.", "a.", "t.")) for p in tmp_path.iterdir())


def test_debug_shows_the_traceback(work):
    d, _ = work
    with pytest.raises(ValueError, match="unknown method"):
        main(["fit", str(d / "fig.npz"), "--method", "nonsense", "-o", str(d / "x.json"), "--debug"])


def test_console_script_subprocess(tmp_path):
    """The installed console script: bad input gives exit 2 and one line (help is tested in-process)."""
    exe = Path(sys.executable).with_name("stickfigure")
    if not exe.exists():
        pytest.skip(f"the console script is not installed beside {sys.executable}")
    bad = subprocess.run([str(exe), "render", str(tmp_path / "m.json"), str(tmp_path / "x.csv"), "-o",
                          str(tmp_path / "o.png")], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [f"stickfigure: error: no such model file: {tmp_path / 'm.json'}"]


# ----------------------------------------------------------------- commands
def test_fit_writes_a_model(work, model, capsys):
    d, fig = work
    sk = sf.Skeleton.load(model)
    assert sk.method == "mi-tree" and sk.n_sticks == 3 and len(sk.edges) == 2
    assert (d / "model.npz").exists()


@pytest.mark.parametrize("method", ["sfm", "multibody-sfm"])
def test_fit_with_loader_options(method, work, tmp_path, capsys):
    d, fig = work
    out = tmp_path / "m.json"
    assert main(["-q", "fit", str(d / "occ.csv"), "--method", method, "--frames", "0:30", "--subsample", "2",
                 "--seed", "0", "-o", str(out)]) == 0
    sk = sf.Skeleton.load(out)
    assert sk.method == method and sk.n_points == fig.n_points
    assert "model written to" in capsys.readouterr().out


def test_fit_projects_3d_mocap(tmp_path, capsys):
    walker = sf.synthetic.walker(n_frames=20, project=False, seed=0)
    sf.save(walker, tmp_path / "walk3d.npz")
    labels = json.dumps(walker.labels_true.tolist())
    assert main(["-q", "fit", str(tmp_path / "walk3d.npz"), "--project", "30,20", "--method", "mi-tree",
                 "--param", f"labels={labels}", "-o", str(tmp_path / "w.json")]) == 0
    assert sf.Skeleton.load(tmp_path / "w.json").n_dims == 2
    # Using the model with the 3D file again needs the same projection; the error says so.
    assert main(["render", str(tmp_path / "w.json"), str(tmp_path / "walk3d.npz"), "-o", str(tmp_path / "w.png")]) == 2
    assert "--project" in _error_line(capsys)
    assert main(["-q", "render", str(tmp_path / "w.json"), str(tmp_path / "walk3d.npz"), "--project", "30,20",
                 "-o", str(tmp_path / "w.png")]) == 0
    # A pinhole camera for the projection; without --project the distance has nothing to place.
    assert main(["-q", "fit", str(tmp_path / "walk3d.npz"), "--project", "30,20", "--camera-distance", "6",
                 "--method", "mi-tree", "--param", f"labels={labels}", "-o", str(tmp_path / "p.json")]) == 0
    assert sf.Skeleton.load(tmp_path / "p.json").n_dims == 2
    assert main(["fit", str(tmp_path / "walk3d.npz"), "--camera-distance", "6", "--method", "mi-tree",
                 "--param", f"labels={labels}", "-o", str(tmp_path / "q.json")]) == 2
    assert "--camera-distance" in _error_line(capsys)


def test_impute(work, model, tmp_path, capsys):
    d, fig = work
    out = tmp_path / "filled.csv"
    assert main(["impute", str(model), str(d / "occ.csv"), "-o", str(out)]) == 0
    filled = sf.load(out)
    occ = sf.load(d / "occ.csv")
    assert not np.isnan(filled.xy).any()
    np.testing.assert_allclose(filled.xy[occ.observed], occ.xy[occ.observed], atol=1e-9)
    assert "filled" in capsys.readouterr().out


def test_render_png_gif_mp4(work, model, tmp_path):
    d, fig = work
    assert main(["-q", "render", str(model), str(d / "fig.npz"), "-o", str(tmp_path / "f.png"), "--n", "4"]) == 0
    im = Image.open(tmp_path / "f.png")
    assert im.size[0] >= 800 and np.asarray(im.convert("L")).std() > 5
    assert main(["-q", "render", str(model), str(d / "occ.csv"), "-o", str(tmp_path / "a.gif"), "--frames", "5:25",
                 "--imputed", "--width", "160"]) == 0
    assert Image.open(tmp_path / "a.gif").n_frames == 20
    assert main(["-q", "render", str(model), str(d / "fig.npz"), "-o", str(tmp_path / "b.gif"), "--max-frames",
                 "10", "--width", "128"]) == 0
    assert Image.open(tmp_path / "b.gif").n_frames == 10
    assert main(["-q", "render", str(model), str(d / "fig.npz"), "-o", str(tmp_path / "c.mp4"), "--width",
                 "128"]) == 0
    assert (tmp_path / "c.mp4").stat().st_size > 1000


def test_export_angles_and_bvh(work, model, tmp_path):
    d, fig = work
    assert main(["export-angles", str(model), "-o", str(tmp_path / "angles.csv")]) == 0
    with open(tmp_path / "angles.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * fig.n_frames and rows[0].keys() == {"frame", "joint", "parent_stick", "child_stick",
                                                                "angle_deg"}
    assert all(-180 < float(r["angle_deg"]) <= 180 for r in rows)
    # On other frames of the same points, numbered as in the clip.
    assert main(["export-angles", str(model), str(d / "occ.csv"), "--frames", "10:20", "-o",
                 str(tmp_path / "later.csv")]) == 0
    with open(tmp_path / "later.csv", newline="") as fh:
        frames = sorted({int(r["frame"]) for r in csv.DictReader(fh)})
    assert frames == list(range(10, 20))
    assert main(["export-bvh", str(model), "-o", str(tmp_path / "m.bvh"), "--fps", "25"]) == 0
    back = sf.load(tmp_path / "m.bvh", merge_rigid=False)
    assert back.n_frames == fig.n_frames and back.frame_rate == pytest.approx(25.0)
    assert {"stick0", "stick1", "stick2"} <= set(back.names)
    sk = sf.Skeleton.load(model)
    from stickfigure.export import bvh_coordinates, pose

    p = pose(sk)
    for e, c in enumerate(p.child_stick):  # each child stick's BVH joint is the model's joint
        fk = back.xy[back.names.index(f"stick{c}")]
        np.testing.assert_allclose(fk, bvh_coordinates(p.joints[e], None, 2), atol=1e-4)
    assert main(["export-bvh", str(model), str(d / "fig.npz"), "--rigid", "-o", str(tmp_path / "r.bvh")]) == 0
    assert "CHANNELS 3 Zrotation" in (tmp_path / "r.bvh").read_text()


def test_evaluate(work, model, capsys):
    d, fig = work
    assert main(["evaluate", str(model), str(d / "fig.npz")]) == 0
    table = capsys.readouterr().out
    assert "ari" in table and "edge_f1" in table
    assert main(["evaluate", str(model), str(d / "fig.npz"), "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["ari"] == pytest.approx(1.0)  # mi-tree was given the true segmentation


def test_evaluate_needs_ground_truth(work, model, tmp_path, capsys):
    d, fig = work
    bare = fig.copy(labels_true=None, edges_true=None, joints_true=None, part_names=None)
    sf.save(bare, tmp_path / "bare.npz")
    assert main(["evaluate", str(model), str(tmp_path / "bare.npz")]) == 2
    assert "ground truth" in _error_line(capsys)


def test_report(work, model, tmp_path):
    d, fig = work
    assert main(["-q", "report", str(model), str(d / "fig.npz"), "-o", str(tmp_path / "r.html"), "--title",
                 "a test"]) == 0
    html = (tmp_path / "r.html").read_text()
    assert "<html" in html.lower() and "a test" in html


def _texture_video(path: Path, n_frames: int = 24) -> None:
    """Two textured squares moving in opposite directions over a dark background."""
    import imageio.v2 as imageio

    rng = np.random.default_rng(0)
    tex = (rng.random((40, 40, 3)) * 255).astype(np.uint8)
    with imageio.get_writer(path, fps=12, codec="libx264", quality=9, macro_block_size=16) as w:
        for k in range(n_frames):
            img = np.full((144, 192, 3), 30, np.uint8)
            img[20 + k:60 + k, 20 + 2 * k:60 + 2 * k] = tex
            img[80:120, 140 - 2 * k:180 - 2 * k] = tex[::-1]
            w.append_data(img)


def test_track(tmp_path, capsys):
    video = tmp_path / "squares.mp4"
    _texture_video(video)
    out = tmp_path / "tracks.npz"
    assert main(["-q", "track", str(video), "-o", str(out), "--max-points", "60"]) == 0
    traj = sf.load(out)
    assert traj.image_size == (192, 144) and traj.n_points >= 4 and traj.video == str(video)
    assert "tracks over" in capsys.readouterr().out
    # The tracks render over their video.
    assert main(["-q", "render", "--help"]) == 0


def test_learn(work, tmp_path, capsys):
    d, fig = work
    labels = json.dumps(fig.labels_true.tolist())
    assert main(["-q", "learn", str(d / "fig.npz"), "--method", "mi-tree", "--param", f"labels={labels}",
                 "-o", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    for what in ("model", "animation", "report"):
        assert f"{what}:" in out
    assert (tmp_path / "out" / "report.html").exists()
    # --camera-distance places the camera of --project; with --project none there is none.
    assert main(["-q", "learn", str(d / "fig.npz"), "--project", "none", "--camera-distance", "5",
                 "-o", str(tmp_path / "none")]) == 2
    assert "--camera-distance" in _error_line(capsys)


def test_learn_video_with_tracker_options(work, tmp_path, capsys):
    """--roi and --track-option reach the tracker: only the square moving in the region is tracked."""
    video = tmp_path / "squares.mp4"
    _texture_video(video)
    out = tmp_path / "o"
    assert main(["-q", "learn", str(video), "-o", str(out), "--method", "multibody-sfm", "--roi", "0,0,110,144",
                 "--track-option", "max_points=40", "--track-option", "min_length=5"]) == 0
    tracks = sf.load(out / "tracks.npz")
    assert tracks.meta["roi"] == [0, 0, 110, 144] and tracks.meta["tracker"]["max_points"] == 40
    assert np.nanmax(tracks.xy[..., 0]) <= 110
    d, _ = work
    assert main(["-q", "learn", str(d / "fig.npz"), "-o", str(tmp_path / "p"), "--roi", "0,0,10,10"]) == 2
    assert "video input only" in _error_line(capsys)
    assert main(["-q", "learn", str(video), "-o", str(tmp_path / "q"), "--track-option", "no_such=1"]) == 2
    assert "no_such" in _error_line(capsys)


@pytest.mark.parametrize("content", [b"", b"this is not a video\n" * 50])
def test_learn_unreadable_video_one_line(content, tmp_path):
    """A broken video: exit 2, one line on the process's stderr (FFmpeg's own complaints
    silenced too), and no output folder left behind."""
    video = tmp_path / "broken.mp4"
    video.write_bytes(content)
    out = tmp_path / "out"
    # A fresh process: FFmpeg's log level is fixed the first time a process uses it.
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    env.pop("OPENCV_FFMPEG_LOGLEVEL", None)
    run = subprocess.run([sys.executable, "-m", "stickfigure.cli", "-q", "learn", str(video), "-o", str(out)],
                         capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 2
    err = run.stderr.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("stickfigure: error: ") and "broken.mp4" in err[0]
    assert not out.exists()


def _run_demo(out, capsys, *argv):
    assert main(["-q", "demo", "-o", str(out), *argv]) == 0
    printed = capsys.readouterr().out
    for name in ("frames.png", "random.gif", "summary.txt", "model.json", "random.npz"):
        assert (out / name).stat().st_size > 0, name
        assert name in printed
    return printed


def test_demo_wiring(tmp_path, capsys):
    """The demo's steps and files, with a fast method (the default em run is the slow test below)."""
    method = "sfm" if "sfm" in sf.available_methods() else "mi-tree"
    out = tmp_path / "demo"
    _run_demo(out, capsys, "--n-frames", "30", "--method", method)
    assert Image.open(out / "random.gif").n_frames == 30
    summary = (out / "summary.txt").read_text()
    assert f"method: {method}" in summary and "truth: 5 sticks" in summary
    sk = sf.Skeleton.load(out / "model.json")
    truth = sf.load(out / "random.npz")
    assert sk.n_points == truth.n_points and truth.n_parts_true == 5 and truth.missing_fraction > 0.05


@pytest.mark.slow
def test_demo_default_run(tmp_path, capsys):
    """`stickfigure demo` as a newcomer runs it: the main method on the default figure."""
    _run_demo(tmp_path / "demo", capsys)
    assert "method: em" in (tmp_path / "demo" / "summary.txt").read_text()
    assert Image.open(tmp_path / "demo" / "random.gif").n_frames == 60


def test_demo_figures():
    from stickfigure.demo import make_figure

    walker = make_figure("walker", n_frames=20)
    assert walker.shape == (55, 20, 2) and walker.n_parts_true == 11
    random = make_figure("random", seed=1)
    assert random.n_frames == 60 and random.n_parts_true == 5
    assert np.array_equal(make_figure("random", seed=1).xy, random.xy)  # seeded
    with pytest.raises(ValueError, match="figure"):
        make_figure("horse")
