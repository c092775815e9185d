"""Method "em" end to end: known structures, determinism, imputation, errors, files, pictures."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

import stickfigure as sf
from stickfigure.models.em import EMSkeleton
from stickfigure.metrics import score_skeleton


def _edges(sk: sf.Skeleton, traj: sf.Trajectories) -> set[tuple[int, int]]:
    """The skeleton's edges in the true part numbering (majority vote per stick)."""
    m = {s: int(np.bincount(traj.labels_true[sk.labels == s]).argmax()) for s in range(sk.n_sticks)}
    return {tuple(sorted((m[a], m[b]))) for a, b in sk.edges}


def _true_edges(traj: sf.Trajectories) -> set[tuple[int, int]]:
    return {tuple(sorted(e)) for e in traj.edges_true}


@pytest.fixture(scope="module")
def chain():
    """A 3-stick figure whose structure em must recover exactly (given its groups)."""
    return sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.01, seed=7)


@pytest.fixture(scope="module")
def fitted(chain):
    est = EMSkeleton(random_state=0, labels=chain.labels_true, n_iter=100)
    return est.fit(chain)


def test_known_structure_from_true_groups(chain, fitted):
    sk = fitted.skeleton_
    assert sk.method == "em"
    assert adjusted_rand_score(chain.labels_true, sk.labels) == 1.0
    assert _edges(sk, chain) == _true_edges(chain)
    P, F, _ = chain.shape
    assert sk.motions.shape == (3, F, 2, 4)
    np.testing.assert_allclose(sk.motions[..., :3] @ np.swapaxes(sk.motions[..., :3], -1, -2),
                               np.broadcast_to(np.eye(2), (3, F, 2, 2)), atol=1e-8)  # orthonormal rows
    assert sk.local.shape == (P, 3)
    # Predictions reproduce the data to the noise level.
    rms = np.sqrt(np.nanmean((sk.predict() - chain.xy) ** 2))
    assert rms < 2 * chain.meta["noise_std"]
    # Joints: one per edge, near the true joints.
    assert sk.joints.shape == (2, F, 2) and sk.edge_joints.shape == (2,)
    for e, row in zip(sk.edges, sk.edge_joints):
        te = tuple(sorted(_edges_map(sk, chain)[s] for s in e))
        j = [i for i, t in enumerate(chain.edges_true) if tuple(sorted(t)) == te][0]
        err = np.median(np.linalg.norm(sk.joints[row] - chain.joints_true[j], axis=1))
        assert err < 0.15


def _edges_map(sk, traj):
    return {s: int(np.bincount(traj.labels_true[sk.labels == s]).argmax()) for s in range(sk.n_sticks)}


def test_stages_and_selection(fitted):
    info = fitted.skeleton_.info
    stages = info["stages"]
    assert len(stages) == 3  # no joints, one, two
    assert [len(s["edges"]) for s in stages] == [0, 1, 2]
    objs = [s["objective"] for s in stages]
    assert info["objective_stage"] == int(np.argmax(objs))
    assert info["bic_stage"] == int(np.argmax([s["bic"] for s in stages]))
    assert info["selected_stage"] == info["bic_stage"]  # the default selection
    assert fitted.skeleton_.log_likelihood == pytest.approx(objs[info["selected_stage"]])


def test_same_seed_same_skeleton(chain):
    a = sf.fit(chain, method="em", random_state=3, n_iter=60, max_merges=1)
    b = sf.fit(chain, method="em", random_state=3, n_iter=60, max_merges=1)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.edges == b.edges
    np.testing.assert_array_equal(a.motions, b.motions)
    assert a.log_likelihood == b.log_likelihood


def test_affinity_propagation_start(small_figure):
    # The clustering start and the merge search alone: on this 60-frame scene the articulated
    # split (tested in test_em_updates.py) turns the one point the clustering misplaces, near a
    # joint, into a 2-point stick (ARI 0.88) instead of leaving it to the resampling.
    sk = sf.fit(small_figure, method="em", random_state=0, n_iter=80, articulated_rounds=0)
    assert adjusted_rand_score(small_figure.labels_true, sk.labels) > 0.9
    assert _edges(sk, small_figure) == _true_edges(small_figure)


def test_impute_held_out_frames(chain, fitted):
    train, test = chain.split(0.7)
    est = EMSkeleton(random_state=0, labels=chain.labels_true, n_iter=100).fit(train)
    occluded, hidden = sf.synthetic.occlude(test, seed=1)
    filled = est.impute(occluded)
    assert filled.shape == test.xy.shape
    assert np.all(np.isfinite(filled))
    np.testing.assert_array_equal(filled[~hidden & test.observed], test.xy[~hidden & test.observed])
    rmse = np.sqrt(np.mean(np.sum((filled[hidden] - test.xy[hidden]) ** 2, axis=-1)))
    spread = np.sqrt(np.mean(np.sum((test.xy - np.nanmean(test.xy, axis=(0, 1))) ** 2, axis=-1)))
    assert rmse < 0.1 * spread


def _weak_perspective(traj: sf.Trajectories, c: np.ndarray) -> sf.Trajectories:
    """Each frame scaled by c[f] about the figure's mean: a subject nearing a pinhole camera."""
    m = np.nanmean(traj.xy, axis=0)
    return traj.with_xy(m + (traj.xy - m) * np.asarray(c)[:, None])


def test_frame_scales_recover_a_weak_perspective_scale():
    from scipy.spatial.transform import Rotation

    from stickfigure.models.em.impute import frame_scales

    rng = np.random.default_rng(0)
    P, F = 14, 40
    labels = np.repeat([0, 1, 2, 3], [4, 4, 4, 2])
    local = rng.normal(size=(P, 3))
    local[4:8, 2] = 0.0  # a flat stick: its largest stretch is still the scale
    c = np.exp(0.3 * np.sin(np.linspace(0.0, 6.0, F)))
    xy = np.zeros((P, F, 2))
    for s in range(4):
        R = Rotation.random(F, random_state=s).as_matrix()[:, :2]  # (F, 2, 3) orthonormal rows
        idx = labels == s
        xy[idx] = (c[:, None, None] * np.einsum("fdk,pk->fpd", R, local[idx])
                   + rng.normal(size=(F, 1, 2))).transpose(1, 0, 2)
    np.testing.assert_allclose(frame_scales(labels, local, xy), c, rtol=1e-9)
    # Points in another order, missing entries, and frames no stick can measure (interpolated).
    perm = rng.permutation(P)
    gappy = xy[perm].copy()
    gappy[np.isin(perm, [0, 1]), :10] = np.nan  # stick 0 shows 2 points in frames 0-9; the others measure
    gappy[np.isin(perm, [0, 1, 4, 5, 8, 9]), 20:25] = np.nan  # no stick shows 3 points in frames 20-24
    got = frame_scales(labels[perm], local[perm], gappy)
    measured = np.r_[np.arange(0, 20), np.arange(25, F)]
    np.testing.assert_allclose(got[measured], c[measured], rtol=1e-9)
    between = np.interp(np.arange(20, 25), [19, 25], np.log(c[[19, 25]]))  # interpolated in log scale
    np.testing.assert_allclose(np.log(got[20:25]), between, atol=1e-9)
    # A 2-point stick alone says nothing: scale 1.
    assert np.array_equal(frame_scales(np.zeros(2, int), local[:2], xy[:2]), np.ones(F))
    with pytest.raises(ValueError, match="xy"):
        frame_scales(labels, local, xy[..., :1])


def test_impute_scale_follows_a_subject_nearing_the_camera(tmp_path):
    """Through a camera the figure nears (image 0.8 -> 1.3 times its size), ``impute_scale`` halves
    the error; on an orthographic image it changes little."""
    fig = sf.synthetic.random_figure(4, frames=120, seed=1)
    near = _weak_perspective(fig, np.linspace(0.8, 1.3, fig.n_frames))
    for data, lo, hi in ((near, 0.0, 0.6), (fig, 0.8, 1.25)):
        train, test = data.split(0.7)
        occluded, hidden = sf.synthetic.occlude(test, seed=1)
        est = EMSkeleton(random_state=0, impute_scale=True).fit(train)
        scaled = est.impute(occluded)
        np.testing.assert_array_equal(scaled[~hidden & test.observed], test.xy[~hidden & test.observed])
        est.skeleton_.save(tmp_path / "m.json")  # the option and the training frames' scale are saved
        np.testing.assert_allclose(sf.Skeleton.load(tmp_path / "m.json").impute(occluded), scaled, atol=1e-9)
        est.skeleton_.params["impute_scale"] = False
        plain = est.impute(occluded)
        rmse = [np.sqrt(np.mean(np.sum((f[hidden] - test.xy[hidden]) ** 2, axis=-1))) for f in (scaled, plain)]
        assert lo < rmse[0] / rmse[1] < hi, rmse
    with pytest.raises(ValueError, match="impute_scale"):
        EMSkeleton(impute_scale="yes").fit(fig)


def test_impute_names_a_stick_hidden_in_every_frame(chain, fitted):
    # Its pose cannot come from anywhere: a clear error, not numpy's "array of sample points
    # is empty" from deep inside the start (as before).
    xy = chain.xy.copy()
    xy[fitted.labels_ == 0] = np.nan
    with pytest.raises(ValueError, match=r"stick 0 \(points .*\) is not visible in any frame"):
        fitted.impute(xy)


def test_start_state_with_a_stick_hidden_in_every_frame(chain, fitted):
    # The held-out check may hide every entry of a small stick: the imputation start must not
    # fail there (it gave numpy's "array of sample points is empty"); the stick gets a
    # placeholder pose, which its joints move in EM.
    from stickfigure.models.em.impute import start_state
    from stickfigure.models.em.model import Observations

    sk = fitted.skeleton_
    scale, centre = float(sk.state["scale"]), np.asarray(sk.state["centre"], float)
    seen = (sk.labels != 0)[:, None] & chain.observed
    obs = Observations(np.where(seen[..., None], (chain.xy - centre) / scale, 0.0), seen.astype(float))
    st = start_state(sk.labels, sk.local / scale, np.asarray(sk.state["ends"], float) / scale,
                     np.asarray(sk.state["vertex_of"], np.int64), np.asarray(sk.state["alpha"], float),
                     np.asarray(sk.state["beta"], float), tuple(float(v) for v in sk.state["precisions"]), 1.0, obs)
    assert np.all(np.isfinite(st.point_predictions()))
    RRt = st.rot[0] @ np.swapaxes(st.rot[0], 1, 2)
    np.testing.assert_allclose(RRt, np.broadcast_to(np.eye(2), RRt.shape))


