"""The KLT tracker on synthetic videos with known motion, and on the shared clips."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import stickfigure as sf
from stickfigure.track import best_window, track_video

from _video import paste_two_link_arm, write_video

W, H = 240, 180
PATCH = 80  # side of the moving textured square
VEL = np.array([1.3, 0.6])  # pixels per frame
ORIGIN = np.array([30.0, 30.0])  # top-left of the patch in frame 0
CENTRE = np.array([195.0, 45.0])  # a textured disc turning about its centre
RADIUS = 28
OMEGA = np.radians(2.0)  # radians per frame (image coordinates, y down)


def _texture(rng: np.random.Generator, h: int, w: int, blur: float = 1.5) -> np.ndarray:
    """Random blotchy texture with plenty of corners, uint8."""
    t = rng.uniform(0, 255, size=(h, w)).astype(np.float32)
    t = cv2.GaussianBlur(t, (0, 0), blur)
    t = (t - t.min()) / (t.max() - t.min()) * 255
    return t.astype(np.uint8)


def _frames(n: int, seed: int = 0, *, flicker: bool = False, cut_at: int | None = None) -> list[np.ndarray]:
    """A static textured background, a textured square moving at VEL px/frame and a disc turning at OMEGA.

    Both are drawn with sub-pixel accuracy by affine warps of their textures.
    ``flicker`` adds a region on the right whose texture is new noise every frame;
    ``cut_at`` switches to an unrelated scene (a shot cut) from that frame on.
    """
    rng = np.random.default_rng(seed)
    bg = _texture(rng, H, W, blur=1.2)
    bg = (bg.astype(np.float32) * 0.5 + 40).astype(np.uint8)  # dimmer than the patch
    patch = _texture(rng, PATCH, PATCH, blur=2.0)
    disc = _texture(rng, H, W, blur=2.0)
    yy, xx = np.mgrid[:H, :W]
    in_disc = np.hypot(xx - CENTRE[0], yy - CENTRE[1]) <= RADIUS
    other = np.full((H, W), 200, np.uint8)
    other[::7] = 30  # a different scene: stripes
    out = []
    for f in range(n):
        if cut_at is not None and f >= cut_at:
            img = other.copy()
        else:
            img = bg.copy()
            x, y = ORIGIN + VEL * f
            M = np.array([[1.0, 0, x], [0, 1.0, y]])
            warped = cv2.warpAffine(patch, M, (W, H), flags=cv2.INTER_CUBIC, borderValue=0)
            inside = cv2.warpAffine(np.full_like(patch, 255), M, (W, H), flags=cv2.INTER_NEAREST) > 0
            img[inside] = warped[inside]
            R = cv2.getRotationMatrix2D((float(CENTRE[0]), float(CENTRE[1])), -np.degrees(OMEGA * f), 1.0)
            img[in_disc] = cv2.warpAffine(disc, R, (W, H), flags=cv2.INTER_CUBIC)[in_disc]
            if flicker:
                img[100:175, 170:235] = rng.integers(0, 256, size=(75, 65), dtype=np.uint8)
        out.append(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    return out


def _write(path, frames, fourcc: str) -> str:
    return write_video(path, frames, fourcc)


@pytest.fixture(scope="module")
def moving_patch_video(tmp_path_factory):
    """Lossless (FFV1) video, 40 frames."""
    return _write(tmp_path_factory.mktemp("vid") / "patch.avi", _frames(40), "FFV1")


def _undo_motion(traj):
    """Each observation moved back to frame 0 along the square's, the disc's and the background's motion.

    Returns (square, disc, background), each of shape (P, F, 2).
    """
    f = np.arange(traj.n_frames) + traj.meta["frame_offset"]
    square = traj.xy - VEL[None, None, :] * f[None, :, None]
    a = -OMEGA * f  # rotate back
    d = traj.xy - CENTRE
    disc = np.stack([np.cos(a) * d[..., 0] - np.sin(a) * d[..., 1],
                     np.sin(a) * d[..., 0] + np.cos(a) * d[..., 1]], axis=-1) + CENTRE
    return square, disc, traj.xy


def _track_errors(traj):
    """Per track, the largest deviation (pixels) from the best-fitting known motion, shape (P,), and which.

    ``which`` is 0 for the square, 1 for the disc and 2 for the static background
    (a background feature nudged by an object passing over it is not static).
    """
    errs = []
    for back in _undo_motion(traj):
        ref = np.nanmedian(back, axis=1, keepdims=True)
        errs.append(np.nanmax(np.linalg.norm(back - ref, axis=2), axis=1))
    errs = np.stack(errs)
    return errs.min(axis=0), errs.argmin(axis=0)


def _outline_distance(traj, which):
    """Distance (pixels) of each track from its object's outline, in the object's frame-0 position."""
    sq, dc, _ = (np.nanmedian(b, axis=1) for b in _undo_motion(traj))
    d_sq = np.minimum(np.abs(sq - ORIGIN), np.abs(sq - ORIGIN - PATCH)).min(axis=1)
    d_dc = np.abs(np.linalg.norm(dc - CENTRE, axis=1) - RADIUS)
    return np.select([which == 0, which == 1], [d_sq, d_dc], 0.0)


def _patch_tracks(traj, typical: float = 1.0, worst: float = 4.0) -> None:
    """Tracks follow the known motion.

    Tracks whose window lies inside an object, over the whole clip: 90% within
    ``typical / 2`` pixels on the translating square, within ``2 * typical``
    on the turning disc (LK models a window's motion as a translation, so a
    turning texture costs it some accuracy). Features next to an outline mix
    two motions in their window and drift by a pixel or two; every track stays
    within ``worst``.
    """
    err, which = _track_errors(traj)
    inner = _outline_distance(traj, which) > 8  # half the default LK window
    for obj, tol in ((0, 0.5 * typical), (1, 2.0 * typical)):
        sel = inner & (which == obj)
        if sel.sum() >= 3:
            q = np.quantile(err[sel], 0.9)
            assert q < tol, f"90% of inner tracks on object {obj} within {q:.2f} px"
    assert inner.sum() >= 5
    assert np.median(err) < typical, f"median track error {np.median(err):.2f} px"
    assert err.max() < worst, f"worst track error {err.max():.2f} px"


def test_tracks_follow_known_motion(moving_patch_video):
    traj = track_video(moving_patch_video)
    assert isinstance(traj, sf.Trajectories)
    assert traj.n_frames == 40 and traj.n_dims == 2
    assert traj.image_size == (W, H)
    assert traj.frame_rate == pytest.approx(25.0)
    assert traj.meta["frame_offset"] == 0
    assert traj.video is not None and traj.video.endswith("patch.avi")
    # The static background is removed; what is left are points on the patch.
    assert traj.n_points >= 10
    _patch_tracks(traj)
    # ...and the points lie on the square or the disc (in their frame-0 positions).
    err, which = _track_errors(traj)
    assert np.mean(which == 2) < 0.05  # the static background is gone
    sq, dc, _ = (np.nanmedian(b, axis=1) for b in _undo_motion(traj))
    on_square = np.all((sq >= ORIGIN - 2) & (sq <= ORIGIN + PATCH + 2), axis=1)
    on_disc = np.linalg.norm(dc - CENTRE, axis=1) <= RADIUS + 2
    assert np.all(np.select([which == 0, which == 1], [on_square, on_disc], True))
    # Points on the turning disc are followed through its 78-degree turn.
    assert on_disc.sum() >= 5
    assert traj.observed[on_disc].sum(axis=1).max() == 40
    # Features inside the objects found in frame 0 are followed to the end.
    inner = (_outline_distance(traj, which) > 8) & (traj.meta["track_start"] == 0)
    assert inner.sum() >= 10
    assert np.median(traj.observed[inner].sum(axis=1)) == 40


def test_mp4_video_and_progress(tmp_path, capsys):
    path = _write(tmp_path / "patch.mp4", _frames(25, seed=3), "mp4v")
    traj = track_video(path, progress=True)
    assert traj.n_points >= 5
    # A lossy codec blurs and blocks the texture: a few points next to the moving
    # outlines get dragged; the bulk is still sub-pixel.
    _patch_tracks(traj, typical=1.5, worst=np.inf)
    assert np.quantile(_track_errors(traj)[0], 0.95) < 3.0
    assert "tracking" in capsys.readouterr().err


def test_static_background_kept_when_asked(moving_patch_video):
    kept = track_video(moving_patch_video, min_motion=0)
    moved = track_video(moving_patch_video)
    assert kept.n_points > moved.n_points + 20
    assert kept.meta["tracking"]["static"] == 0


def test_figure_on_plain_background_is_not_taken_for_the_camera(tmp_path):
    # The only features are on the moving square: its motion must not be removed as a camera pan.
    rng = np.random.default_rng(6)
    tex = _texture(rng, 30, 30, blur=1.5)
    frames = []
    for f in range(25):
        img = np.full((H, W), 90, np.uint8)
        img[60:90, 20 + 2 * f:50 + 2 * f] = tex
        frames.append(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    traj = track_video(_write(tmp_path / "plain.avi", frames, "FFV1"))
    assert traj.n_points >= 5
    assert np.nanmax(np.ptp(traj.xy[..., 0], axis=1)) > 30  # they move with the square


def test_camera_pan_is_removed(tmp_path):
    # The whole textured scene slides left 1.5 px/frame (a pan); a square moves against it.
    rng = np.random.default_rng(7)
    scene = _texture(rng, H, W + 60, blur=1.5)
    scene = (scene.astype(np.float32) * 0.5 + 40).astype(np.uint8)
    tex = _texture(rng, 40, 40, blur=1.5)
    frames = []
    for f in range(30):
        M = np.array([[1.0, 0, -1.5 * f], [0, 1.0, 0]])
        img = cv2.warpAffine(scene, M, (W, H), flags=cv2.INTER_CUBIC)
        img[70:110, 40 + 3 * f:80 + 3 * f] = tex  # moves right in the image
        frames.append(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    path = _write(tmp_path / "pan.avi", frames, "FFV1")
    traj = track_video(path)
    # What is left moves right with the square, not left with the scene.
    dx = np.nanmedian(np.diff(traj.xy[..., 0], axis=1), axis=1)
    assert traj.n_points >= 5
    assert np.mean(dx > 2) > 0.9
    # Measured in image coordinates instead, the panning background stays.
    still = track_video(path, stabilize=False)
    dx = np.nanmedian(np.diff(still.xy[..., 0], axis=1), axis=1)
    assert np.sum(dx < -1) > 20


def test_lost_points_are_nan_and_never_resurrected(tmp_path):
    # The square leaves the region of interest on the right: its points are lost, as NaN, for good.
    frames = _frames(60, seed=1)
    path = _write(tmp_path / "exit.avi", frames, "FFV1")
    traj = track_video(path, min_length=5, roi=(0, 0, 150, H))
    obs = traj.observed
    assert (~obs).any()
    # One contiguous run of observations per trajectory.
    runs = np.diff(obs.astype(np.int8), axis=1)
    n_starts = (runs == 1).sum(axis=1) + obs[:, 0]
    assert np.all(n_starts == 1)
    # Re-detected features started new trajectories later on.
    assert len(set(traj.meta["track_start"].tolist())) > 1
    _patch_tracks(traj)


def test_forward_backward_check_rejects_bad_tracks(tmp_path):
    path = _write(tmp_path / "flicker.avi", _frames(30, seed=2, flicker=True), "FFV1")

    def in_flicker(traj):
        x, y = traj.xy[..., 0], traj.xy[..., 1]
        with np.errstate(invalid="ignore"):
            return (x >= 170) & (x < 235) & (y >= 100) & (y < 175)

    # The appearance check is off, so the forward-backward check alone decides.
    strict = track_video(path, min_length=1, min_motion=0, min_ncc=-1)
    loose = track_video(path, min_length=1, min_motion=0, min_ncc=-1, fb_threshold=1e6)
    # Independent noise every frame: a feature there rarely survives the check for long...
    run_strict = in_flicker(strict).sum(axis=1)
    run_strict = run_strict[run_strict > 0]
    assert np.mean(run_strict > 3) < 0.1
    # ...while without it LK happily "tracks" the noise.
    run_loose = in_flicker(loose).sum(axis=1)
    run_loose = run_loose[run_loose > 0]
    assert np.mean(run_loose > 3) > 0.5
    assert strict.meta["tracking"]["fb_lost"] > loose.meta["tracking"]["fb_lost"]
    # The appearance check catches them too.
    assert (in_flicker(track_video(path, min_length=1, min_motion=0))).sum(axis=1).max() <= 2
    # Tracks on the real objects are unaffected.
    patch = track_video(path)
    ok = ~np.any(in_flicker(patch), axis=1)
    assert ok.sum() >= 10
    _patch_tracks(patch.slice(points=ok))


def test_roi_and_frame_range(moving_patch_video):
    roi = (20, 20, 110, 90)
    traj = track_video(moving_patch_video, roi=roi, start=5, stop=30, min_length=5)
    assert traj.n_frames == 25
    assert traj.meta["frame_offset"] == 5
    assert traj.meta["roi"] == list(roi)
    x, y = traj.xy[..., 0], traj.xy[..., 1]
    obs = traj.observed
    assert np.all((x[obs] >= 20) & (x[obs] <= 129) & (y[obs] >= 20) & (y[obs] <= 109))
    # Positions are in full-frame coordinates at absolute frame numbers.
    _patch_tracks(traj)
    # Frames past the end of the video are simply not there.
    tail = track_video(moving_patch_video, start=30, stop=1000, min_length=2)
    assert tail.n_frames == 10


def test_shot_cut_ends_every_track(tmp_path):
    path = _write(tmp_path / "cut.avi", _frames(40, seed=4, cut_at=22), "FFV1")
    traj = track_video(path, min_length=3, min_motion=0)
    assert traj.meta["shots"] == [0, 22]
    assert track_video(path, start=10, min_length=3, min_motion=0).meta["shots"] == [10, 22]
    obs = traj.observed
    assert not np.any(obs[:, 21] & obs[:, 22])  # no trajectory crosses the cut
    assert np.all(np.isin(traj.meta["track_shot"], [0, 1]))


@pytest.mark.parametrize("content", [b"", b"this is not a video\n" * 50])
def test_unreadable_or_empty_video(tmp_path, content):
    p = tmp_path / "bad.mp4"
    p.write_bytes(content)
    with pytest.raises(ValueError, match="bad.mp4") as err:
        track_video(p)
    assert "\n" not in str(err.value)


def test_bad_arguments(tmp_path, moving_patch_video):
    with pytest.raises(ValueError, match="not found"):
        track_video(tmp_path / "missing.mp4")
    with pytest.raises(ValueError, match="directory"):
        track_video(tmp_path)
    with pytest.raises(ValueError, match="roi"):
        track_video(moving_patch_video, roi=(500, 500, 10, 10))
    with pytest.raises(ValueError, match="roi"):
        track_video(moving_patch_video, roi="everything")
    with pytest.raises(ValueError, match="beyond the end"):
        track_video(moving_patch_video, start=100)
    with pytest.raises(ValueError, match="stop"):
        track_video(moving_patch_video, start=5, stop=6)
    with pytest.raises(ValueError, match="survived"):
        track_video(moving_patch_video, min_motion=500)


def test_one_frame_video_is_an_error(tmp_path):
    path = _write(tmp_path / "one.avi", _frames(1), "FFV1")
    with pytest.raises(ValueError, match="only 1 frame"):
        track_video(path)


# ----------------------------------------------------------------- best_window
def _coverage_traj(pattern: np.ndarray, shots=None) -> sf.Trajectories:
    P, F = pattern.shape
    rng = np.random.default_rng(0)
    xy = rng.normal(size=(P, F, 2)) + np.c_[np.arange(P) * 3.0, np.full(P, 100.0)][:, None, :]
    xy[~pattern] = np.nan
    meta = {"shots": shots} if shots else {}
    return sf.Trajectories(xy, image_size=(200, 200), meta=meta)


def test_best_window_picks_most_observations():
    F = 100
    obs = np.zeros((40, F), bool)
    obs[:30, 10:60] = True  # 30 points x 50 frames = 1500
    obs[30:, :] = True  # 10 points everywhere (they count in every window)
    obs[:5, 60:70] = True
    traj = _coverage_traj(obs)
    win = best_window(traj, coverage=1.0, min_points=5, max_points=None)
    assert (win.meta["window"]["start"], win.meta["window"]["stop"]) == (10, 60)
    assert win.n_points == 40 and win.n_frames == 50
    assert win.meta["frame_offset"] == 10
    assert win.missing_fraction == 0.0
    # Choosing again from the choice changes nothing.
    again = best_window(win, coverage=1.0, min_points=5, max_points=None)
    assert again.n_points == win.n_points and again.n_frames == win.n_frames


def test_best_window_complete_data_is_unchanged(small_figure):
    win = best_window(small_figure, max_points=None)
    assert win.n_points == small_figure.n_points and win.n_frames == small_figure.n_frames
    np.testing.assert_array_equal(win.xy, small_figure.xy)


def test_best_window_respects_shots_and_max_points():
    F = 80
    obs = np.ones((60, F), bool)
    traj = _coverage_traj(obs, shots=[0, 30])
    win = best_window(traj, max_points=25)
    w = win.meta["window"]
    assert w["start"] >= 30 and w["stop"] == 80  # the longer shot
    assert win.n_points == 25
    # Shot starts are video frame numbers: a slice starting inside the first shot still sees the cut.
    part = best_window(traj.slice(frames=slice(20, 80)), max_points=None)
    assert part.meta["frame_offset"] >= 30
    # Spread: points 0..59 lie along a line every 3 px; the kept ones cover it.
    m = np.nanmean(win.xy, axis=1)
    assert np.ptp(m[:, 0]) > 150
    assert np.min(np.diff(np.sort(m[:, 0]))) > 4


def test_best_window_bad_input(small_figure):
    with pytest.raises(ValueError, match="coverage"):
        best_window(small_figure, coverage=0)
    with pytest.raises(TypeError):
        best_window(small_figure.xy)


# ------------------------------------------------------------------ real clips
@pytest.mark.data
def test_bikes(data_dir):
    traj = track_video(data_dir / "video" / "bikes.mp4", stop=100)
    assert traj.image_size == (640, 272)
    assert traj.n_frames == 100
    # bikes.mp4 is edited: cuts after frames 29 and 75.
    assert traj.meta["shots"] == [0, 30, 76]
    assert traj.n_points > 50
    win = best_window(traj)
    assert win.n_points >= 10 and win.n_frames >= 10
    assert win.missing_fraction < 0.2
    # Frames 30-75: a camera moving past parked cars. Most tracks are there, but one rigid scene explains them,
    # so that window is not what a skeleton is learned from.
    street = [c for c in win.meta["window"]["candidates"] if c["first"] >= 30 and c["last"] < 76]
    assert len(street) == 1 and not street[0]["chosen"]
    assert street[0]["points"] >= 50 and street[0]["scene_points"] >= 0.9 * street[0]["points"]


@pytest.mark.data
@pytest.mark.slow
def test_clip_flies(data_dir):
    traj = track_video(data_dir / "video" / "clip.mp4")
    assert traj.n_frames == 1500 and traj.image_size == (1024, 1024)
    assert traj.meta["shots"] == [0]
    assert traj.n_points >= 30
    win = best_window(traj)
    assert win.n_points >= 10 and win.n_frames >= 300
    assert win.missing_fraction < 0.2


# ------------------------------------------- choosing independent motion over a rigid scene
PAN_FRAMES, ARM_FRAMES = 100, 50
VW, VH = 320, 240
ARM_SHOULDER = np.array([120.0, 120.0])


def _arm_pose(f):
    """Angles of the two limbs of the arm shot (radians, image coordinates)."""
    a1 = np.radians(-10 + 35 * np.sin(2 * np.pi * f / ARM_FRAMES))
    return a1, a1 + np.radians(50 * np.sin(2 * np.pi * f / ARM_FRAMES + 1.0))


def _pan_then_arm_frames(seed: int = 0, pan_frames: int = PAN_FRAMES, arm_frames: int = ARM_FRAMES):
    """A camera panning past a rigid scene with depth, a cut, then an articulated 'arm' in front of a still camera.

    The pan shot has three depth layers (horizontal bands) moving at 0.6, 1.6
    and 3.2 px/frame with a slow common tilt: one rigid scene seen by a
    translating camera, so its layers move differently (parallax) and no single
    homography removes them. It is long and richly textured: the most tracked
    points times frames. The arm shot is shorter: a textured upper limb turning
    about a fixed shoulder and a forearm turning about the elbow, over a plain
    dark background.
    """
    rng = np.random.default_rng(seed)
    speeds = (0.6, 1.6, 3.2)
    bands = [(0, 80), (80, 160), (160, 240)]
    big = [_texture(rng, VH, VW + int(s * pan_frames) + 20, blur=1.3) for s in speeds]
    tex = [_texture(rng, 24, 90, blur=1.6) for _ in range(2)]
    out = []
    for f in range(pan_frames):
        img = np.zeros((VH, VW), np.uint8)
        for (y0, y1), s, t in zip(bands, speeds, big):
            # Layer content at x + s f, y - 0.1 s f (the camera moves right and slightly up): sub-pixel warp.
            M = np.array([[1.0, 0, -s * f], [0, 1.0, 0.1 * s * f]])
            img[y0:y1] = cv2.warpAffine(t, M, (t.shape[1], VH), flags=cv2.INTER_CUBIC)[y0:y1, :VW]
        out.append(img)
    for f in range(arm_frames):
        img = np.full((VH, VW), 35, np.uint8)
        paste_two_link_arm(img, tex, ARM_SHOULDER, *_arm_pose(f))
        out.append(img)
    return [cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) for im in out]


def write_pan_then_arm(path, **kw) -> str:
    return write_video(path, _pan_then_arm_frames(**kw))


@pytest.fixture(scope="module")
def pan_then_arm_tracks(tmp_path_factory):
    return track_video(write_pan_then_arm(tmp_path_factory.mktemp("pan") / "pan_arm.avi"))


def _on_arm(win):
    """Per point of a window in the arm shot: does it follow one of the two limbs (within 15 px of its axis)?"""
    f = np.arange(win.n_frames) + win.meta["frame_offset"] - PAN_FRAMES
    a1, a2 = _arm_pose(f)
    elbow = ARM_SHOULDER + 80 * np.stack([np.cos(a1), np.sin(a1)], axis=1)
    on = np.zeros(win.n_points, bool)
    for origin, ang in ((ARM_SHOULDER, a1), (elbow, a2)):
        d = win.xy - origin
        along = d[..., 0] * np.cos(ang) + d[..., 1] * np.sin(ang)
        across = -d[..., 0] * np.sin(ang) + d[..., 1] * np.cos(ang)
        with np.errstate(invalid="ignore"):
            inside = (along > -3) & (along < 93) & (np.abs(across) < 15)
        on |= np.nanmean(np.where(win.observed, inside, np.nan), axis=1) > 0.9
    return on


def test_tracker_records_camera_motion(pan_then_arm_tracks):
    tr = pan_then_arm_tracks
    assert tr.meta["shots"] == [0, PAN_FRAMES]
    cam = np.asarray(tr.meta["camera"]["shift_px"])
    assert cam.shape == (tr.n_frames,) and cam[0] == 0
    # The pan moves (its far layer alone covers a third of the frame); the arm shot's camera is still.
    assert np.median(cam[1:PAN_FRAMES]) > 0.3
    assert np.all(cam[PAN_FRAMES:] == 0)


def test_best_window_prefers_independent_motion_to_a_rigid_scene(pan_then_arm_tracks):
    tr = pan_then_arm_tracks
    # Counting points alone picks the long, textured pan (what best_window did before):
    old = best_window(tr, select="coverage")
    assert old.meta["window"]["stop"] <= PAN_FRAMES
    assert old.n_points > 40
    win = best_window(tr)
    w = win.meta["window"]
    assert win.meta["frame_offset"] >= PAN_FRAMES, w["message"]  # the arm's shot
    assert w["verdict"] == "independent motion"
    assert _on_arm(win).mean() > 0.95 and win.n_points >= 20
    # The pan's candidate: its points are the rigid scene, almost none move on their own.
    pan = [c for c in w["candidates"] if c["last"] < PAN_FRAMES]
    assert len(pan) == 1 and not pan[0]["chosen"]
    assert pan[0]["camera_px"] > 20
    assert pan[0]["independent"] <= 0.05 * pan[0]["points"]


def test_best_window_says_when_nothing_moves_on_its_own(pan_then_arm_tracks):
    pan = pan_then_arm_tracks.slice(frames=slice(0, PAN_FRAMES))
    win = best_window(pan)
    w = win.meta["window"]
    assert w["verdict"] == "no independent motion"
    assert "rigid scene" in w["message"] and "moving camera" in w["message"]
    assert win.n_points > 40  # still the best-covered window, for a user who wants it anyway


def test_rigid_residuals_explain_parallax_not_independent_motion():
    """A rigid 3D scene under a translating, turning affine camera is one rank-4 motion; a swinging limb is not."""
    from stickfigure.track import _rigid_residuals

    rng = np.random.default_rng(1)
    F = 40
    X = rng.uniform(-100, 100, size=(60, 3))  # depth spread as wide as the image: strong parallax
    t = np.linspace(0, 1, F)
    ang = 0.8 * t  # the camera turns about the vertical while it translates
    R = np.stack([np.stack([np.cos(ang), np.zeros(F), np.sin(ang)], 1), np.tile([0.0, 1.0, 0.0], (F, 1))], 1)
    scene = np.einsum("fij,pj->pfi", R, X) + np.stack([160 + 60 * t, 120 - 10 * t], 1)
    theta = np.radians(40) * np.sin(2 * np.pi * t)  # a limb swinging about a fixed point
    off = np.c_[rng.uniform(20, 80, 12), rng.uniform(-8, 8, 12)]  # along and across the limb
    c, s = np.cos(theta), np.sin(theta)
    limb = np.stack([200 + off[:, :1] * c - off[:, 1:] * s, 100 + off[:, :1] * s + off[:, 1:] * c], axis=-1)
    xy = np.concatenate([scene, limb]) + rng.normal(scale=0.2, size=(72, F, 2))
    xy[:5, :6] = np.nan  # some points missing at the start
    res = _rigid_residuals(xy, 4, 1.0, np.random.default_rng(0))
    assert np.all(res[:60] < 1.0)
    assert np.all(res[60:] > 3.0)


def test_best_window_verdict_one_rigid_body_or_several():
    """Points of one body moving in the image: 'one rigid body'; two bodies moving apart: independent motion."""
    rng = np.random.default_rng(3)
    F = 50
    f = np.arange(F)

    def body(n, centre, vel, omega, scale_rate):
        local = rng.uniform(-25, 25, size=(n, 2))
        ang, sc = omega * f, 1 + scale_rate * f
        R = np.stack([np.stack([np.cos(ang), -np.sin(ang)], 1), np.stack([np.sin(ang), np.cos(ang)], 1)], 1)
        return (np.einsum("fij,pj->pfi", R * sc[:, None, None], local)
                + (np.asarray(centre) + np.outer(f, vel))[None])

    car = body(30, (100, 100), (2.0, 0.5), 0.01, 0.004)
    other = body(30, (250, 150), (-1.0, 1.5), -0.02, 0.0)
    for bodies, verdict in (([car], "one rigid body"), ([car, other], "independent motion")):
        xy = np.concatenate(bodies) + rng.normal(scale=0.3, size=(30 * len(bodies), F, 2))
        xy[::7, :5] = np.nan  # tracks that start late
        tr = sf.Trajectories(xy, image_size=(400, 300))
        w = best_window(tr).meta["window"]
        assert w["verdict"] == verdict, w["message"]
    assert "no articulated motion" in best_window(sf.Trajectories(car, image_size=(400, 300))).meta["window"]["message"]
