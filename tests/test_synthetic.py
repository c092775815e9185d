"""Synthetic figures: rigidity, joints on both sticks, occlusion protocol."""

import numpy as np
import pytest

import stickfigure as sf


def _rigid_3d(t):
    lab = t.labels_true
    for s in np.unique(lab):
        q = t.xy[lab == s]
        d = np.linalg.norm(q[:, None] - q[None], axis=-1)
        assert np.ptp(d, axis=2).max() < 1e-9


def test_walker_is_rigid_and_joints_lie_on_both_sticks():
    w = sf.synthetic.walker(noise=0.0, seed=0, project=False)
    _rigid_3d(w)
    for e, (a, b) in enumerate(w.edges_true):
        for s in (a, b):
            d = np.linalg.norm(w.xy[w.labels_true == s] - w.joints_true[e][None], axis=-1)
            assert np.ptp(d, axis=1).max() < 1e-9


@pytest.mark.parametrize("planar", [False, True])
def test_random_figure_ground_truth(planar):
    t = sf.synthetic.random_figure(n_sticks=6, frames=40, planar=planar, noise=0.0, seed=3)
    assert t.n_dims == 2 and t.n_parts_true == 6
    assert len(t.edges_true) == 5  # a tree
    assert t.joints_true.shape == (5, 40, 2)
    counts = np.bincount(t.labels_true)
    assert counts.min() >= 5 and counts.max() <= 9
    # A stick's 2D trajectories have rank <= 4 (affine camera), and are not collinear.
    for s in range(6):
        W = t.xy[t.labels_true == s].transpose(1, 2, 0).reshape(-1, counts[s])
        sv = np.linalg.svd(W - W.mean(axis=1, keepdims=True), compute_uv=False)
        assert sv[3 if not planar else 2] < 1e-8 * sv[0]
        assert sv[1] > 1e-3 * sv[0]


def test_same_seed_same_figure():
    a = sf.synthetic.random_figure(4, seed=11)
    b = sf.synthetic.random_figure(4, seed=11)
    np.testing.assert_array_equal(a.xy, b.xy)
    assert a.edges_true == b.edges_true


def test_arm_matches_meeds_setup():
    a = sf.synthetic.arm()
    assert a.shape == (32, 33, 2) and a.edges_true == [(0, 1), (1, 2), (2, 3)]
    # Straight at start and end, folded in the middle.
    ext = [np.ptp(a.xy[:, f], axis=0).max() for f in (0, 16, 32)]
    assert ext[1] < 0.6 * ext[0] and ext[2] > 0.9 * ext[0]


def test_occlude_hides_ten_to_fifteen_percent():
    t = sf.synthetic.random_figure(5, frames=100, seed=2)
    occ, hidden = sf.synthetic.occlude(t, seed=0)
    assert 0.10 <= hidden.mean() <= 0.15
    assert np.isnan(occ.xy[hidden]).all()
    np.testing.assert_array_equal(occ.xy[~hidden], t.xy[~hidden])
    # The bar sweeps left to right: early frames lose points on the left.
    bar = hidden.copy()
    f_early, f_late = 10, 90
    if bar[:, f_early].any() and bar[:, f_late].any():
        assert t.xy[bar[:, f_early], f_early, 0].mean() < t.xy[bar[:, f_late], f_late, 0].mean()