def test_missing_training_data(chain):
    rng = np.random.default_rng(0)
    xy = chain.xy.copy()
    xy[rng.random(xy.shape[:2]) < 0.3] = np.nan
    sk = sf.fit(chain.with_xy(xy, allow_unobserved=False), method="em", random_state=0,
                labels=chain.labels_true, n_iter=80)
    assert _edges(sk, chain) == _true_edges(chain)


def test_save_load_and_impute_after_loading(tmp_path, chain, fitted):
    path = fitted.skeleton_.save(tmp_path / "em.json")
    back = sf.Skeleton.load(path)
    assert back.edges == fitted.skeleton_.edges
    occluded, hidden = sf.synthetic.occlude(chain, seed=2)
    np.testing.assert_allclose(back.impute(occluded), fitted.skeleton_.impute(occluded))


def test_imputation_options_are_parameters_and_survive_saving(tmp_path, chain, fitted):
    # The joint motion-endpoint block and the rotation and centroid priors (docs/em.md section 8)
    # are read from the saved parameters; each setting predicts the hidden entries near the truth.
    path = fitted.skeleton_.save(tmp_path / "opts.json")
    occluded, hidden = sf.synthetic.occlude(chain, seed=3)
    filled = {}
    for joint in (True, False):
        for prior in (True, False):
            for centroid in (True, False):
                sk = sf.Skeleton.load(path)
                sk.params.update(impute_joint_ends=joint, impute_rotation_prior=prior, impute_centroid_prior=centroid)
                filled[joint, prior, centroid] = f = sk.impute(occluded)
                rmse = np.sqrt(np.mean(np.sum((f[hidden] - chain.xy[hidden]) ** 2, axis=-1)))
                assert rmse < 0.05, (joint, prior, centroid)
    np.testing.assert_allclose(filled[True, True, True], fitted.skeleton_.impute(occluded))  # the defaults
    assert not np.allclose(filled[True, True, True], filled[False, False, False])
    assert not np.allclose(filled[True, True, True], filled[True, True, False])
    old = sf.Skeleton.load(path)  # a model saved before the options existed: their defaults
    del old.params["impute_joint_ends"], old.params["impute_rotation_prior"], old.params["impute_centroid_prior"]
    np.testing.assert_allclose(old.impute(occluded), filled[True, True, True])


@pytest.mark.parametrize("bad,match", [
    ({"selection": "aic"}, "selection"),
    ({"merge_scope": "global"}, "merge_scope"),
    ({"n_ends": 1}, "n_ends"),
    ({"n_iter": 0}, "n_iter"),
    ({"tol": -1.0}, "tol"),
    ({"dissolve_points": -1}, "dissolve_points"),
    ({"max_frames": 2}, "max_frames"),
    ({"oversegment": 0.5}, "oversegment"),
    ({"holdout": 1.5}, "holdout"),
    ({"n_jobs": 0}, "n_jobs"),
    ({"holdout_masks": 0}, "holdout_masks"),
    ({"holdout_points": 0}, "holdout_points"),
    ({"split_dissolved": -1}, "split_dissolved"),
    ({"split_dissolved": 2.5}, "split_dissolved"),
    ({"split_axes": 0}, "split_axes"),
    ({"split_axes": 4}, "split_axes"),
    ({"max_trees": 0}, "max_trees"),
    ({"max_trees": "one"}, "max_trees"),
    ({"max_trees": True}, "max_trees"),
    ({"impute_joint_ends": "yes"}, "impute_joint_ends"),
    ({"impute_rotation_prior": 1}, "impute_rotation_prior"),
    ({"impute_centroid_prior": "no"}, "impute_centroid_prior"),
    ({"dissolve_scope": "middle"}, "dissolve_scope"),
    ({"labels": [0, 1]}, "labels"),
])
def test_bad_parameters(chain, bad, match):
    with pytest.raises(ValueError, match=match):
        EMSkeleton(**bad).fit(chain)


def test_3d_data_is_rejected():
    traj = sf.synthetic.walker(n_frames=10, project=False)
    with pytest.raises(ValueError, match="2D"):
        sf.fit(traj, method="em")


def test_paper_variants_run(chain):
    # The paper's choices: two endpoints at the centroid, mean merge, whole-model scoring,
    # fixed iteration counts, no baseline, no score reuse, no stick refinement, no moves after the
    # merge search, every frame searched.
    sk = sf.fit(chain, method="em", random_state=0, labels=chain.labels_true, n_ends=2,
                endpoint_init="centroid", merge_init="mean", merge_scope="full", n_iter=40, n_iter_merge=10,
                tol=0.0, merge_baseline=False, reuse_scores=False, refine_sticks=False, resplit=False,
                dissolve_points=0, max_frames=None)
    assert len(sk.info["stages"]) == 3
    assert sk.info["stages"][-1]["n_sticks"] == 3
    assert all(s["n_sweeps"] == 40 for s in sk.info["stages"])


def test_plots(tmp_path, chain, fitted):
    import matplotlib

    matplotlib.use("Agg")
    from stickfigure.plot import em as emplot

    fig = emplot.plot_stages(fitted.skeleton_, chain)
    assert len(fig.axes) >= 3
    titles = [a.get_title() for a in fig.axes if a.get_title()]
    assert titles[0].startswith("stage 0: EM") and titles[1].startswith("stage 1: merge")
    assert sum("(selected)" in t for t in titles) == 1
    ax = emplot.plot_objective(fitted.skeleton_)
    assert ax.get_xlabel() == "merge stage"
    out = emplot.figure(fitted.skeleton_, chain, tmp_path / "em.png")
    assert out.exists() and out.stat().st_size > 1000
    with pytest.raises(ValueError, match="em"):
        emplot.plot_stages(sf.Skeleton(method="sfm", labels=np.zeros(3, int), n_sticks=1))


def test_progress_bar_reports_stages(chain, capsys):
    sf.fit(chain, method="em", random_state=0, labels=chain.labels_true, n_iter=20, progress=True)
    err = capsys.readouterr().err
    assert "stage" in err and "objective" in err


def _by_distance_to_first_joint(chain):
    """The points of the first true joint's two parts, each part's nearest the joint first."""
    T = chain.labels_true
    a, b = chain.edges_true[0]
    dist = np.nanmean(np.linalg.norm(chain.xy - chain.joints_true[0][None], axis=-1), axis=1)
    return (np.flatnonzero(T == a)[np.argsort(dist[T == a], kind="stable")],
            np.flatnonzero(T == b)[np.argsort(dist[T == b], kind="stable")])


def test_spurious_two_point_stick_is_dissolved(chain):
    # Known answer: the point of each of two jointed parts nearest their joint is given a stick
    # of its own (what an articulated split of a misassigned point produces). Without
    # resampling or refinement the merge search keeps it (joined in the tree, 4 sticks); the
    # Hartigan-style dissolution must give the points back to their parts (BIC charges the
    # 2-point stick's per-frame rotations, which only buy it a near-exact fit).
    T = chain.labels_true
    ia, ib = _by_distance_to_first_joint(chain)
    pa, pb = ia[0], ib[0]
    labels = T.copy()
    labels[[pa, pb]] = T.max() + 1
    kw = dict(random_state=0, labels=labels, resample_every=0, refine_sticks=False, n_iter=100)
    kept = sf.fit(chain, method="em", dissolve_points=0, **kw)
    assert kept.n_sticks == 4
    sk = sf.fit(chain, method="em", **kw)
    assert sk.n_sticks == 3
    assert adjusted_rand_score(T, sk.labels) == 1.0
    assert _edges(sk, chain) == _true_edges(chain)
    assert sk.info["stages"][-1]["dissolved"] == [sorted([int(pa), int(pb)])]
    assert sk.info["selected_stage"] == len(sk.info["stages"]) - 1


def test_structure_search_on_subsampled_frames(chain):
    # max_frames: the search runs on 20 evenly spaced frames of 60; the selected structure is
    # then re-fitted on all frames (motions for every frame, predictions at the noise level).
    sk = sf.fit(chain, method="em", random_state=0, labels=chain.labels_true, n_iter=100, max_frames=20)
    refit = sk.info["refit"]
    assert refit["search_frames"] == 20 and refit["frames"] == chain.n_frames
    assert sk.log_likelihood == refit["objective"]
    assert sk.motions.shape == (3, chain.n_frames, 2, 4) and sk.joints.shape[1] == chain.n_frames
    assert adjusted_rand_score(chain.labels_true, sk.labels) == 1.0
    assert _edges(sk, chain) == _true_edges(chain)
    rms = np.sqrt(np.nanmean((sk.predict() - chain.xy) ** 2))
    assert rms < 2 * chain.meta["noise_std"]
    full = sf.fit(chain, method="em", random_state=0, labels=chain.labels_true, n_iter=100, max_frames=None)
    assert "refit" not in full.info
    assert _edges(full, chain) == _true_edges(chain)


def test_search_frames_keep_reference_and_every_point():
    from stickfigure.models.em.structure import search_frames

    mask = np.ones((3, 100), bool)
    mask[0, 0] = False  # the reference frame (most points seen, the first such) is frame 1
    fr = search_frames(mask, 10)
    assert fr[0] == 0 and fr[-1] == 99 and 1 in fr and np.all(np.diff(fr) > 0)
    mask[2] = False
    mask[2, 37] = mask[2, 38] = True  # a point seen only off the even grid
    fr = search_frames(mask, 10)
    assert 37 in fr or 38 in fr
    assert search_frames(mask, None) is None and search_frames(mask, 100) is None



