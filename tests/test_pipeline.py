"""learn(): input -> (tracks) -> skeleton -> animation + report, on synthetic data, a synthetic video and real files."""

from __future__ import annotations

import cv2
import imageio.v2 as imageio
import numpy as np
import pytest

import stickfigure as sf
from stickfigure.pipeline import learn
from stickfigure.report import write_report

from _video import paste_two_link_arm, write_video

#: The method the pipeline tests fit end to end without help (no given segmentation): the paper's
#: method for the known-answer test, the quickest one for the wiring test.
END_TO_END = "em"
QUICK = "multibody-sfm"


def _video_frames(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames


@pytest.fixture(scope="module")
def walker():
    return sf.synthetic.walker(n_frames=24, seed=0)


def test_learn_from_trajectories(tmp_path, walker):
    out = learn(walker, tmp_path / "out", method="mi-tree", labels=walker.labels_true)
    assert set(out) == {"points", "model", "model_arrays", "animation", "report"}
    for p in out.values():
        assert p.exists() and p.stat().st_size > 0
    skel = sf.Skeleton.load(out["model"])
    assert skel.method == "mi-tree" and skel.n_points == walker.n_points
    assert skel.n_sticks == walker.n_parts_true
    # What was fitted is saved beside the model: the report can be rebuilt from the files alone.
    pts = sf.load(out["points"])
    assert pts.shape == walker.shape
    np.testing.assert_allclose(pts.xy, walker.xy)
    again = write_report(skel, pts, tmp_path / "again.html")
    assert "mi-tree" in again.read_text(encoding="utf-8")
    # The animation has every frame.
    frames = _video_frames(out["animation"])
    assert len(frames) == walker.n_frames and frames[0].std() > 5


def test_learn_writes_gif_and_respects_frames(tmp_path, walker):
    out = learn(walker, tmp_path / "o", method="mi-tree", labels=walker.labels_true, frames=(5, 17),
                animation="gif")
    assert out["animation"].suffix == ".gif"
    pts = sf.load(out["points"])
    assert pts.n_frames == 12 and pts.meta["frame_offset"] == 5
    assert len(imageio.mimread(out["animation"])) == 12


def test_learn_from_3d_projects(tmp_path):
    walker3d = sf.synthetic.walker(n_frames=30, seed=1, project=False)
    out = learn(walker3d, tmp_path / "o", method="mi-tree", labels=walker3d.labels_true, project="side")
    pts = sf.load(out["points"])
    assert pts.n_dims == 2 and pts.meta["projection"]["azimuth"] == 0.0
    # Through a pinhole camera: the points written are that camera's image.
    out = learn(walker3d, tmp_path / "p", method="mi-tree", labels=walker3d.labels_true, project="side",
                camera_distance=5.0)
    pts = sf.load(out["points"])
    np.testing.assert_allclose(pts.xy, walker3d.project("side", distance=5.0).xy)
    assert pts.meta["projection"]["distance"] == 5.0


def test_learn_bad_input(tmp_path, walker):
    with pytest.raises(ValueError, match="unknown method"):
        learn(walker, tmp_path / "o", method="no-such-method")
    with pytest.raises(ValueError, match="not found"):
        learn(tmp_path / "missing.c3d", tmp_path / "o", method="mi-tree")
    with pytest.raises(ValueError, match="frames"):
        learn(walker, tmp_path / "o", method="mi-tree", frames=(10, 5))
    with pytest.raises(ValueError, match="animation"):
        learn(walker, tmp_path / "o", method="mi-tree", animation="avi")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a folder"):
        learn(walker, tmp_path / "file", method="mi-tree")


def test_unknown_method_fails_before_tracking(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(ValueError, match="unknown method"):
        learn(bad, tmp_path / "o", method="no-such-method")
    with pytest.raises(ValueError, match="broken.mp4"):
        learn(bad, tmp_path / "o", method=QUICK)


def _arm_angles(f, n):
    a1 = np.radians(-10 + 30 * np.sin(2 * np.pi * f / n))
    return a1, a1 + np.radians(40 * np.sin(2 * np.pi * f / n + 1.0))


SHOULDER = np.array([90.0, 150.0])  # both limbs stay inside the 300 x 300 frame


def _two_limb_video(path, n=60):
    """A textured 'arm': an upper limb turning about a fixed shoulder and a forearm turning about the elbow."""
    rng = np.random.default_rng(0)
    H, W = 300, 300
    bg = np.full((H, W), 35, np.uint8)
    tex = [cv2.GaussianBlur(rng.uniform(0, 255, (24, 90)).astype(np.float32), (0, 0), 1.6).astype(np.uint8)
           for _ in range(2)]
    frames = []
    for f in range(n):
        img = bg.copy()
        paste_two_link_arm(img, tex, SHOULDER, *_arm_angles(f, n))
        frames.append(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    write_video(path, frames, fps=20.0)
    return path


def test_learn_from_video(tmp_path):
    video = _two_limb_video(tmp_path / "arm.avi")
    out = learn(video, tmp_path / "o", method=QUICK, max_points=40)
    assert {"tracks", "points", "model", "animation", "report"} <= set(out)
    tracks = sf.load(out["tracks"])
    assert tracks.video.endswith("arm.avi") and tracks.image_size == (300, 300)
    pts = sf.load(out["points"])
    skel = sf.Skeleton.load(out["model"])
    assert 10 <= skel.n_points == pts.n_points <= 40
    # The points to learn from lie on both limbs: in each limb's coordinates, 0..90 px along it
    # from the shoulder (upper arm) or the elbow (forearm), within 12 px of its axis.
    f = np.arange(pts.n_frames) + pts.meta["frame_offset"]
    a1, a2 = _arm_angles(f, 60)
    elbow = SHOULDER + 80 * np.stack([np.cos(a1), np.sin(a1)], axis=1)
    on = []
    for origin, ang in ((SHOULDER, a1), (elbow, a2)):
        d = pts.xy - origin
        along = d[..., 0] * np.cos(ang) + d[..., 1] * np.sin(ang)
        across = -d[..., 0] * np.sin(ang) + d[..., 1] * np.cos(ang)
        with np.errstate(invalid="ignore"):
            inside = (along > -3) & (along < 93) & (np.abs(across) < 15)
        on.append(np.nanmean(np.where(pts.observed, inside, np.nan), axis=1) > 0.9)
    assert np.all(on[0] | on[1])  # every point follows one limb
    assert on[0].sum() >= 5 and on[1].sum() >= 5  # and both limbs are represented
    assert skel.n_sticks >= 1
    html = out["report"].read_text(encoding="utf-8")
    assert "data:image/jpeg;base64," in html  # the video frames are in the report


def _walker_video(path, n_frames=80, seed=0, W=480, H=360):
    """The synthetic walker rendered as textured limbs over a textured background.

    Each limb is the convex hull of its points, textured by warping its own
    texture with the limb's affine motion (exact for a rigid limb under the
    walker's orthographic camera). Returns the per-frame map of which limb
    each pixel shows (-1: background), shape (F, H, W).
    """
    tr = sf.synthetic.walker(n_frames=n_frames, points_per_stick=12, noise=0.0, seed=seed, cycles=1.5)
    xy = tr.xy
    lo, hi = np.nanmin(xy.reshape(-1, 2), axis=0), np.nanmax(xy.reshape(-1, 2), axis=0)
    s = 0.8 * min(W / (hi[0] - lo[0]), H / (hi[1] - lo[1]))
    px = np.stack([(xy[..., 0] - lo[0]) * s + 0.1 * W, H - ((xy[..., 1] - lo[1]) * s + 0.1 * H)], axis=-1)
    rng = np.random.default_rng(seed)

    def texture(lo_, span):
        t = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 2.0)
        return ((t - t.min()) / np.ptp(t) * span + lo_).astype(np.uint8)

    bg = texture(30, 60)
    S = tr.n_parts_true
    texs = [texture(55, 200) for _ in range(S)]
    labels = np.full((n_frames, H, W), -1, np.int16)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (W, H))
    for f in range(n_frames):
        img = bg.copy()
        for part in range(S):
            m = tr.labels_true == part
            A, _ = cv2.estimateAffine2D(px[m, 0].astype(np.float32), px[m, f].astype(np.float32), method=cv2.LMEDS)
            hull = cv2.convexHull(px[m, f].astype(np.float32)).astype(np.int32)
            mask = np.zeros((H, W), np.uint8)
            cv2.fillConvexPoly(mask, hull, 255)
            mask = cv2.dilate(mask, np.ones((5, 5), np.uint8)) > 0
            img[mask] = cv2.warpAffine(texs[part], A, (W, H), flags=cv2.INTER_LINEAR)[mask]
            labels[f][mask] = part
        w.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    w.release()
    return labels


@pytest.mark.slow
def test_learn_walker_video_known_answer(tmp_path):
    """A rendered walking figure: tracked, selected and fitted from the video alone, scored against its limbs."""
    from sklearn.metrics import adjusted_rand_score

    labels = _walker_video(tmp_path / "walker.avi")
    out = learn(tmp_path / "walker.avi", tmp_path / "o", method=END_TO_END)
    pts = sf.load(out["points"])
    skel = sf.Skeleton.load(out["model"])
    # Each tracked point's true limb: the limb under it in most of the frames it is seen.
    f = np.arange(pts.n_frames) + pts.meta["frame_offset"]
    xi = np.clip(np.round(pts.xy[..., 0]), 0, labels.shape[2] - 1)
    yi = np.clip(np.round(pts.xy[..., 1]), 0, labels.shape[1] - 1)
    under = np.where(pts.observed, labels[np.broadcast_to(f, xi.shape), np.nan_to_num(yi).astype(int),
                                         np.nan_to_num(xi).astype(int)], -2)
    truth = np.array([np.bincount(u[u >= -1] + 1).argmax() - 1 for u in under])
    assert np.mean(truth >= 0) > 0.95  # the static background is gone
    on = truth >= 0
    assert len(np.unique(truth[on])) >= 9  # most of the 11 limbs are represented
    assert skel.n_sticks >= 6
    assert adjusted_rand_score(truth[on], skel.labels[on]) > 0.6


@pytest.mark.data
@pytest.mark.slow
def test_learn_bikes(tmp_path, data_dir):
    out = learn(data_dir / "video" / "bikes.mp4", tmp_path / "bikes", method=END_TO_END)
    skel = sf.Skeleton.load(out["model"])
    assert skel.n_sticks >= 2
    assert out["animation"].stat().st_size > 10_000


@pytest.mark.data
def test_learn_from_mocap_file(tmp_path, data_dir):
    path = data_dir / "mocap" / "131_01.bvh"
    P = sf.load(path).n_points
    # This test is about reading, slicing and projecting the file; any segmentation will do.
    labels = np.arange(P) // 3
    out = learn(path, tmp_path / "bvh", method="mi-tree", frames=(0, 60), labels=labels)
    pts = sf.load(out["points"])
    assert pts.n_dims == 2 and pts.n_frames == 60 and pts.n_points == P
    assert pts.meta["projection"]["azimuth"] == 45.0  # the isometric view
    assert "131_01.bvh" in out["report"].read_text(encoding="utf-8")


# ------------------------------------------- a rigid scene before the figure; a video with no figure
@pytest.mark.slow
def test_learn_picks_the_articulated_shot_not_the_rigid_pan(tmp_path):
    """A long pan past a rigid scene with parallax, then a short articulated arm: the arm is learned."""
    from test_track import PAN_FRAMES, _on_arm, write_pan_then_arm

    video = write_pan_then_arm(tmp_path / "pan_arm.avi", pan_frames=60)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # nothing to warn about: the arm moves on its own
        out = learn(video, tmp_path / "o", method=QUICK, max_points=60)
    pts = sf.load(out["points"])
    w = pts.meta["window"]
    assert pts.meta["frame_offset"] >= 60 and w["verdict"] == "independent motion"
    pts.meta["frame_offset"] += PAN_FRAMES - 60  # _on_arm counts arm frames from PAN_FRAMES
    assert _on_arm(pts).mean() > 0.95
    html = out["report"].read_text(encoding="utf-8")
    assert "What it was learned from" in html and 'class="banner"' not in html


def test_cli_learn_says_when_the_video_has_no_independent_motion(tmp_path, capsys):
    from stickfigure.cli import main
    from test_track import write_pan_then_arm

    video = write_pan_then_arm(tmp_path / "pan.avi", pan_frames=40, arm_frames=0)
    assert main(["learn", video, "-o", str(tmp_path / "o"), "-m", QUICK, "--quiet"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("warning: no independent motion found")
    assert "rigid scene seen by the moving camera" in lines[-1]
    html = (tmp_path / "o" / "report.html").read_text(encoding="utf-8")
    assert 'class="banner"' in html and "no independent motion found" in html.lower()
