"""The SfM baselines: known answers on rigid scenes, imputation, the estimator contract, errors."""

import numpy as np
import pytest

import stickfigure as sf
from stickfigure import metrics
from test_segmentation import rigid_bodies


def test_sfm_registered_and_contract():
    assert {"sfm", "multibody-sfm"} <= set(sf.available_methods())
    est = sf.get_method("sfm")(random_state=0)
    tr = sf.synthetic.random_figure(n_sticks=1, frames=40, noise=0.01, seed=0, points_per_stick=12)
    assert est.fit(tr) is est
    skel = est.skeleton_
    assert skel.n_sticks == 1 and skel.edges == [] and skel.joints is None
    assert skel.motions.shape == (1, 40, 2, 4) and skel.local.shape == (12, 3)
    assert np.all(est.labels_ == 0) and est.log_likelihood_ == skel.log_likelihood
    np.testing.assert_allclose(skel.predict(), tr.xy, atol=5 * tr.meta["noise_std"])


def test_sfm_imputes_rigid_object_within_twice_the_noise():
    """Acceptance: rigid object, 30% of entries missing, RMSE of the hidden entries <= 2 sigma."""
    for seed in range(3):
        tr = sf.synthetic.random_figure(n_sticks=1, frames=80, noise=0.01, seed=seed, points_per_stick=25)
        occ, hidden = tr.missing_at_random(0.3, random_state=seed)
        skel = sf.fit(occ, method="sfm", random_state=0)
        filled = sf.get_method("sfm").impute_skeleton(skel, occ)
        rmse = metrics.imputation_rmse(filled, tr.xy, hidden)
        assert rmse < 2 * tr.meta["noise_std"]


def test_sfm_log_likelihood_is_gaussian_at_ml_noise():
    tr = sf.synthetic.random_figure(n_sticks=1, frames=30, noise=0.02, seed=3, points_per_stick=10)
    skel = sf.fit(tr, method="sfm")
    s2 = skel.info["noise_std_ml"] ** 2
    n = tr.n_points * tr.n_frames * 2
    assert skel.log_likelihood == pytest.approx(-0.5 * n * (np.log(2 * np.pi * s2) + 1))


def test_sfm_impute_new_frames_and_file_round_trip(tmp_path):
    tr = sf.synthetic.random_figure(n_sticks=1, frames=60, noise=0.01, seed=4, points_per_stick=15)
    train, test = tr.split(0.7)
    skel = sf.fit(train, method="sfm", random_state=0)
    occ, hidden = sf.synthetic.occlude(test, seed=1)
    again = sf.Skeleton.load(skel.save(tmp_path / "m.json"))
    a = sf.get_method("sfm").impute_skeleton(skel, occ)
    b = sf.get_method("sfm").impute_skeleton(again, occ)
    np.testing.assert_allclose(a, b)
    assert metrics.imputation_rmse(a, test.xy, hidden) < 2 * tr.meta["noise_std"]
    assert not np.isnan(a).any()


def test_sfm_errors():
    tr = sf.synthetic.random_figure(n_sticks=1, frames=10, seed=0)
    with pytest.raises(ValueError, match="rank"):
        sf.fit(tr, method="sfm", rank=4)
    with pytest.raises(ValueError, match="at least 2 points"):
        sf.fit(np.zeros((1, 5, 2)), method="sfm")
    with pytest.raises(TypeError, match="bad parameter"):
        sf.fit(tr, method="sfm", nonsense=1)


@pytest.mark.parametrize("seed", [0, 1])
def test_multibody_sfm_segments_independent_bodies(seed):
    xy, labels = rigid_bodies(n_bodies=3, points=(10, 20), frames=50, noise=0.01, seed=seed)
    tr = sf.Trajectories(xy, labels_true=labels)
    skel = sf.fit(tr, method="multibody-sfm", random_state=0)
    assert skel.n_sticks == 3
    assert metrics.misclassification_rate(labels, skel.labels) == 0.0
    assert skel.motions.shape == (3, 50, 2, 4) and skel.edges == []
    # each body's factorisation explains its points to the noise level
    assert skel.info["noise_std_ml"] < 0.012


def test_multibody_sfm_given_count_missing_data_and_imputation():
    xy, labels = rigid_bodies(n_bodies=2, points=(12, 16), frames=60, noise=0.01, seed=3)
    tr = sf.Trajectories(xy, labels_true=labels)
    occ, hidden = tr.missing_at_random(0.2, random_state=0)
    skel = sf.fit(occ, method="multibody-sfm", n_bodies=2, random_state=0)
    assert metrics.misclassification_rate(labels, skel.labels) == 0.0
    filled = sf.get_method("multibody-sfm").impute_skeleton(skel, occ)
    assert metrics.imputation_rmse(filled, xy, hidden) < 2 * 0.01
    # deterministic
    again = sf.fit(occ, method="multibody-sfm", n_bodies=2, random_state=0)
    np.testing.assert_array_equal(again.labels, skel.labels)


def test_multibody_sfm_on_articulated_figure_finds_its_parts():
    tr = sf.synthetic.random_figure(n_sticks=3, frames=100, noise=0.01, seed=13)
    skel = sf.fit(tr, method="multibody-sfm", random_state=0, spread=2.0)
    assert metrics.adjusted_rand_index(tr.labels_true, skel.labels) > 0.9


def test_multibody_sfm_errors():
    xy, _ = rigid_bodies(n_bodies=2, seed=0)
    with pytest.raises(ValueError, match="n_bodies"):
        sf.fit(xy, method="multibody-sfm", n_bodies=0)
    with pytest.raises(ValueError, match="n_bodies"):
        sf.fit(xy, method="multibody-sfm", n_bodies=10_000)


@pytest.mark.data
@pytest.mark.parametrize("name", ["1R2RC", "truck1"])
def test_multibody_sfm_on_hopkins(data_dir, name):
    """Acceptance: misclassification <= 5% with the number of bodies estimated."""
    path = data_dir / "hopkins155" / name / f"{name}_truth.mat"
    if not path.exists():
        pytest.skip(f"{path} not found")
    tr = sf.load(path)
    skel = sf.fit(tr, method="multibody-sfm", random_state=0)
    assert skel.n_sticks == tr.n_parts_true
    assert metrics.misclassification_rate(tr.labels_true, skel.labels) <= 0.05


@pytest.mark.parametrize("seed", [0, 1])
def test_multibody_sfm_under_perspective(seed):
    """A body that the affine camera does not fit exactly is still one body (merge_bodies)."""
    tr = sf.synthetic.rigid_bodies(3, frames=40, noise=0.01, seed=seed, points_per_body=(15, 30), perspective=0.1)
    skel = sf.fit(tr, method="multibody-sfm", random_state=0)
    assert skel.n_sticks == 3
    assert metrics.misclassification_rate(tr.labels_true, skel.labels) <= 0.02