def test_independent_bodies_stay_apart():
    # Two rigid bodies moving independently: the merge search still joins them (one tree), but
    # that joint is a loose vertex the data do not support as rigid, so it saves no parameters
    # in BIC and the forest (no edge) is selected. Before, BIC credited the rigid-joint saving
    # and selected the joined stage on this scene.
    traj = sf.synthetic.rigid_bodies(n_bodies=2, frames=100, seed=0)
    sk = sf.fit(traj, method="em", random_state=0)
    stages = sk.info["stages"]
    assert len(stages) == 2 and len(stages[1]["edges"]) == 1
    assert sk.n_sticks == 2 and sk.edges == [] and sk.info["selected_stage"] == 0
    assert stages[1]["bic"] < stages[0]["bic"]
    assert sk.info["settings"]["max_trees"] is None  # "auto": the synthetic scene names no figure count


def test_max_trees_joins_a_forest_whatever_the_criterion():
    # The same two bodies said to be one figure (max_trees=1, or the format's n_figures with the
    # default "auto"): the selected forest is joined by its best merge, recorded as "joined".
    traj = sf.synthetic.rigid_bodies(n_bodies=2, frames=100, seed=0)
    sk = sf.fit(traj, method="em", random_state=0, max_trees=1)
    assert sk.edges == [(0, 1)] and sk.info["stages"][-1]["joined"] == [[0, 1]]
    assert sk.info["selected_stage"] == len(sk.info["stages"]) - 1
    from stickfigure.plot.em import stage_kind

    assert stage_kind(sk.info["stages"][-1], len(sk.info["stages"]) - 1) == "trees joined"
    traj.meta["n_figures"] = 1
    auto = sf.fit(traj, method="em", random_state=0)
    assert auto.edges == [(0, 1)] and auto.info["settings"]["max_trees"] == 1
    traj.meta["n_figures"] = 2
    assert sf.fit(traj, method="em", random_state=0).edges == []
    assert sf.fit(traj, method="em", random_state=0, max_trees=None, n_iter=20).info["settings"]["max_trees"] is None


def _benchmark_figure(seed: int) -> sf.Trajectories:
    """The random 3D figure of benchmarks/bench_em.py for a scene seed."""
    rng = np.random.default_rng(20_000 + seed)
    return sf.synthetic.random_figure(n_sticks=int(rng.integers(3, 8)), frames=int(rng.integers(90, 181)),
                                      noise=0.01, seed=seed, points_per_stick=(5, 9))


def test_finer_start_recovers_parts_the_clustering_merged():
    # Known answer: on this 5-part figure (32 points) the clustering's count is 4, and the
    # search from it ends at 7 sticks that cut one part in three (ARI 0.80). The second start
    # from ceil(32 / 3.5) = 10 groups finds the five parts and their tree, and its BIC is the
    # higher, so it is kept. (Figure 2004, used before, is now clustered right at once.)
    traj = _benchmark_figure(2089)
    one = sf.fit(traj, method="em", random_state=2089, oversegment=None)
    assert one.info["initial_clustering"]["n_segments"] == 4 and "starts" not in one.info
    assert adjusted_rand_score(traj.labels_true, one.labels) < 0.9
    sk = sf.fit(traj, method="em", random_state=2089, n_jobs=2)
    starts = sk.info["starts"]
    assert len(starts) == 2 and starts[1]["n_initial_sticks"] == 10
    # Starts are compared by the BIC each search reached before its held-out check.
    assert sk.info["start"] == int(np.argmax([s["search_bic"] for s in starts])) == 1
    assert sk.info["first_start_misfit"] > 1.35
    assert adjusted_rand_score(traj.labels_true, sk.labels) == 1.0
    assert _edges(sk, traj) == _true_edges(traj)
    # The second search ran beside the first in a forked process (on Linux); run after it in
    # this process, it gives the same skeleton: it draws from its own generator.
    import multiprocessing

    from stickfigure.models.em.forked import _fork_context

    assert sk.info["second_start_parallel"] == (_fork_context() is not None)
    assert not multiprocessing.active_children()
    seq = sf.fit(traj, method="em", random_state=2089, n_jobs=1)
    assert seq.info["second_start_parallel"] is False
    assert seq.info["starts"] == starts
    np.testing.assert_array_equal(seq.labels, sk.labels)
    assert seq.edges == sk.edges
    np.testing.assert_array_equal(seq.joints, sk.joints)


def test_no_second_start_when_every_stick_is_rigid():
    # Every stick of the first search fits at the noise level (this 4-part figure is found
    # exactly): the finer start, which could only add sticks, is not run.
    traj = _benchmark_figure(4)
    sk = sf.fit(traj, method="em", random_state=4, n_jobs=2)
    assert "starts" not in sk.info and sk.info["first_start_misfit"] <= 1.35
    # The speculative second search was stopped, not left running.
    import multiprocessing

    assert not multiprocessing.active_children()
    assert adjusted_rand_score(traj.labels_true, sk.labels) == 1.0
    assert _edges(sk, traj) == _true_edges(traj)


@pytest.mark.parametrize("seed, frames", [(7015, 105), (7046, 116)])
def test_noisy_figure_whose_sticks_all_hold_two_parts_gets_the_second_start(seed, frames):
    # Known answer at 3 % noise (three times the benchmark's): the first search ends with 2
    # sticks for these 3-part figures, one holding points of two parts, and the worst misfit
    # against the lower quartile over the sticks stays near 1 (1.08, 1.21): a noise level taken
    # from sticks that are all too coarse is inflated with them. Against the data's local noise
    # level it is 1.92 and 2.25, so the finer start runs, and it finds the three parts and
    # their tree (before: ARI 0.52 and 0.48, edge F1 0 and 0.67).
    traj = sf.synthetic.random_figure(n_sticks=3, frames=frames, noise=0.03, seed=seed, points_per_stick=(5, 9))
    sk = sf.fit(traj, method="em", random_state=seed, n_jobs=1)
    assert sk.info["first_start_misfit"] <= 1.35 < 1.5 < sk.info["first_start_local_misfit"]
    assert sk.info["second_start_by_local_misfit"] is True and sk.info["start"] == 1
    assert adjusted_rand_score(traj.labels_true, sk.labels) == 1.0
    assert _edges(sk, traj) == _true_edges(traj)


def test_local_noise_variance_measures_the_noise_without_sticks():
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.refine import local_noise_variance

    traj = sf.synthetic.random_figure(n_sticks=4, frames=100, noise=0.02, seed=3)
    obs, _, scale = normalise(traj.xy)
    sigma = traj.meta["noise_std"] / scale  # in the normalised units EM works in
    var = local_noise_variance(obs, Priors())
    # The most rigid small sets read the noise a little low (they are chosen for fitting best).
    assert 0.6 * sigma**2 < var < 1.1 * sigma**2
    # Four trajectories admit no rigidity test: no local level rather than an error.
    assert local_noise_variance(obs.take(np.arange(4)), Priors()) is None


def test_a_hub_split_in_the_first_search_calls_for_the_second_start(monkeypatch):
    # A stick that split_hubs had to split was not rigid when the search left it, though the
    # final state fits: the finer start is searched as for a misfit. The same rigid figure as
    # above, with a split reported (the state left as it was).
    from stickfigure.models.em import refine

    monkeypatch.setattr(refine, "split_hubs", lambda st, obs, priors, settings, rng, value, crit: (st, value, 0, [0]))
    traj = _benchmark_figure(4)
    sk = sf.fit(traj, method="em", random_state=4, n_jobs=1)
    assert sk.info["first_start_hub_split"] is True and sk.info["first_start_misfit"] <= 1.35
    assert len(sk.info["starts"]) == 2
    assert any(s["hubs"] == [0] for s in sk.info["stages"])


def test_noiseless_figure_is_not_oversegmented():
    # Known answer on noiseless data: every stick's residual is the residue the truncated EM
    # leaves, different from stick to stick. With the noise variance floored at 1e-300 and
    # tau_w capped at 1e10, the stick checks read that residue as articulation and this
    # 5-part figure came out as 13 sticks (ARI 0.67); the floor 1 / max_precision (1e-6,
    # a noise std of 1e-3 of the spread) leaves the five parts and their tree.
    traj = sf.synthetic.random_figure(n_sticks=5, frames=120, noise=0.0, seed=1)
    sk = sf.fit(traj, method="em", random_state=0)
    assert sk.info["precisions"]["tau_w"] <= 1e6
    assert adjusted_rand_score(traj.labels_true, sk.labels) == 1.0
    assert _edges(sk, traj) == _true_edges(traj)


def test_noise_variance_is_floored_by_the_precision_bound(chain):
    from stickfigure.models.em import fit_stages
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.refine import misfit_ratios, noise_variance
    from stickfigure.models.em.structure import EMSettings

    stages, sel, _, _ = fit_stages(chain, EMSettings(n_iter=60), Priors(), np.random.default_rng(0),
                                   labels=chain.labels_true)
    st = stages[sel].state
    obs, _, _ = normalise(chain.xy)
    rss, quartile = noise_variance(st, obs, Priors(max_precision=1e12))
    assert rss.shape == (st.n_sticks,) and 1e-12 < quartile < 1e-2  # 1 % noise: the sticks' own level
    _, var = noise_variance(st, obs, Priors(max_precision=1e2))
    assert var == 1e-2  # above the data's level: the bound
    loose, tight = misfit_ratios(st, obs, Priors(max_precision=1e2)), misfit_ratios(st, obs, Priors(max_precision=1e12))
    np.testing.assert_allclose(loose, tight * quartile / 1e-2)


