"""Generic pictures: one frame, frame grids, GIF/MP4 animations (with video overlay), the stick tree."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from PIL import Image  # noqa: E402

import stickfigure as sf  # noqa: E402
from stickfigure import export, plot  # noqa: E402
from test_export import truth_skeleton  # noqa: E402


@pytest.fixture(scope="module")
def figure():
    return sf.synthetic.random_figure(n_sticks=4, frames=30, planar=True, noise=0.005, seed=5)


@pytest.fixture(scope="module")
def skeleton(figure):
    return truth_skeleton(figure)


def _ax():
    return Figure().add_subplot()


def test_draw_frame_colours_sticks_joints(figure, skeleton):
    ax = plot.draw_frame(_ax(), figure, skeleton, frame=3)
    p = export.pose(skeleton, figure)
    colors = plot.stick_colors(skeleton.n_sticks)
    # Points: one per observed point, coloured by its stick.
    pts = ax.collections[2]
    assert pts.get_offsets().shape == (figure.n_points, 2)
    np.testing.assert_allclose(pts.get_facecolors(), colors[skeleton.labels])
    # Sticks: the pose's segments at that frame, each in its stick's colour.
    sticks = ax.collections[1]
    segs = sticks.get_segments()
    assert len(segs) == p.segments.shape[0]
    np.testing.assert_allclose(np.stack(segs), p.segments[:, :, 3])
    np.testing.assert_allclose(sticks.get_colors()[:, :3], colors[p.segment_stick, :3])
    # Joints: white circles at the joints.
    joints = ax.collections[5]
    np.testing.assert_allclose(joints.get_offsets(), p.joints[:, 3])
    assert ax.get_title() == "frame 3"
    assert not ax.yaxis_inverted() and ax.get_aspect() == 1.0  # y up, equal aspect


def test_draw_frame_unassigned_grey_and_missing(figure, skeleton):
    labels = skeleton.labels.copy()
    labels[0] = -1
    sk = sf.Skeleton(method="truth", labels=labels, n_sticks=skeleton.n_sticks, edges=skeleton.edges,
                     joints=skeleton.joints, motions=skeleton.motions, local=skeleton.local)
    occluded, hidden = sf.synthetic.occlude(figure, seed=2)
    f = int(np.argmax(hidden.sum(axis=0)))
    ax = plot.draw_frame(_ax(), occluded, sk, frame=f)
    shown = ax.collections[2]
    assert shown.get_offsets().shape[0] == occluded.observed[:, f].sum()  # missing points are not drawn
    if occluded.observed[0, f]:
        np.testing.assert_allclose(shown.get_facecolors()[0], plot.UNASSIGNED)
    assert ax.collections[3].get_offsets().shape[0] == 0
    # With imputed positions: hollow markers for the missing points, crosses at the truth.
    ax = plot.draw_frame(_ax(), occluded, sk, frame=f, imputed=True, truth=figure.xy)
    holes, crosses = ax.collections[3], ax.collections[4]
    n_missing = int(hidden[:, f].sum())
    n_missing_on_sticks = int((hidden[:, f] & (labels >= 0)).sum())
    assert holes.get_offsets().shape[0] == n_missing_on_sticks  # an unassigned point has no prediction
    assert crosses.get_offsets().shape[0] == n_missing
    assert len(ax.collections[0].get_segments()) == n_missing_on_sticks
    assert np.all(holes.get_facecolors()[:, 3] == 0) if len(holes.get_facecolors()) else True


def test_draw_frame_image_axes_point_down(figure):
    xy = 100 + 50 * figure.xy
    img = figure.copy(xy=xy, joints_true=None, edges_true=None, image_size=(320, 240))
    ax = plot.draw_frame(_ax(), img, frame=0)  # no skeleton: coloured by the true parts
    assert ax.yaxis_inverted()
    assert ax.get_xlim() == (0.0, 320.0) and ax.get_ylim() == (240.0, 0.0)
    colors = plot.stick_colors(4)
    np.testing.assert_allclose(ax.collections[2].get_facecolors(), colors[figure.labels_true])


def test_draw_frame_3d_and_errors(skeleton, figure):
    w3 = sf.synthetic.walker(n_frames=10, project=False, seed=0)
    sk3 = truth_skeleton(w3)
    ax = plot.draw_frame(_ax(), w3, sk3, frame=1, view="isometric")
    assert ax.collections[2].get_offsets().shape == (w3.n_points, 2)
    with pytest.raises(ValueError, match="out of range"):
        plot.draw_frame(_ax(), figure, skeleton, frame=99)
    with pytest.raises(ValueError, match="points"):
        plot.draw_frame(_ax(), w3, skeleton)
    with pytest.raises(ValueError, match="shape"):
        plot.draw_frame(_ax(), figure, skeleton, imputed=np.zeros((2, 2, 2)))
    with pytest.raises(TypeError, match="Trajectories"):
        plot.draw_frame(_ax(), "walk.csv")


def test_plot_frames_png(tmp_path, figure, skeleton):
    fig = plot.plot_frames(figure, skeleton, frames=[0, 10, 20, 29], path=tmp_path / "grid.png", ncols=2,
                           panel_size=2.0, dpi=50)
    assert len(fig.axes) == 4 and [a.get_title() for a in fig.axes] == ["frame 0", "frame 10", "frame 20", "frame 29"]
    im = Image.open(tmp_path / "grid.png")
    assert im.size[0] == 200 and im.size[1] > 150  # 2 columns x 2 in x 50 dpi
    assert np.asarray(im.convert("L")).std() > 5  # something is drawn
    fig = plot.plot_frames(figure.slice(frames=slice(5, 30)), skeleton, n=3)
    assert [a.get_title() for a in fig.axes] == ["frame 5", "frame 17", "frame 29"]  # video frame numbers


def test_follow_centres_each_frame_at_one_scale(tmp_path, figure, skeleton):
    far = figure.with_xy(figure.xy + np.linspace(0, 20, figure.n_frames)[None, :, None])  # drifts away
    fig = plot.plot_frames(far, skeleton, frames=[0, 29], follow=True)
    spans, centres = [], []
    for ax, f in zip(fig.axes, (0, 29)):
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        spans.append((x1 - x0, y1 - y0))
        lo, hi = np.nanmin(far.xy[:, f], axis=0), np.nanmax(far.xy[:, f], axis=0)
        assert np.all(lo > (x0, y0)) and np.all(hi < (x1, y1))  # the figure is in view
        centres.append(((x0 + x1) / 2, (y0 + y1) / 2))
    np.testing.assert_allclose(spans[0], spans[1])
    assert centres[1][0] - centres[0][0] == pytest.approx(20, abs=1.0)
    out = plot.animate(far, skeleton, tmp_path / "follow.gif", follow=True, width=96, dpi=40, max_frames=5)
    assert Image.open(out).n_frames == 5


def test_select_frames():
    assert plot.select_frames(None, 10).tolist() == list(range(10))
    assert plot.select_frames(None, 10, default_count=3).tolist() == [0, 4, 9]
    assert plot.select_frames("2:8:3", 10).tolist() == [2, 5]
    assert plot.select_frames("1,4,-1", 10).tolist() == [1, 4, 9]
    assert plot.select_frames(slice(None, 2), 10).tolist() == [0, 1]
    for bad in ("a:b", "1:2:3:4", "5:5", [10], "0:4:0"):
        with pytest.raises(ValueError):
            plot.select_frames(bad, 10)


def test_animate_gif_frame_count_and_subsampling(tmp_path, figure, skeleton):
    out = plot.animate(figure, skeleton, tmp_path / "a.gif", fps=10, width=160, dpi=50)
    im = Image.open(out)
    assert im.n_frames == figure.n_frames and im.size[0] == 160
    assert im.info["duration"] == 100 and im.info.get("loop") == 0
    # At most 8 frames: every 4th frame of 30 (8 of them), played 4x slower per frame.
    out = plot.animate(figure, skeleton, tmp_path / "b.gif", fps=10, max_frames=8, width=128, dpi=50)
    im = Image.open(out)
    assert im.n_frames == 8 and im.info["duration"] == 400
    out = plot.animate(figure, None, tmp_path / "c.gif", frames="3:9", width=128, dpi=50)
    assert Image.open(out).n_frames == 6


def test_animate_mp4(tmp_path, figure, skeleton):
    import imageio.v3 as iio

    out = plot.animate(figure, skeleton, tmp_path / "a.mp4", width=160, dpi=50)
    frames = iio.imread(out, index=None, extension=".mp4")
    assert frames.shape[0] == figure.n_frames and frames.shape[2] == 160


def test_animate_errors(tmp_path, figure, skeleton):
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        plot.animate(figure, skeleton, tmp_path / "a.avi")
    with pytest.raises(ValueError, match="max_frames"):
        plot.animate(figure, skeleton, tmp_path / "a.gif", max_frames=0)
    with pytest.raises(ValueError, match="empty"):
        plot.animate(figure, skeleton, tmp_path / "a.gif", frames="5:5")
    assert not list(tmp_path.iterdir())  # nothing half-written


def _grey_video(path, n_frames, size=(96, 64)):
    """A video whose frame k is uniformly grey at level 20 + 8 k."""
    import imageio.v2 as imageio

    w, h = size
    with imageio.get_writer(path, fps=10, codec="libx264", quality=10, macro_block_size=16,
                            pixelformat="yuv444p") as wr:
        for k in range(n_frames):
            wr.append_data(np.full((h, w, 3), 20 + 8 * k, np.uint8))


def test_animate_over_video_honours_frame_offset(tmp_path, figure):
    video = tmp_path / "grey.mp4"
    _grey_video(video, 20)
    xy = np.clip(48 + 10 * figure.xy[:, :20], 1, 95)
    traj = sf.Trajectories(xy, image_size=(96, 64), video=str(video), labels_true=figure.labels_true)
    part = traj.slice(frames=slice(6, 12))
    assert part.meta["frame_offset"] == 6
    out = plot.animate(part, None, tmp_path / "over.gif", width=192, dpi=50, point_size=1)
    im = Image.open(out)
    assert im.n_frames == 6
    levels = []
    for k in range(6):
        im.seek(k)
        a = np.asarray(im.convert("L"), float)
        h, w = a.shape
        levels.append(np.median(a[int(0.2 * h):int(0.8 * h), int(0.1 * w):int(0.2 * w)]))
    np.testing.assert_allclose(levels, 20 + 8 * np.arange(6, 12), atol=4)
    # The same with plot_frames, and video=False draws no picture.
    fig = plot.plot_frames(part, frames=[2], video=False)
    assert not fig.axes[0].images
    fig = plot.plot_frames(part, frames=[2])
    assert np.median(np.asarray(fig.axes[0].images[0].get_array())) == pytest.approx(20 + 8 * 8, abs=4)


def test_draw_tree(skeleton):
    ax = plot.draw_tree(_ax(), skeleton)
    nodes = [c for c in ax.collections if c.get_offsets().shape[0] == skeleton.n_sticks]
    assert nodes, "one node per stick"
    np.testing.assert_allclose(nodes[0].get_facecolors(), plot.stick_colors(skeleton.n_sticks))
    labels = sorted(t.get_text() for t in ax.texts)
    assert labels[0].startswith("S0")
    pos = plot._tree_layout(skeleton)
    parents = skeleton.parents()
    for s, p in enumerate(parents):  # each child one level below its parent
        if p >= 0:
            assert pos[s][1] == pos[int(p)][1] - 1
    with pytest.raises(ValueError, match="names"):
        plot.draw_tree(_ax(), skeleton, names=["a"])
