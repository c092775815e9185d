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