def test_misfit_ratios_of_true_sticks_stay_near_one_with_half_the_data_missing():
    # 4-point sticks, half the entries hidden: in many frames a stick shows fewer than 3 points
    # and its rotation is interpolated, not fitted. Counting 3 + D parameters in every frame it
    # is seen in (as the ratio once did) left negative degrees of freedom (ratio 0) or a few
    # (ratio 17-36) for these rigid sticks; counted as the noise variance counts them (fit_dof)
    # they fit at about 1.
    from stickfigure.models.em import fit_stages
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.refine import fit_dof, misfit_ratios
    from stickfigure.models.em.structure import EMSettings

    tr = sf.synthetic.random_figure(n_sticks=4, frames=120, noise=0.01, seed=3, points_per_stick=4)
    occ, _ = sf.synthetic.occlude(tr, seed=3, bar_fraction=0.3, random_fraction=0.3)
    stages, sel, _, _ = fit_stages(occ, EMSettings(n_iter=60), Priors(), np.random.default_rng(0),
                                   labels=tr.labels_true)
    st = stages[sel].state
    obs, _, _ = normalise(occ.xy)
    assert np.all(fit_dof(st, obs) > 0)
    ratio = misfit_ratios(st, obs, Priors())
    assert np.all((ratio > 0.5) & (ratio < 1.5))


def test_heldout_error_predicts_hidden_entries_only(chain):
    # The held-out error re-fits the motions from the visible entries (as imputation does):
    # nothing hidden, nothing to score; with 15 % hidden, the true structure predicts them to
    # about the noise (1 % of the figure's size) and a point whose stick is wrong far worse.
    from stickfigure.models.em import fit_stages
    from stickfigure.models.em.impute import heldout_error
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.structure import EMSettings

    settings = EMSettings(n_iter=60, holdout=None)
    stages, sel, _, _ = fit_stages(chain, settings, Priors(), np.random.default_rng(0), labels=chain.labels_true)
    st = stages[sel].state
    obs, _, scale = normalise(chain.xy)
    P, F = obs.mask.shape
    np.testing.assert_array_equal(heldout_error(st, obs, Priors(), settings, np.zeros((P, F), bool)), 0.0)
    hidden = np.random.default_rng(1).random((P, F)) < 0.15
    err = heldout_error(st, obs, Priors(), settings, hidden)
    assert err.shape == (P,) and np.all(err[hidden.sum(axis=1) == 0] == 0)
    rms = np.sqrt(err.sum() / (2 * hidden.sum())) * scale
    assert rms < 4 * chain.meta["noise_std"]


def test_cross_body_two_point_stick_is_dissolved_by_prediction():
    # Known answer: the far ends of two leaf parts of a 4-part figure, given a stick of their
    # own, pair two points that share no joint (what em did to CMU markers, LTHI + C7).
    # Without resampling or refinement the search keeps it; in 2D it fits its two points
    # exactly. The held-out check hides entries and predicts them with the structure fixed:
    # with one of its points hidden the other leaves the stick's rotation open, so it must be
    # dissolved and the points given back to their parts.
    from stickfigure.models.em import fit_stages
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.impute import heldout_error
    from stickfigure.models.em.refine import heldout_dissolve
    from stickfigure.models.em.structure import EMSettings
    from stickfigure.synthetic import occlude
    from stickfigure.trajectories import Trajectories

    traj = sf.synthetic.random_figure(n_sticks=4, frames=90, noise=0.01, seed=3)
    T = traj.labels_true
    leaves = [p for p in range(int(T.max()) + 1) if sum(p in e for e in traj.edges_true) == 1]
    far = []
    for part in leaves[:2]:
        idx = np.flatnonzero(T == part)
        j = [k for k, e in enumerate(traj.edges_true) if part in e][0]
        d = np.nanmean(np.linalg.norm(traj.xy[idx] - traj.joints_true[j][None], axis=-1), axis=1)
        far.append(int(idx[np.argmax(d)]))
    labels = T.copy()
    labels[far] = T.max() + 1
    settings = EMSettings(n_iter=100, resample_every=0, refine_sticks=False, dissolve_points=0, resplit=False,
                          holdout=None, bridge_points=0)
    stages, sel, _, _ = fit_stages(traj, settings, Priors(), np.random.default_rng(0), labels=labels)
    st = stages[sel].state
    assert st.n_sticks == 5
    obs, _, _ = normalise(traj.xy)
    out, _, _, gone, info = heldout_dissolve(st, obs, Priors(), settings, np.random.default_rng(0),
                                             stages[sel].objective, 3, 0.15)
    assert gone == [sorted(far)]
    assert adjusted_rand_score(T, out.labels) == 1.0
    assert info["error_after"] < info["error_before"]
    # dissolve_scope="leaves" offers it too: the search joined the cross-body stick at one end
    # only, so it is a leaf.
    assert st.joints_per_stick()[st.labels[far[0]]] == 1
    out, _, _, gone, _ = heldout_dissolve(st, obs, Priors(), settings, np.random.default_rng(0),
                                          stages[sel].objective, 3, 0.15, scope="leaves")
    assert gone == [sorted(far)] and adjusted_rand_score(T, out.labels) == 1.0
    # With several masks (holdout_masks) the errors are pooled over independent occlusion
    # masks drawn from the generator in turn, and the same stick goes.
    rng = np.random.default_rng(0)
    xy = np.where(obs.mask[..., None] > 0, obs.w, np.nan)
    masks = [occlude(Trajectories(xy), seed=rng, bar_fraction=0.075, random_fraction=0.075)[1] for _ in range(3)]
    assert not np.array_equal(masks[0], masks[1])
    pooled = sum(heldout_error(st, obs, Priors(), settings, h) for h in masks).sum()
    out, _, _, gone, info = heldout_dissolve(st, obs, Priors(), settings, np.random.default_rng(0),
                                             stages[sel].objective, 3, 0.15, n_masks=3)
    assert info["error_before"] == pytest.approx(np.sqrt(pooled / (2 * sum(h.sum() for h in masks))))
    assert gone == [sorted(far)]


def test_heldout_check_needs_the_sticks_own_points_predicted_better(chain, monkeypatch):
    # A dissolution is kept only when it predicts better both the near set (the stick's points
    # and the sticks that take them) and the stick's own points. The predictions are replaced
    # by fixed errors: the first stick tried improves only its receivers' points (the EM
    # re-run's doing, as with the CMU pelvis stick), the second improves its own points too.
    from stickfigure.models.em import fit_stages, impute, refine
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.structure import EMSettings

    settings = EMSettings(n_iter=30)
    stages, sel, _, _ = fit_stages(chain, settings, Priors(), np.random.default_rng(0), labels=chain.labels_true)
    st = stages[sel].state
    assert st.n_sticks == 3
    obs, _, _ = normalise(chain.xy)
    tried = []
    dissolve = refine.dissolve_stick

    def record(state, obs_, priors, s):
        tried.append(np.flatnonzero(state.labels == s))
        return dissolve(state, obs_, priors, s)

    def errors(state, obs_, priors, settings_, hidden, n_iter=50):
        if state.n_sticks == 3:
            return np.ones(obs_.n_points)
        if state.n_sticks == 1:
            return np.full(obs_.n_points, 2.0)
        e = np.full(obs_.n_points, 0.5)
        if len(tried) == 1:
            e[tried[0]] = 1.0
        return e

    monkeypatch.setattr(refine, "dissolve_stick", record)
    monkeypatch.setattr(impute, "heldout_error", errors)
    out, _, _, gone, _ = refine.heldout_dissolve(st, obs, Priors(), settings, np.random.default_rng(0),
                                                 stages[sel].objective, 100, 0.15)
    assert len(tried) >= 2
    assert gone[0] == tried[1].tolist()
    assert tried[0].tolist() not in gone
    assert out.n_sticks == 2


def test_heldout_check_leaves_rigid_three_point_sticks_to_the_likelihood(monkeypatch):
    # Sticks of at most free_points (holdout_points, default 2) points are always offered to
    # the held-out check; a larger one only while its fit is suspect (misfit ratio above
    # 1.25). A 3-point stick that fits at the noise level is the likelihood's to judge:
    # prediction is biased against it (all three hidden by the bar). (True 3-point parts do
    # not always fit that well: here two of the four are above 1.25, and are offered.)
    from stickfigure.models.em import fit_stages, refine
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.structure import EMSettings

    traj = sf.synthetic.random_figure(n_sticks=4, frames=90, noise=0.01, seed=3, points_per_stick=3)
    settings = EMSettings(n_iter=60, resample_every=0, refine_sticks=False, dissolve_points=0, resplit=False,
                          holdout=None, bridge_points=0)
    stages, sel, _, _ = fit_stages(traj, settings, Priors(), np.random.default_rng(0), labels=traj.labels_true)
    st = stages[sel].state
    obs, _, _ = normalise(traj.xy)
    ratio = refine.misfit_ratios(st, obs, Priors())
    sticks = [tuple(np.flatnonzero(st.labels == s)) for s in range(st.n_sticks)]
    rigid = {sticks[s] for s in np.flatnonzero(ratio <= refine.SUSPECT_MISFIT)}
    assert st.n_sticks == 4 and len(rigid) == 2
    tried = []
    dissolve = refine.dissolve_stick

    def record(state, obs_, priors, s):
        tried.append(tuple(np.flatnonzero(state.labels == s)))
        return dissolve(state, obs_, priors, s)

    monkeypatch.setattr(refine, "dissolve_stick", record)

    def check(**kw):
        tried.clear()
        refine.heldout_dissolve(st, obs, Priors(), settings, np.random.default_rng(0), stages[sel].objective, 3,
                                0.15, **kw)
        return set(tried)

    assert check(free_points=2).isdisjoint(rigid)
    assert rigid <= check(free_points=None)  # without the gate every 3-point stick is offered
    # A stick whose fit turns suspect is offered.
    first = sorted(rigid)[0]
    ratios = refine.misfit_ratios

    def suspect(state, o, p):
        out = ratios(state, o, p)
        out[state.labels[first[0]]] = 2.0
        return out

    monkeypatch.setattr(refine, "misfit_ratios", suspect)
    got = check(free_points=2)
    assert first in got and got.isdisjoint(rigid - {first})


@pytest.mark.parametrize("kw,free,largest", [({}, 2, 3), ({"holdout_points": 3}, 3, 3),
                                             ({"dissolve_points": 2}, 2, 2)])
