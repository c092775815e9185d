"""The data model: validation, slicing, splitting, projection."""

import numpy as np
import pytest

import stickfigure as sf
from stickfigure.trajectories import ISOMETRIC_VIEW, view_rotation


def test_shape_and_properties():
    xy = np.random.default_rng(0).normal(size=(4, 10, 2))
    xy[1, 3] = np.nan
    t = sf.Trajectories(xy, names=list("abcd"), frame_rate=30)
    assert t.shape == (4, 10, 2) and t.n_points == 4 and t.n_frames == 10 and t.n_dims == 2
    assert t.observed.shape == (4, 10) and not t.observed[1, 3]
    assert t.missing_fraction == pytest.approx(1 / 40)
    assert "4 points x 10 frames" in repr(t)


@pytest.mark.parametrize(
    "xy, match",
    [
        (np.zeros((4, 10)), "shape"),
        (np.zeros((4, 10, 4)), "D = 2 or 3"),
        (np.zeros((4, 1, 2)), "at least 2 frames"),
        (np.zeros((0, 5, 2)), "no points"),
        (np.full((2, 5, 2), np.inf), "infinite"),
    ],
)
def test_bad_input_names_the_problem(xy, match):
    with pytest.raises(ValueError, match=match):
        sf.Trajectories(xy)


def test_never_observed_point_is_rejected_unless_allowed():
    xy = np.zeros((3, 5, 2))
    xy[2] = np.nan
    with pytest.raises(ValueError, match="never observed: 2"):
        sf.Trajectories(xy)
    assert sf.Trajectories(xy, allow_unobserved=True).n_points == 3


def test_partial_nan_hides_whole_observation():
    xy = np.zeros((2, 4, 2))
    xy[0, 1, 0] = np.nan
    t = sf.Trajectories(xy)
    assert np.isnan(t.xy[0, 1]).all()


def test_ground_truth_validation():
    xy = np.zeros((3, 4, 2))
    with pytest.raises(ValueError, match="labels_true"):
        sf.Trajectories(xy, labels_true=[0, 1])
    with pytest.raises(ValueError, match="edges_true"):
        sf.Trajectories(xy, labels_true=[0, 1, 1], edges_true=[(0, 5)])
    with pytest.raises(ValueError, match="joints_true"):
        sf.Trajectories(xy, labels_true=[0, 1, 1], edges_true=[(0, 1)], joints_true=np.zeros((2, 4, 2)))


def test_slice_and_split_keep_ground_truth(small_figure):
    t = small_figure
    train, test = t.split(0.7)
    assert train.n_frames + test.n_frames == t.n_frames
    assert train.n_frames == round(0.7 * t.n_frames)
    np.testing.assert_array_equal(test.xy, t.xy[:, train.n_frames:])
    np.testing.assert_array_equal(train.joints_true, t.joints_true[:, : train.n_frames])
    sub = t.slice(points=[0, 2, 4])
    np.testing.assert_array_equal(sub.labels_true, t.labels_true[[0, 2, 4]])
    assert sub.edges_true == t.edges_true
    with pytest.raises(ValueError, match="at least 2 frames"):
        t.slice(frames=[0])


def test_view_rotation_is_orthonormal_and_isometric_is_symmetric():
    R = view_rotation(*ISOMETRIC_VIEW)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # The isometric camera looks along (1, 1, 1): the three axes project with equal length.
    lens = np.linalg.norm(R[:2], axis=0)
    np.testing.assert_allclose(lens, lens[0], rtol=1e-9)


def test_project_up_axis_stays_up():
    xy = np.zeros((2, 3, 3))
    xy[1, :, 2] = 1.0  # point 1 is above point 0 (z up)
    p = sf.Trajectories(xy, up_axis=2).project("front")
    assert p.n_dims == 2 and p.xy[1, 0, 1] == pytest.approx(1.0) and p.xy[1, 0, 0] == pytest.approx(0.0)
    xy_y = xy[..., [0, 2, 1]]  # same scene, y up
    q = sf.Trajectories(xy_y, up_axis=1).project("front")
    np.testing.assert_allclose(q.xy, p.xy, atol=1e-12)
    with pytest.raises(ValueError, match="3D"):
        p.project()
    with pytest.raises(ValueError, match="view"):
        sf.Trajectories(xy).project("nowhere")


def test_missing_at_random_fraction():
    t = sf.synthetic.random_figure(3, frames=50, seed=1)
    m, hidden = t.missing_at_random(0.25, random_state=0)
    assert hidden.mean() == pytest.approx(0.25, abs=0.01)
    assert np.isnan(m.xy[hidden]).all() and not np.isnan(m.xy[~hidden]).any()


def test_project_pinhole_camera():
    rng = np.random.default_rng(0)
    xy = rng.normal(size=(6, 20, 3))
    t = sf.Trajectories(xy, up_axis=2, labels_true=[0, 0, 0, 1, 1, 2], edges_true=[(0, 1), (1, 2)],
                        joints_true=xy[:2] + 0.1)
    ortho = t.project((30.0, 20.0), scale=2.0)
    # A distant camera approaches the scaled-orthographic image of the points about the centre.
    far = t.project((30.0, 20.0), scale=2.0, distance=1e7)
    centre = 2.0 * (np.nanmean(xy.reshape(-1, 3), axis=0) @ view_rotation(30.0, 20.0, 2)[:2].T)
    np.testing.assert_allclose(far.xy, ortho.xy - centre, atol=1e-5)
    np.testing.assert_allclose(far.joints_true, ortho.joints_true - centre, atol=1e-5)
    assert far.meta["projection"]["distance"] == 1e7 and "distance" not in ortho.meta["projection"]
    # Near: a point's image is its orthographic one times distance / depth.
    near = t.project((30.0, 20.0), scale=2.0, distance=10.0)
    R = view_rotation(30.0, 20.0, 2)
    Y = (xy - np.nanmean(xy.reshape(-1, 3), axis=0)) @ R.T
    np.testing.assert_allclose(near.xy, 2.0 * Y[..., :2] * (10.0 / (10.0 - Y[..., 2]))[..., None], rtol=1e-12)
    # Nearer the camera is drawn larger.
    d = Y[..., 2].ravel()
    grow = (np.linalg.norm(near.xy.reshape(-1, 2), axis=1) / np.linalg.norm(2.0 * Y[..., :2].reshape(-1, 2), axis=1))
    assert grow[np.argmax(d)] > 1 > grow[np.argmin(d)]
    mag = 10.0 / (10.0 - d)
    assert near.meta["projection"]["magnification"] == pytest.approx([mag.min(), mag.max()], rel=1e-12)
    # Missing entries stay missing.
    xy2 = xy.copy()
    xy2[1, 3] = np.nan
    assert np.isnan(sf.Trajectories(xy2).project(distance=10.0).xy[1, 3]).all()


def test_project_pinhole_camera_must_stand_clear_of_the_scene():
    xy = np.zeros((3, 4, 3))
    xy[0, :, 0] = 5.0
    t = sf.Trajectories(xy, up_axis=2)
    with pytest.raises(ValueError, match="inside the scene"):
        t.project("side", distance=2.0)  # the side camera looks along +x; a point is 3.3 nearer
    for bad in (0.0, -1.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="distance must be a positive finite number"):
            t.project("side", distance=bad)
    assert np.isfinite(t.project("side", distance=4.0).xy).all()
