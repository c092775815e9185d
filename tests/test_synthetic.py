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


def _singular_values(xy):
    X = np.concatenate([xy[..., 0], xy[..., 1]], axis=1).T  # (2F, P)
    return np.linalg.svd(X - X.mean(axis=1, keepdims=True), compute_uv=False)


def test_rigid_bodies_are_affine_bodies_and_perspective_breaks_that():
    tr = sf.synthetic.rigid_bodies(3, frames=40, noise=0.0, seed=1, points_per_body=12)
    assert tr.shape == (36, 40, 2) and tr.n_parts_true == 3 and tr.edges_true == []
    for b in range(3):
        s = _singular_values(tr.xy[tr.labels_true == b])
        assert s[3] < 1e-9 * s[0] and s[2] > 1e-3 * s[0]  # exactly rank 3 under the affine camera
    # the bodies move independently: together they need more than one body's rank
    assert _singular_values(tr.xy)[6] > 1e-3 * _singular_values(tr.xy)[0]
    pe = sf.synthetic.rigid_bodies(3, frames=40, noise=0.0, seed=1, points_per_body=12, perspective=0.2)
    s = _singular_values(pe.xy[pe.labels_true == 0])
    assert s[3] > 1e-4 * s[0]
    noisy = sf.synthetic.rigid_bodies(2, frames=30, noise=0.02, seed=0)
    assert noisy.meta["noise_std"] > 0
    np.testing.assert_array_equal(noisy.xy, sf.synthetic.rigid_bodies(2, frames=30, noise=0.02, seed=0).xy)