def test_heldout_points_reaches_the_check(chain, monkeypatch, kw, free, largest):
    # The estimator's holdout_points is the check's free_points; dissolve_points bounds both.
    from stickfigure.models.em import refine

    seen = []
    check = refine.heldout_dissolve

    def record(st, obs, priors, settings, rng, value, max_points, *args, **kwargs):
        seen.append((kwargs["free_points"], max_points))
        return check(st, obs, priors, settings, rng, value, max_points, *args, **kwargs)

    monkeypatch.setattr(refine, "heldout_dissolve", record)
    EMSkeleton(random_state=0, labels=chain.labels_true, n_iter=30, n_jobs=1, **kw).fit(chain)
    assert seen == [(free, largest)]


@pytest.mark.parametrize("kw,axes", [({}, 1), ({"split_axes": 3}, 3)])
def test_split_axes_reaches_the_articulated_splits(chain, monkeypatch, kw, axes):
    # The estimator's split_axes is the cut family of the articulated splits.
    from stickfigure.models.em import refine

    seen = set()
    candidates = refine.articulated_split_candidates

    def record(*args, **kwargs):
        seen.add(kwargs["n_axes"])
        return candidates(*args, **kwargs)

    monkeypatch.setattr(refine, "articulated_split_candidates", record)
    EMSkeleton(random_state=0, labels=chain.labels_true, n_iter=30, n_jobs=1, **kw).fit(chain)
    assert seen == {axes}


def test_true_joints_are_rigid(chain):
    from stickfigure.models.em import fit_stages
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.structure import EMSettings, rigid_joints

    stages, sel, _, _ = fit_stages(chain, EMSettings(n_iter=100), Priors(), np.random.default_rng(0),
                                   labels=chain.labels_true)
    st = stages[sel].state
    obs, _, _ = normalise(chain.xy)
    shared = np.bincount(st.vertex_of) >= 2
    assert shared.sum() == 2 and rigid_joints(st, obs).all()


def test_jointed_pair_with_swapped_points_is_resplit(chain):
    # Two jointed parts each given some of the other's points (the two farthest of one, the
    # farthest of the other): with resampling off, EM and the merge search keep them (each
    # stick's motion is fitted to its wrong points too). The pair re-split fits their union as
    # one body and cuts it into two jointed pieces; that moves most of them back.
    T = chain.labels_true
    a, b = chain.edges_true[0]
    ia, ib = _by_distance_to_first_joint(chain)
    labels = T.copy()
    labels[ia[-2:]] = b
    labels[ib[-1:]] = a
    kw = dict(random_state=0, labels=labels, resample_every=0, refine_sticks=False, n_iter=100, dissolve_points=0)
    kept = sf.fit(chain, method="em", resplit=False, **kw)
    assert adjusted_rand_score(T, kept.labels) < 0.75
    sk = sf.fit(chain, method="em", **kw)
    assert adjusted_rand_score(T, sk.labels) > 0.85
    assert max(s["moved"] for s in sk.info["stages"]) >= 3 and sk.info["selected_stage"] == len(sk.info["stages"]) - 1
    # The re-split leaves the tree one link off; the sub-tree move (tree.py) puts it right.
    assert _edges(sk, chain) == _true_edges(chain)
    from stickfigure.plot.em import stage_kind

    kinds = [stage_kind(s, k) for k, s in enumerate(sk.info["stages"])]
    assert kinds[0] == "EM" and kinds[-2:] == ["re-split", "sub-tree moves"]


# ----------------------------------------------------------------- missing data
def _rigid_body(n: int, F: int, seed: int) -> np.ndarray:
    """A rigid 3D body of n points turning smoothly, seen orthographically: (n, F, 2)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 3)) * np.array([1.0, 0.7, 0.5])
    ang = np.cumsum(rng.normal(scale=0.05, size=(F, 3)), axis=0) + rng.normal(size=3)
    from stickfigure.geometry import rotation_from_vectors as _rodrigues

    R = _rodrigues(ang)[:, :2, :]
    t = np.cumsum(rng.normal(scale=0.02, size=(F, 2)), axis=0)
    return np.einsum("fdk,nk->nfd", R, X) + t[None]


@pytest.mark.parametrize("pattern", ["whole frames hidden", "75% withheld"])
def test_stick_sfm_leaves_missing_entries_out(pattern):
    """Per-stick SfM with gaps predicts the hidden entries (it started such sticks flat and face-on)."""
    from stickfigure.models.em.initialise import stick_sfm
    from stickfigure.models.em.model import normalise

    xy = _rigid_body(8, 80, seed=3)
    rng = np.random.default_rng(0)
    hide = np.zeros(xy.shape[:2], bool)
    if pattern == "whole frames hidden":
        hide[:, 30:36] = True  # the whole stick behind an occluder
        hide |= rng.random(hide.shape) < 0.05
    else:
        hide = rng.random(hide.shape) < 0.75
        hide[np.arange(8), rng.integers(0, 80, 8)] = False
    obs, centre, scale = normalise(np.where(hide[..., None], np.nan, xy))
    rot, trans, local = stick_sfm(obs, np.zeros(8, np.int64), 1, np.random.default_rng(0))
    pred = np.einsum("fdk,pk->pfd", rot[0], local) + trans[0]
    truth = (xy - centre) / scale
    d2 = np.sum((pred - truth) ** 2, axis=-1)
    if pattern == "whole frames hidden":  # exact elsewhere; the hidden frames interpolated
        out = np.zeros_like(hide)
        out[:, 30:36] = True
        assert np.sqrt(np.mean(d2[hide & ~out])) < 1e-4  # was 0.22 (started flat)
        assert np.sqrt(np.mean(d2[out])) < 0.2  # was 0.30
    else:
        assert np.sqrt(np.mean(d2[hide])) < 0.2  # was 0.85


def test_sparse_stick_start_factorises_the_given_completion():
    """75 % withheld: with ``Observations.filled`` (the scene's completion) the SfM start
    factorises it instead of the stick's trajectories interpolated in time; given the true
    trajectories as the completion, the start predicts the hidden entries far better, and
    subsets of points or frames carry the completion with them."""
    from stickfigure.models.em.initialise import stick_sfm
    from stickfigure.models.em.model import normalise

    xy = _rigid_body(8, 80, seed=3)
    rng = np.random.default_rng(0)
    hide = rng.random(xy.shape[:2]) < 0.75
    hide[np.arange(8), rng.integers(0, 80, 8)] = False
    obs, centre, scale = normalise(np.where(hide[..., None], np.nan, xy))
    truth = (xy - centre) / scale

    def hidden_rms(o):
        rot, trans, local = stick_sfm(o, np.zeros(o.n_points, np.int64), 1, np.random.default_rng(0))
        pred = np.einsum("fdk,pk->pfd", rot[0], local) + trans[0]
        return np.sqrt(np.mean(np.sum((pred - truth[:, :o.n_frames]) ** 2, axis=-1)[hide[:, :o.n_frames]]))

    interpolated = hidden_rms(obs)
    obs.filled = truth
    assert hidden_rms(obs) < 0.25 * interpolated  # 0.0065 against 0.077
    np.testing.assert_array_equal(obs.take(np.array([1, 3])).filled, truth[[1, 3]])
    np.testing.assert_array_equal(obs.take_frames(np.arange(0, 80, 2)).filled, truth[:, ::2])


def test_start_spread_is_capped_by_the_largest_2d_radius():
    """A start axis far longer than anything the projections ever show is shrunk to 2x their radius."""
    from stickfigure.models.em.initialise import MAX_DEPTH_RATIO, _bound_spread

    xy = _rigid_body(8, 40, seed=1)
    r2 = np.sqrt(np.max(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=-1), axis=0)))
    rng = np.random.default_rng(0)
    shape = rng.normal(size=(8, 3)) * np.array([0.3, 0.2, 190.0])  # a near-singular metric upgrade
    out = _bound_spread(shape, xy)
    spreads = np.sqrt(np.linalg.eigvalsh(np.cov((out - out.mean(0)).T, bias=True)))
    assert spreads.max() <= MAX_DEPTH_RATIO * r2 * (1 + 1e-9)
    np.testing.assert_allclose(out.mean(0), shape.mean(0))
    ok = rng.normal(size=(8, 3)) * 0.1 * r2  # a plausible shape is left alone
    np.testing.assert_array_equal(_bound_spread(ok, xy), ok)


def test_fill_gaps_interpolates_interior_gaps_only():
    from stickfigure.models.em.initialise import fill_gaps

    xy = np.arange(12, dtype=float).reshape(1, 6, 2)
    xy[0, [0, 2, 3]] = np.nan
    out = fill_gaps(xy, ends=False)
    np.testing.assert_allclose(out[0, 2:4], [[4.0, 5.0], [6.0, 7.0]])
    assert np.isnan(out[0, 0]).all()
    np.testing.assert_allclose(fill_gaps(xy)[0, 0], xy[0, 1])


def _withheld(traj: sf.Trajectories, seed: int, fraction: float = 0.75) -> sf.Trajectories:
    """``traj`` with ``fraction`` of its entries hidden at random (generator ``seed``); every
    point keeps at least one observation (the protocol of the paper's 75 %-withheld claim)."""
    rng = np.random.default_rng(seed)
    hide = rng.random(traj.xy.shape[:2]) < fraction
    hide[np.arange(traj.n_points), rng.integers(0, traj.n_frames, traj.n_points)] = False
    return traj.with_xy(np.where(hide[..., None], np.nan, traj.xy), allow_unobserved=False)


@pytest.mark.parametrize("seed", [16, 18])
def test_first_groups_of_sparse_data_come_from_the_smooth_completion(seed):
    """75 % withheld: grouped on the smooth low-rank completion, the 4 parts come out exactly
    (on these two figures interpolation in time gave ARI 0.66 and 0.72; docs/em.md section 5)."""
    from stickfigure.models.em import _initial_groups

    traj = sf.synthetic.random_figure(n_sticks=4, frames=120, noise=0.01, seed=seed, points_per_stick=(5, 9))
    train, _ = traj.split(0.7)
    sparse = _withheld(train, seed=5)
    labels, info = _initial_groups(sparse, 12, np.random.default_rng(0))
    assert info["input"] == "smooth low-rank completion"
    assert adjusted_rand_score(traj.labels_true, labels) == 1.0


def test_first_groups_of_sparse_data_fall_back_to_interpolation_when_it_predicts_better():
    # Independent random walks (no low-rank structure; for a random walk the best guess inside a
    # gap is the straight line between its ends): interpolation in time predicts the held-out
    # entries better than a rank-16 factorisation, and is used.
    from stickfigure.models.em import _initial_groups

    rng = np.random.default_rng(1)
    xy = np.cumsum(rng.normal(size=(30, 200, 2)), axis=1)
    xy[rng.random(xy.shape[:2]) < 0.6] = np.nan
    _, info = _initial_groups(sf.Trajectories(xy), 12, np.random.default_rng(0))
    assert info["input"].startswith("gaps interpolated")
    assert info["completion"]["interpolation_rmse"] < min(info["completion"]["holdout_rmse"].values())
    assert info["completion"]["method"] == "interpolation"


@pytest.mark.parametrize("seed", [25, 30])
def test_sparse_training_keeps_the_last_true_joint(seed):
    """75 % withheld: the merge that completes the true tree is kept. The loose-joint test
    (``structure.rigid_joints``) charged closing a joint's gap by the sticks' sizes in every
    frame; a stick showing a point or none moves almost or entirely for free there, so true
    joints read as loose, the last merge saved no parameters in BIC and was not selected (one
    edge missing on both figures; docs/em.md section 11)."""
    traj = sf.synthetic.random_figure(n_sticks=4, frames=120, noise=0.01, seed=seed, points_per_stick=(5, 9))
    train, _ = traj.split(0.7)
    sparse = _withheld(train, seed=5)
    sk = sf.fit(sparse, method="em", random_state=3)
    assert adjusted_rand_score(traj.labels_true, sk.labels) == 1.0
    assert _edges(sk, traj) == _true_edges(traj)


def test_sparse_training_keeps_the_groups(chain):
    """Given the true groups, 75% of the training observations withheld: no stick is joined or lost.

    (The per-stick start used to begin every stick hidden in some frame flat, and EM let
    frames showing one or two points turn freely, which blew the sticks' depth up.)
    """
    sparse = _withheld(chain, seed=2)
    sk = sf.fit(sparse, method="em", random_state=0, labels=chain.labels_true, n_iter=60)
    assert sk.n_sticks == 3
    assert adjusted_rand_score(chain.labels_true, sk.labels) == 1.0
    rms = np.sqrt(np.nanmean(np.sum((sk.predict() - chain.xy) ** 2, axis=-1)))  # hidden entries too
    spread = np.sqrt(np.mean(np.sum((chain.xy - np.nanmean(chain.xy, axis=(0, 1))) ** 2, axis=-1)))
    assert rms < 0.1 * spread


def _imputation_rmse(method: str, train: sf.Trajectories, test: sf.Trajectories, seed: int) -> tuple[float, sf.Skeleton]:
    from stickfigure.models import get_method

    occluded, hidden = sf.synthetic.occlude(test, seed=seed)
    sk = sf.fit(train, method=method, random_state=seed)
    filled = np.asarray(get_method(method).impute_skeleton(sk, occluded))
    d = filled[hidden] - test.xy[hidden]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1)))), sk


