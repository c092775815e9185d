"""The held-out imputation protocol of Ross et al."""

import numpy as np
import pytest

import stickfigure as sf
from stickfigure import evaluation as ev


def test_make_split_shapes_and_occlusion_rate():
    tr = sf.synthetic.random_figure(n_sticks=2, frames=50, noise=0.01, seed=0)
    split = ev.make_split(tr, random_state=0)
    assert split["train"].n_frames == 35 and split["test"].n_frames == 15
    assert split["hidden"].shape == (tr.n_points, 15)
    frac = split["hidden"].mean()
    assert 0.08 < frac < 0.2  # the paper's 10-15%, a bit wider for small scenes
    assert np.isnan(split["test_occluded"].xy[split["hidden"]]).all()
    again = ev.make_split(tr, random_state=0)
    np.testing.assert_array_equal(again["hidden"], split["hidden"])


def test_imputation_protocol_sfm_on_rigid_object():
    tr = sf.synthetic.random_figure(n_sticks=1, frames=60, noise=0.01, seed=1, points_per_stick=20)
    out = ev.imputation_protocol(tr, "sfm", random_state=0)
    assert out["rmse"] < 2 * tr.meta["noise_std"]
    assert out["rmse_over_noise"] == pytest.approx(out["rmse"] / tr.meta["noise_std"])
    assert out["imputed"].shape == (20, 18, 2) and not np.isnan(out["imputed"]).any()
    assert out["fit_time_s"] >= 0 and out["skeleton"].method == "sfm"
    assert out["scores"]["ari"] == 1.0


def test_imputation_protocol_with_training_occlusion():
    tr = sf.synthetic.random_figure(n_sticks=1, frames=60, noise=0.01, seed=2, points_per_stick=20)
    out = ev.imputation_protocol(tr, "sfm", occlude_train=True, train_missing=0.5, random_state=0)
    assert out["train_missing_fraction"] > 0.5
    assert out["rmse"] < 3 * tr.meta["noise_std"]


def test_compare_methods_share_the_split():
    tr = sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.01, seed=3)
    res = ev.compare_methods(tr, {"sfm": {}, "multibody-sfm": {"spread": 2.0}}, random_state=0)
    assert [r["method"] for r in res] == ["sfm", "multibody-sfm"]
    assert res[0]["n_hidden"] == res[1]["n_hidden"]
    # an articulated figure is not one rigid body: per-part motions impute better
    assert res[1]["rmse"] < res[0]["rmse"]


def test_protocol_errors():
    tr = sf.synthetic.random_figure(n_sticks=1, frames=20, seed=0)
    with pytest.raises(ValueError, match="train_fraction"):
        ev.imputation_protocol(tr, "sfm", train_fraction=1.5)
    with pytest.raises(ValueError, match="train_missing"):
        ev.imputation_protocol(tr, "sfm", train_missing=1.0)
    with pytest.raises(ValueError, match="unknown method"):
        ev.imputation_protocol(tr, "nope")
    with pytest.raises(ValueError, match="empty"):
        ev.compare_methods(tr, [])