def test_rigid_bodies_errors():
    with pytest.raises(ValueError, match="perspective"):
        sf.synthetic.rigid_bodies(2, perspective=0.9)
    with pytest.raises(ValueError, match="frames"):
        sf.synthetic.rigid_bodies(2, frames=1)
    with pytest.raises(ValueError, match="points_per_body"):
        sf.synthetic.rigid_bodies(2, points_per_body=(5, 3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_marker_gaps_hide_one_long_run_on_each_chosen_point(seed):
    traj = sf.synthetic.walker(n_frames=120, seed=seed)
    out, hidden = sf.synthetic.marker_gaps(traj, 4, seed=seed, min_fraction=0.25, max_fraction=0.5)
    assert hidden.shape == (traj.n_points, traj.n_frames)
    gapped = np.flatnonzero(hidden.any(axis=1))
    assert gapped.size == 4
    for p in gapped:
        run = np.flatnonzero(hidden[p])
        assert np.all(np.diff(run) == 1)  # one contiguous run
        assert 0.25 * traj.n_frames - 1 <= run.size <= 0.5 * traj.n_frames + 1
    assert np.all(np.isnan(out.xy[hidden])) and np.array_equal(out.observed, traj.observed & ~hidden)
    _, hidden2 = sf.synthetic.marker_gaps(traj, 4, seed=seed, min_fraction=0.25, max_fraction=0.5)
    assert np.array_equal(hidden, hidden2)  # the same seed, the same gaps
    assert out.meta["gaps"]["n_points"] == 4


def test_marker_gaps_name_bad_arguments():
    traj = sf.synthetic.walker(n_frames=30, seed=0)
    with pytest.raises(ValueError, match="at most"):
        sf.synthetic.marker_gaps(traj, traj.n_points + 1, seed=0)
    with pytest.raises(ValueError, match="min_fraction"):
        sf.synthetic.marker_gaps(traj, 2, seed=0, min_fraction=0.7, max_fraction=0.5)
    with pytest.raises(ValueError, match="n_points"):
        sf.synthetic.marker_gaps(traj, 0, seed=0)
    with pytest.raises(TypeError, match="Trajectories"):
        sf.synthetic.marker_gaps(traj.xy, 2, seed=0)


def test_skin_motion_moves_every_coordinate_by_sd_and_keeps_the_truth():
    traj = sf.synthetic.walker(n_frames=200, seed=0, project=False)
    xy = traj.xy.copy()
    xy[2, 50:60] = np.nan
    traj = traj.with_xy(xy)
    out = sf.synthetic.skin_motion(traj, 0.05, seed=3)
    d = out.xy - traj.xy
    ok = traj.observed
    assert np.array_equal(out.observed, ok)  # missing stays missing
    full = ok.all(axis=1)
    # Each coordinate's displacement has s.d. sd over the frames (exactly, where the point is always seen).
    np.testing.assert_allclose(d[full].std(axis=1), 0.05, rtol=1e-9)
    assert np.array_equal(out.labels_true, traj.labels_true)
    assert np.array_equal(out.edges_true, traj.edges_true)
    np.testing.assert_array_equal(out.joints_true, traj.joints_true)  # the bones do not move
    assert out.meta["skin_motion"] == {"sd": 0.05, "timescale": 12.0}
    again = sf.synthetic.skin_motion(traj, 0.05, seed=3)
    np.testing.assert_array_equal(again.xy, out.xy)  # the same seed, the same motion
    assert not np.allclose(sf.synthetic.skin_motion(traj, 0.05, seed=4).xy[full], out.xy[full])
    np.testing.assert_array_equal(sf.synthetic.skin_motion(traj, 0.0, seed=3).xy, traj.xy)
    # Each point its own amplitude: the same draw, scaled point by point.
    sd = np.linspace(0.0, 0.1, traj.n_points)
    each = sf.synthetic.skin_motion(traj, sd, seed=3)
    np.testing.assert_allclose(each.xy - traj.xy, d * (sd / 0.05)[:, None, None], atol=1e-12)
    assert each.meta["skin_motion"]["sd"] == pytest.approx(sd.tolist())


@pytest.mark.parametrize("timescale", [4.0, 12.0])
def test_skin_motion_is_smooth_on_its_timescale(timescale):
    # A Gaussian kernel of s.d. T makes an autocorrelation exp(-lag^2 / 4T^2): one half at 1.67 T.
    traj = sf.Trajectories(xy=np.zeros((3, 20000, 2)))
    d = sf.synthetic.skin_motion(traj, 1.0, seed=0, timescale=timescale).xy
    x = d - d.mean(axis=1, keepdims=True)

    def autocorrelation(lag):
        return float(np.mean(x[:, lag:] * x[:, :-lag]) / np.mean(x * x))

    half = 2.0 * np.sqrt(np.log(2.0)) * timescale
    assert autocorrelation(int(round(half))) == pytest.approx(0.5, abs=0.08)
    assert autocorrelation(1) > 0.95
    assert autocorrelation(int(round(4 * timescale))) < 0.1


def test_skin_motion_names_bad_arguments():
    traj = sf.synthetic.walker(n_frames=30, seed=0)
    with pytest.raises(ValueError, match="sd"):
        sf.synthetic.skin_motion(traj, -1.0)
    with pytest.raises(ValueError, match="shape"):
        sf.synthetic.skin_motion(traj, np.ones(traj.n_points + 1))
    with pytest.raises(ValueError, match="sd"):
        sf.synthetic.skin_motion(traj, np.full(traj.n_points, np.nan))
    with pytest.raises(ValueError, match="timescale"):
        sf.synthetic.skin_motion(traj, 1.0, timescale=0)
    with pytest.raises(ValueError, match="2 frames"):
        sf.synthetic.skin_motion(sf.Trajectories(xy=np.zeros((3, 1, 2))), 1.0)
    with pytest.raises(TypeError, match="Trajectories"):
        sf.synthetic.skin_motion(traj.xy, 1.0)


@pytest.mark.parametrize("n_limbs", [1, 4, 6])
def test_star_ground_truth(n_limbs):
    t = sf.synthetic.star(n_limbs=n_limbs, frames=40, noise=0.0, seed=2, hub_points=8, limb_points=5)
    assert t.n_parts_true == n_limbs + 1 and t.edges_true == [(0, k) for k in range(1, n_limbs + 1)]
    assert np.bincount(t.labels_true).tolist() == [8] + [5] * n_limbs
    assert t.joints_true.shape == (n_limbs, 40, 2)
    # Each joint moves rigidly with both its sticks: added to either stick's points, the
    # 2D trajectories keep the rank of one rigid body under an affine camera (<= 4 centred: 3).
    for e, (a, b) in enumerate(t.edges_true):
        for s in (a, b):
            q = np.concatenate([t.xy[t.labels_true == s], t.joints_true[e][None]])
            W = q.transpose(1, 2, 0).reshape(-1, q.shape[0])
            sv = np.linalg.svd(W - W.mean(axis=1, keepdims=True), compute_uv=False)
            assert sv[3] < 1e-8 * sv[0]
    # No two joints coincide on the hub.
    d = np.linalg.norm(t.joints_true[:, None] - t.joints_true[None], axis=-1).min(axis=-1)
    assert n_limbs == 1 or d[~np.eye(n_limbs, dtype=bool)].min() > 0.01


def test_star_names_bad_arguments():
    with pytest.raises(ValueError, match="n_limbs"):
        sf.synthetic.star(n_limbs=0)
    with pytest.raises(ValueError, match="hub_points"):
        sf.synthetic.star(hub_points=0)
    with pytest.raises(ValueError, match="frames"):
        sf.synthetic.star(frames=1)