@pytest.mark.slow
@pytest.mark.parametrize("condition", ["occluded", "75% withheld"])
def test_training_with_missing_data_recovers_structure_and_imputes(condition):
    """Ross et al.'s robustness claim: trained on occluded or sparse data (75% of the
    observations withheld), the figure's structure is recovered and the held-out
    occluded entries are imputed better than by multibody SfM.

    Before the missing-data fixes the 75% case ended with one stick; with the first groups
    from the smooth completion (session 33) the tree was right but a stick took points of
    another part (ARI 0.79), because the SfM start of a sparse stick fitted 18 times worse than
    the noise and the articulated split cut it. With the sticks started from the completion
    too (session 34) it comes out exactly. The paper's claim holds on about two thirds of
    such figures here, not all (docs/em.md section 11)."""
    traj = sf.synthetic.random_figure(n_sticks=4, frames=120, noise=0.01, seed=11, points_per_stick=(5, 9))
    train, test = traj.split(0.7)
    if condition == "occluded":
        train, _ = sf.synthetic.occlude(train, seed=6)
    else:
        train = _withheld(train, seed=5)
    em, sk = _imputation_rmse("em", train, test, seed=3)
    mb, _ = _imputation_rmse("multibody-sfm", train, test, seed=3)
    assert adjusted_rand_score(traj.labels_true, sk.labels) > 0.9
    assert _edges(sk, traj) == _true_edges(traj)
    assert em < mb  # (the 0.7x mean-ratio target is checked over scenes by benchmarks/bench_em.py)


def test_impute_does_not_mirror_a_stick_from_coplanar_visible_points():
    """Where the visible points of a stick are nearly coplanar, the mirror image of the stick
    fits them as well as the stick does; the start then comes from the neighbouring frames,
    not from a Procrustes fit that may take the mirror (hidden points thrown across)."""
    rng = np.random.default_rng(4)
    n, F = 8, 80
    X = rng.normal(size=(n, 3)) * 0.5
    X[:5, 2] = 0.0  # five points on a plane, three off it
    X[5:, 2] = np.array([0.6, -0.5, 0.7])
    from stickfigure.geometry import rotation_from_vectors as _rodrigues

    ang = np.cumsum(rng.normal(scale=0.04, size=(F, 3)), axis=0) + np.array([0.3, 0.5, 0.1])
    xy = np.einsum("fdk,nk->nfd", _rodrigues(ang)[:, :2, :], X) + 0.003 * rng.normal(size=(n, F, 2))
    traj = sf.Trajectories(xy, labels_true=np.zeros(n, np.int64))
    train, test = traj.split(0.7)
    sk = sf.fit(train, method="em", random_state=0, labels=np.zeros(n, np.int64), refine_sticks=False,
                resample_every=0, articulated_rounds=0, n_iter=60)
    hidden = np.zeros(test.xy.shape[:2], bool)
    hidden[5:, 3:21:2] = True  # only the coplanar five visible in every other frame
    filled = sk.impute(test.with_xy(np.where(hidden[..., None], np.nan, test.xy), allow_unobserved=True))
    err = np.sqrt(np.sum((filled[hidden] - test.xy[hidden]) ** 2, axis=-1))
    assert err.max() < 0.1


def _cmu_isometric(data_dir):
    traj = sf.load(data_dir / "mocap" / "85_02.c3d").drop_unobserved().subsample(4).project("isometric")
    return traj, sf.fit(traj, method="em", random_state=0)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known limitation (docs/em.md section 11): this view now gives a body tree "
                                       "of 10 sticks, coarser than the 15 segments (both thigh markers on the pelvis "
                                       "stick, each shin with its foot): ARI 0.452, edge F1 0.381")
def test_cmu_isometric_view_follows_the_segments(data_dir):
    # Real-data known answer: CMU 85_02 (41 markers, 30 Hz, 203 frames), isometric view, scored
    # against the marker set's 15 segments. Not met at any commit checked in session 17 (when the
    # slow tests were run again), back to the parent of d53b263 (ARI 0.490): 9 sticks, ARI 0.531,
    # edge F1 0.381 before the hub splits (6953e5a), 10 sticks, 0.452 / 0.381 since, with every
    # stick one piece of the body and every edge anatomical (test_cmu_isometric_view_gives_a_body_tree).
    # Strict, so that meeting it again is noticed. Earlier, it was met once the compiled EM loops
    # re-rolled the search (docs/em.md section 11): 16 sticks in one tree, ARI 0.608, edge F1 0.64 (it was
    # 15 sticks, 0.530 / 0.56 with numpy 2.4.6 before them). Measured earlier with cuts across
    # a stick's major axis only (split_axes=1): 15 sticks, ARI 0.530, edge F1 0.720; 11 of 14
    # edges anatomical, 14 of 15 sticks one piece of the body (LTHI+STRN is not). With cuts along every axis: 13 sticks,
    # 0.631 / 0.583, 10 of 12 and 12 of 13; with every 3-point stick offered to the held-out
    # check: 12 sticks, 0.554 / 0.522; before the check hid occlusion-like gaps: 8 sticks,
    # 0.487 / 0.381.
    traj, sk = _cmu_isometric(data_dir)
    s = score_skeleton(sk, traj)
    assert sk.n_sticks >= 10
    assert s["ari"] > 0.5 and s["edge_f1"] > 0.6


@pytest.mark.slow
def test_cmu_isometric_view_keeps_its_sticks_on_the_body(data_dir):
    # Met before 6894afb (15 sticks, 11 of 14 edges anatomical, 14 of 15 sticks one piece of
    # the body), lost with it (LTHI and RTHI on 2-point sticks with STRN and T10), met again
    # since the compiled EM loops re-rolled the search: 12 of 15 edges anatomical, 15 of 16
    # sticks one piece of the body.
    traj, sk = _cmu_isometric(data_dir)
    s = score_skeleton(sk, traj)
    assert s["anatomical_edges"] > 0.75 and s["coherent_sticks"] > 0.9


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known limitation (docs/em.md section 11, session 32): with hub_end (the "
                                       "default) the lone LTHI hangs from the thorax stick CLAV+STRN+C7+T10 (12 "
                                       "sticks, 10 of 11 edges anatomical); with hub_end=False a body tree")
def test_cmu_isometric_view_gives_a_body_tree(data_dir):
    # What a body tree means: every stick holds markers of one connected piece of the body
    # (pelvis with the thigh markers, the shank with the foot, ...), and every edge joins two
    # sticks whose segments meet in the body. The held-out check with entries hidden one at a
    # time met this here (8 sticks, all 7 edges anatomical) but was coarser and imputed worse
    # (docs/em.md section 11). Met again (it was a strict xfail, found passing in session 17) at
    # every commit checked then, from the parent of fa998b6: 9 sticks, then 10 since the hub
    # splits (6953e5a), every edge anatomical.
    traj, sk = _cmu_isometric(data_dir)
    s = score_skeleton(sk, traj)
    assert sk.n_sticks >= 6 and len(sk.edges) >= 5
    assert s["coherent_sticks"] == 1.0 and s["anatomical_edges"] == 1.0


@functools.lru_cache(maxsize=1)
def _cmu_whole_take(data_dir):
    traj = sf.load(data_dir / "mocap" / "85_02.c3d").drop_unobserved().project("isometric")
    return traj, sf.fit(traj, method="em", random_state=0)


@pytest.mark.slow
def test_cmu_whole_take_at_its_own_rate_follows_the_segments(data_dir):
    # The same take whole, at its own 120 Hz (810 frames; the search sees 400 of them): twice the
    # frames of the 30 Hz clip above for the same motion. Measured (split_dissolved=4): 15 sticks
    # in one tree, every stick one piece of the body, ARI 0.580, edge F1 0.538; 12 of 14 edges
    # anatomical. Without the split after the held-out check: 12 sticks, ARI 0.570, edge F1
    # 0.500, 10 of 11 (the right toe RMT5+RTOE hung from RBAC+RSHO+RUPA). With cuts along every
    # axis it was a body tree of 11 sticks, ARI 0.508, edge F1 0.364.
    traj, sk = _cmu_whole_take(data_dir)
    s = score_skeleton(sk, traj)
    assert sk.n_sticks >= 10 and len(sk.edges) == sk.n_sticks - 1  # one tree
    assert s["coherent_sticks"] == 1.0 and s["anatomical_edges"] > 0.85 and s["edge_f1"] > 0.45


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known limitation (docs/em.md section 11, session 32): with hub_end (the "
                                       "default) the two shins RKNE+RSHN and LKNE+LSHN are joined (15 sticks, 13 of "
                                       "14 edges anatomical); with hub_end=False a body tree")
def test_cmu_whole_take_at_its_own_rate_gives_a_body_tree(data_dir):
    # A body tree: one tree, every stick one piece of the body, every edge anatomical.
    # em-structure-mocap-views gives the side and front views. Met since the greedy trials draw
    # from their own generators (6894afb): 14 sticks in one tree, ARI 0.587, edge F1 0.583
    # (before: the right shin RKNE+RSHN joined to the left shin, and the left finger LFIN alone
    # to LFWT+LTHI).
    traj, sk = _cmu_whole_take(data_dir)
    s = score_skeleton(sk, traj)
    assert sk.n_sticks >= 8 and len(sk.edges) == sk.n_sticks - 1  # one tree
    assert s["coherent_sticks"] == 1.0 and s["anatomical_edges"] == 1.0


@pytest.mark.parametrize("remerge", [True, False])
def test_search_resumes_after_a_dissolution(monkeypatch, capsys, remerge):
    # A dissolution kept by the held-out check can leave the trees it linked apart (on the whole
    # CMU take a camera kept 7 trees). Here the check is replaced by one that cuts a true joint
    # of the selected tree (as a dissolved stick's lost joint would): with remerge the merge
    # search goes on from that forest and joins the figure again; without it the cut stays.
    from stickfigure.models.em import refine, structure
    from stickfigure.models.em.tree import detach_endpoint

    def cut_a_joint(st, obs, priors, settings, rng, value, *args, **kwargs):
        shared = np.flatnonzero(st.vertex_counts() >= 2)
        e = int(np.flatnonzero(st.vertex_of == shared[0])[0])
        out, val, n = structure.run_em(detach_endpoint(st, e, priors), obs, priors, settings, 50, rng,
                                       resample=False)
        return out, val, n, [[0]], {"fraction": 0.15, "error_before": 1.0, "error_after": 0.5}

    monkeypatch.setattr(refine, "heldout_dissolve", cut_a_joint)
    traj = sf.synthetic.random_figure(n_sticks=4, frames=80, noise=0.01, seed=2)
    sk = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, n_iter=80, refine_sticks=False,
                resplit=False, resample_every=0, reattach=False, remerge=remerge, progress=True)
    stages = sk.info["stages"]
    # The resumed search's merges are counted on from the first search's (3 merges, then 1).
    err = capsys.readouterr().err
    assert "stage 3 of 3" in err and ("stage 4 of 4" in err) == remerge
    cut = [i for i, s in enumerate(stages) if s["heldout"] is not None]
    assert len(cut) == 1 and len(stages[cut[0]]["edges"]) == 2
    truth = {tuple(sorted(e)) for e in traj.edges_true}
    if remerge:
        assert len(stages) == cut[0] + 2 and stages[-1]["merged"] is not None
        assert sk.info["selected_stage"] == cut[0] + 1
        assert {tuple(sorted(e)) for e in sk.edges} == truth
    else:
        assert len(stages) == cut[0] + 1 and sk.info["selected_stage"] == cut[0]
        assert len(sk.edges) == 2 and {tuple(sorted(e)) for e in sk.edges} < truth


@pytest.mark.parametrize("split_dissolved", [4, 0])
def test_a_stick_that_took_a_dissolved_segment_is_split_before_the_resumed_search(monkeypatch, split_dissolved):
    # The held-out check is replaced by one that leaves a 2-point segment's points on its
    # parent's stick (as the dissolution of a CMU thigh put LTHI on the pelvis). With
    # split_dissolved the parent is split at their joint before the search goes on, and the
    # figure is recovered; without it the merged stick stays.
    from stickfigure.models.em import refine, structure
    from stickfigure.models.em.initialise import initial_state

    traj = sf.synthetic.random_figure(n_sticks=4, frames=80, noise=0.01, seed=11, points_per_stick=6)
    a, b = traj.edges_true[0]
    keep = np.ones(traj.n_points, bool)
    keep[np.flatnonzero(traj.labels_true == b)[2:]] = False
    traj = traj.slice(points=keep)
    truth = traj.labels_true
    _, merged = np.unique(np.where(truth == b, a, truth), return_inverse=True)

    def absorb(st, obs, priors, settings, rng, value, *args, **kwargs):
        out = initial_state(obs, merged, 3, priors, rng, n_ends=settings.n_ends)
        out, val, n = structure.run_em(out, obs, priors, settings, 100, rng, resample=False)
        return out, val, n, [np.flatnonzero(truth == b).tolist()], {"fraction": 0.15, "error_before": 1.0,
                                                                    "error_after": 0.5}

    monkeypatch.setattr(refine, "heldout_dissolve", absorb)
    sk = sf.fit(traj, method="em", random_state=0, labels=truth, n_iter=80, refine_sticks=False, resplit=False,
                resample_every=0, reattach=False, split_dissolved=split_dissolved, bridge_points=0)
    cut = [s for s in sk.info["stages"] if s["heldout"] is not None]
    assert len(cut) == 1
    if split_dissolved:
        assert cut[0]["split"] == [int(merged[np.flatnonzero(truth == a)[0]])] and cut[0]["n_sticks"] == 4
        assert sk.n_sticks == 4 and adjusted_rand_score(truth, sk.labels) > 0.9
        assert _edges(sk, traj) == _true_edges(traj)
    else:
        assert cut[0]["split"] == [] and cut[0]["n_sticks"] == 3 and sk.n_sticks == 3


def test_leaves_scope_keeps_a_stick_between_two_joints(chain):
    # dissolve_scope="leaves": a stick with endpoints on two joints (a thigh between the pelvis
    # and the shin) is never offered to the dissolutions; the two end sticks of the chain are.
    from stickfigure.models.em import fit_stages
    from stickfigure.models.em.model import Priors
    from stickfigure.models.em.refine import _next_small_stick
    from stickfigure.models.em.structure import EMSettings, stick_edges

    stages, sel, _, _ = fit_stages(chain, EMSettings(n_iter=100), Priors(), np.random.default_rng(0),
                                   labels=chain.labels_true)
    state = stages[sel].state
    edges, _ = stick_edges(state)
    assert state.n_sticks == 3 and len(edges) == 2
    middle = [s for s in range(3) if sum(s in e for e in edges) == 2][0]
    assert state.joints_per_stick().tolist() == [2 if s == middle else 1 for s in range(3)]
    order = np.arange(3)
    got, tried = [], set()
    while (nxt := _next_small_stick(state, order, 100, tried, "leaves")) is not None:
        got.append(nxt[0])
    assert sorted(got) == sorted(set(range(3)) - {middle})
    assert _next_small_stick(state, np.array([middle]), 100, set(), "all")[0] == middle
    with pytest.raises(ValueError, match="scope"):
        _next_small_stick(state, order, 100, set(), "middle")


def _bare_state(labels, local, ends, vertex_of, rot, trans):
    """A StickState with the variables joint_support reads; the rest are zeros."""
    from stickfigure.models.em.model import StickState

    J, (_, F, D) = int(np.max(vertex_of)) + 1, trans.shape
    zeros = np.zeros
    return StickState(labels=labels, vertex_of=vertex_of, rot=rot, trans=trans, local=local, ends=ends,
                      mu_e=zeros((len(ends), F, D)), tau_e=zeros(len(ends)), mu_v=zeros((J, F, D)),
                      tau_v=zeros((J, F)), alpha=zeros(J), beta=zeros(J), tau_w=1.0, tau_m=1.0, tau_t=1.0)


def test_joint_support_measures_reach_and_gap_of_a_hand_built_joint():
    from stickfigure.models.em.structure import joint_support

    F = 6
    rot = np.broadcast_to(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (2, F, 2, 3)).copy()
    # Stick 1's endpoint on the joint misses stick 0's by (0.3, 0.4) or (-0.3, -0.4): 0.5 in every frame.
    miss = np.where(np.arange(F)[:, None] % 2 == 0, [0.3, 0.4], [-0.3, -0.4])
    trans = np.stack([np.zeros((F, 2)), np.array([3.0, 0.5]) + miss])
    st = _bare_state(vertex_of=np.array([0, 1, 0, 2]), labels=np.array([0, 0, 1, 1]),
                     local=np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 2, 0]]),
                     ends=np.array([[3.0, 0, 0], [-1, 0, 0], [0, -0.5, 0], [0, 5, 0]]), rot=rot, trans=trans)
    reach, gap = joint_support(st, [(0, 1)], [0])
    np.testing.assert_allclose(reach, [[2.0, 0.5]])  # 3 - 1 on stick 0, 0.5 below stick 1's first point
    np.testing.assert_allclose(gap, [0.5])


def test_joint_support_of_a_recovered_chain(chain, fitted):
    sk = fitted.skeleton_
    js = sk.info["joint_support"]
    assert js["edges"] == [list(e) for e in sk.edges]
    reach, gap = np.asarray(js["reach"]), np.asarray(js["gap"])
    assert reach.shape == (len(sk.edges), 2) and gap.shape == (len(sk.edges),)
    # A true joint: the sticks meet to within the noise.
    assert np.all(gap < 5 * chain.meta["noise_std"])
    assert 0 < js["figure_radius"] < np.inf
    # The true joint's image distance to a stick's nearest point is at most its 3D distance (orthographic), and
    # as the stick turns it comes near it: the largest over frames is the reach, up to noise.
    names = _edges_map(sk, chain)
    for (a, b), r in zip(sk.edges, reach):
        te = tuple(sorted((names[a], names[b])))
        J = chain.joints_true[[i for i, t in enumerate(chain.edges_true) if tuple(sorted(t)) == te][0]]
        for s, rs in zip((a, b), r):
            image = np.min(np.linalg.norm(chain.xy[sk.labels == s] - J[None], axis=-1), axis=0).max()
            assert 0.8 * image < rs < 1.2 * image


def test_joint_support_leaves_a_stick_without_points_out():
    from types import SimpleNamespace

    from stickfigure.models.em import mid_air
    from stickfigure.models.em.structure import joint_support

    F = 4
    rot = np.broadcast_to(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (2, F, 2, 3)).copy()
    st = _bare_state(vertex_of=np.array([0, 1, 0, 2]), labels=np.array([0, 0]),
                     local=np.array([[0.0, 0, 0], [1, 0, 0]]),
                     ends=np.array([[3.0, 0, 0], [-1, 0, 0], [0, 0, 0], [0, 1, 0]]), rot=rot, trans=np.zeros((2, F, 2)))
    reach, gap = joint_support(st, [(0, 1)], [0])
    assert reach[0, 0] == pytest.approx(2.0) and np.isnan(reach[0, 1])
    js = {"reach": reach.tolist() + [[1.0, 3.0]], "gap": gap.tolist() + [0.0], "figure_radius": 4.0}
    # The joint of the stick without points is not judged; the other joint is 1.0 from its nearer stick.
    assert mid_air(SimpleNamespace(info={"joint_support": js})) == pytest.approx(0.25)


@pytest.mark.parametrize("bad", [0, -1.0, True, "far", float("nan")])
def test_retry_mid_air_must_be_a_positive_number(chain, bad):
    with pytest.raises(ValueError, match="retry_mid_air"):
        EMSkeleton(retry_mid_air=bad, labels=chain.labels_true, n_iter=5).fit(chain)


def test_retry_mid_air_searches_again_and_keeps_the_skeleton_with_the_nearer_joints(chain):
    from stickfigure.models.em import mid_air

    kw = dict(random_state=0, labels=chain.labels_true, n_iter=60)
    plain = EMSkeleton(**kw).fit(chain).skeleton_  # off by default
    assert "retry" not in plain.info
    sk = EMSkeleton(retry_mid_air=1e-9, **kw).fit(chain).skeleton_  # every joint is beyond that
    retry = sk.info["retry"]
    assert retry["n_ends"] == [3, 4] and retry["mid_air"][0] == pytest.approx(mid_air(plain))
    kept = 0 if retry["kept"] == "first" else 1
    assert retry["mid_air"][kept] == min(retry["mid_air"]) and retry["mid_air"][kept] == pytest.approx(mid_air(sk))
    # hub_end (the default) gives every stick one endpoint more in the state.
    assert np.asarray(sk.state["ends"]).shape == (sk.n_sticks * (retry["n_ends"][kept] + 1), 3)
    if kept == 0:  # the first search is the one a fit without the retry makes
        np.testing.assert_array_equal(sk.labels, plain.labels)
        np.testing.assert_allclose(sk.local, plain.local)
    # A threshold no joint reaches: no second search, the plain skeleton.
    far = EMSkeleton(retry_mid_air=1e9, **kw).fit(chain).skeleton_
    assert "retry" not in far.info
    np.testing.assert_allclose(far.local, plain.local)


# The options that keep given groups as the sticks (the ``labels`` docstring names them).
KEEP_GROUPS = dict(refine_sticks=False, resample_every=0, resplit=False, dissolve_points=0, unpair=False,
                   bridge_points=0, split_hubs=False)


def test_given_labels_are_kept_with_every_group_move_off():
    """The options the ``labels`` docstring names keep the given groups as the sticks; the
    defaults do not (here they join the five small sticks into one)."""
    from sklearn.metrics import adjusted_rand_score

    t = sf.synthetic.random_figure(5, 60, seed=1, points_per_stick=(1, 3), noise=0.02)
    kept = sf.fit(t, method="em", random_state=0, labels=t.labels_true, n_iter=60, **KEEP_GROUPS)
    assert kept.n_sticks == t.n_parts_true and adjusted_rand_score(t.labels_true, kept.labels) == 1.0
    moved = sf.fit(t, method="em", random_state=0, labels=t.labels_true, n_iter=60)
    assert adjusted_rand_score(t.labels_true, moved.labels) < 1.0


@pytest.mark.parametrize("bad", [dict(merge_rank="bic"), dict(align_mirrors="yes")])
def test_merge_rank_and_align_mirrors_are_checked(chain, bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        EMSkeleton(labels=chain.labels_true, n_iter=5, **bad).fit(chain)


@pytest.mark.parametrize("seed", [3, 11])
def test_residual_ranking_joins_given_segments_into_their_tree(seed):
    """Known answer: the segments given and kept, the joints ranked by their least-squares residual
    (mirrors aligned) give the figure's own tree; the fit does not leave the switch on."""
    from stickfigure.metrics import score_skeleton
    from stickfigure.models.em import updates

    t = sf.synthetic.random_figure(5, 80, seed=seed, noise=0.01)
    sk = sf.fit(t, method="em", random_state=0, labels=t.labels_true, n_iter=60, merge_rank="residual",
                align_mirrors=True, **KEEP_GROUPS)
    assert sk.n_sticks == t.n_parts_true and len(sk.edges) == t.n_parts_true - 1
    assert score_skeleton(sk, t)["edge_f1"] == 1.0
    assert sk.info["settings"]["merge_rank"] == "residual" and sk.info["settings"]["align_mirrors"] is True
    assert updates._mirror_tie is None


def _smooth_rotations(rng: np.random.Generator, F: int) -> np.ndarray:
    from stickfigure.geometry import rotation_from_vectors

    ang = np.cumsum(rng.normal(scale=0.05, size=(F, 3)), axis=0) + np.array([0.4, -0.6, 0.2])
    return rotation_from_vectors(ang)  # (F, 3, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_chain_mirrors_puts_flat_frames_in_one_branch(seed):
    from stickfigure.models.em.impute import chain_mirrors

    rng = np.random.default_rng(seed)
    F = 60
    R = _smooth_rotations(rng, F)[:, :2, :]
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    mirrored = R - 2.0 * np.einsum("kdi,i,j->kdj", R, n, n)
    pick = rng.random(F) < 0.5
    flat = np.ones(F, bool)
    flat[0] = False  # an anchor: its branch is known (the visible points span 3D there)
    pick[0] = False
    mixed = np.where(pick[:, None, None], mirrored, R)
    out = chain_mirrors(mixed, flat, np.tile(n, (F - 1, 1)))
    np.testing.assert_allclose(out, R, atol=1e-12)
    # Without an anchor the chain is one branch or the other, the same in every frame.
    out = chain_mirrors(mixed, np.ones(F, bool), np.tile(n, (F, 1)))
    assert np.allclose(out, R) or np.allclose(out, mirrored)
    # Frames that are not flat are never changed.
    np.testing.assert_array_equal(chain_mirrors(mixed, np.zeros(F, bool), np.zeros((0, 3))), mixed)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_impute_starts_a_three_point_stick_in_one_mirror_branch(seed):
    """Three points always lie in a plane, so every frame's Procrustes fit of a 3-point stick
    may take the mirror, and did in 13-26 of 80 frames here before the chain; a slerp between
    frames of the two branches threw a point hidden for a frame or two far off (HDM05: 606 mm
    on a thigh marker, docs/em.md section 11)."""
    from stickfigure.models.em.impute import start_state
    from stickfigure.models.em.model import Observations

    rng = np.random.default_rng(seed)
    F = 80
    X = np.array([[0.0, 0.0, 0.0], [0.9, 0.1, 0.0], [0.2, 1.4, 0.0]])
    X -= X.mean(axis=0)
    xy = np.einsum("fdk,nk->nfd", _smooth_rotations(rng, F)[:, :2, :], X) + 0.01 * rng.normal(size=(3, F, 2))
    st = start_state(np.zeros(3, np.int64), X, np.zeros((2, 3)), np.array([0, 1]), np.ones(2), np.ones(2),
                     (1e4, 1e4, 1.0), 1.0, Observations(xy, np.ones((3, F))))
    R = st.rot[0]  # (F, 2, 3)
    normal = np.cross(R[:, 0], R[:, 1])  # the third axis: it turns over where the branch flips
    assert np.all(np.einsum("fi,fi->f", normal[1:], normal[:-1]) > 0.5)
    # Every frame still fits the visible points (a mirror through their plane fits them equally).
    pred = np.einsum("fdk,nk->nfd", R, X) + st.trans[0][None]
    assert np.sqrt(np.mean((pred - xy) ** 2)) < 0.05
