"""Tests of the "mi-tree" method (Taycher, Fisher & Darrell)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

import stickfigure as sf
from stickfigure.models import mitree as M
from stickfigure.trajectories import Trajectories


# ----------------------------------------------------------------- the paper's synthetic experiments
def _points(rng, length, n):
    return rng.uniform(0.1, 0.9, n) * length + 1j * rng.uniform(-0.15, 0.15, n) * length


def _finish(A, B, loc, lab, rng, noise, edges, joints=None):
    z = A[lab] * loc[:, None] + B[lab]
    z = z + noise * (rng.normal(size=z.shape) + 1j * rng.normal(size=z.shape))
    j = None if joints is None else np.stack([joints.real, joints.imag], -1)
    return Trajectories(np.stack([z.real, z.imag], -1), labels_true=lab, edges_true=edges, joints_true=j)


def chain3(seed=0, frames=100, noise=1.0, n_pts=8):
    """The paper's Fig. 6.1: S1 moves freely, S2 turns about a revolute joint on S1, S3 slides
    along S2's axis (prismatic joint). Poses are independent random perturbations of the
    tree's parameters in every frame; pixel units, 1-pixel noise."""
    rng = np.random.default_rng(seed)
    L = 100.0
    loc = np.concatenate([_points(rng, L, n_pts) for _ in range(3)])
    lab = np.repeat(np.arange(3), n_pts)
    A = np.zeros((3, frames), complex)
    B = np.zeros((3, frames), complex)
    A[0] = np.exp(1j * rng.uniform(-0.5, 0.5, frames))
    B[0] = 300 + 300j + rng.normal(0, 20, frames) + 1j * rng.normal(0, 20, frames)
    A[1] = A[0] * np.exp(1j * rng.uniform(-1.2, 1.2, frames))
    B[1] = B[0] + A[0] * L
    A[2] = A[1] * np.exp(0.4j)
    B[2] = B[1] + A[1] * (rng.uniform(0, 60, frames) + 0.3 * L)
    joints = np.stack([B[1], B[2]])
    return _finish(A, B, loc, lab, rng, noise, [(0, 1), (1, 2)], joints)


def torso5(seed=0, frames=150, noise=1.0, n_pts=8, scale_jitter=0.1):
    """The paper's Fig. 6.2: a humanoid torso of 5 segments -- torso (0) with head (1), left
    upper arm (2) with forearm (3), right upper arm (4). Random perturbations of every
    joint angle and of each segment's SPM scale (foreshortening), 1-pixel noise."""
    rng = np.random.default_rng(seed)
    parent = [-1, 0, 0, 2, 0]
    lengths = np.array([120, 50, 70, 60, 70.0])
    attach = [0, 120 + 0j, 110 + 25j, 70 + 0j, 110 - 25j]
    rest = [np.pi / 2, 0.0, 2.0, 0.3, -2.0]
    loc = np.concatenate([_points(rng, lengths[s], n_pts) for s in range(5)])
    lab = np.repeat(np.arange(5), n_pts)
    A = np.zeros((5, frames), complex)
    B = np.zeros((5, frames), complex)
    for s in range(5):
        rot = (1 + rng.uniform(-scale_jitter, scale_jitter, frames)) * np.exp(1j * (rest[s] + rng.uniform(-0.6, 0.6, frames)))
        if parent[s] < 0:
            A[s] = rot
            B[s] = 300 + 300j + rng.normal(0, 15, frames) + 1j * rng.normal(0, 15, frames)
        else:
            A[s] = A[parent[s]] * rot
            B[s] = B[parent[s]] + A[parent[s]] * attach[s]
    edges = [(p, s) for s, p in enumerate(parent) if p >= 0]
    return _finish(A, B, loc, lab, rng, noise, edges, np.stack([B[c] for _, c in edges]))


def _undirected(edges):
    return {tuple(sorted(e)) for e in edges}


# ----------------------------------------------------------------- twists (eqs. 2-6)
def _similarity(scale, angle, tx, ty):
    c, s = scale * np.cos(angle), scale * np.sin(angle)
    return np.array([[c, -s, tx], [s, c, ty], [0, 0, 1.0]])


@settings(max_examples=40, deadline=None)
@given(st.floats(0.5, 2.0), st.floats(-3.0, 3.0), st.floats(-50, 50), st.floats(-50, 50))
def test_similarity_log_matches_matrix_logarithm(scale, angle, tx, ty):
    Mx = _similarity(scale, angle, tx, ty)
    xi = M.similarity_log(Mx)
    vx, vy, w, c = xi
    hat = np.array([[c, -w, vx], [w, c, vy], [0, 0, 0]])
    np.testing.assert_allclose(scipy.linalg.expm(hat), Mx, atol=1e-9)
    np.testing.assert_allclose(M.similarity_exp(xi), Mx, atol=1e-9)
    with np.errstate(all="ignore"):  # scipy's 1-norm estimator inside logm warns on some examples
        ref = scipy.linalg.logm(Mx).real
    np.testing.assert_allclose(hat, ref, atol=1e-7)


def test_similarity_log_vectorised_and_pure_translation():
    Ms = np.stack([_similarity(1.0, 0.0, 3.0, -4.0), _similarity(1.2, 0.3, 1.0, 2.0)])
    xi = M.similarity_log(Ms)
    assert xi.shape == (2, 4)
    np.testing.assert_allclose(xi[0], [3.0, -4.0, 0.0, 0.0])  # a pure translation is its own twist
    with pytest.raises(ValueError, match="shape"):
        M.similarity_log(np.eye(2))


def test_scaled_twist_centre_is_the_fixed_point():
    Mx = _similarity(0.9, 0.7, 10.0, -3.0)
    tau, log_det = M.scaled_twist(M.similarity_log(Mx))
    theta, ux, uy, w, c = tau
    np.testing.assert_allclose(Mx @ [ux, uy, 1.0], [ux, uy, 1.0], atol=1e-9)
    assert np.isclose(np.hypot(w, c), 1.0)
    assert np.isclose(theta, np.hypot(0.7, np.log(0.9)))
    assert np.isclose(log_det, -3 * np.log(theta))


def _numeric_jacobian(f, x, eps=1e-6):
    J = np.zeros((len(f(x)), len(x)))
    for k in range(len(x)):
        d = np.zeros_like(x)
        d[k] = eps
        J[:, k] = (f(x + d) - f(x - d)) / (2 * eps)
    return J


def test_log_det_is_the_change_of_variables_jacobian():
    """Eq. 6: with (w, c) on the unit circle written as one angle, the map
    (v~x, v~y, w~, c~) -> (theta, ux, uy, phi) has |det J| = theta^-3 (rotation), and
    (v~x, v~y) -> (theta, direction angle) has |det J| = theta^-1 (translation)."""

    def rot_coords(xi):
        tau, _ = M.scaled_twist(xi)
        return np.array([tau[0], tau[1], tau[2], np.arctan2(tau[4], tau[3])])

    xi = np.array([0.3, -1.2, 0.4, -0.25])
    J = _numeric_jacobian(rot_coords, xi)
    _, log_det = M.scaled_twist(xi)
    assert np.isclose(np.log(abs(np.linalg.det(J))), log_det, atol=1e-5)

    def tr_coords(v):
        tau, _ = M.scaled_twist(np.array([v[0], v[1], 0.0, 0.0]))
        return np.array([tau[0], np.arctan2(tau[2], tau[1])])

    v = np.array([2.0, -0.7])
    J = _numeric_jacobian(tr_coords, v)
    _, log_det = M.scaled_twist(np.array([v[0], v[1], 0.0, 0.0]))
    assert np.isclose(np.log(abs(np.linalg.det(J))), log_det, atol=1e-6)
    assert np.isclose(log_det, -np.log(np.hypot(*v)))


def test_scaled_twist_identity_is_zero():
    tau, log_det = M.scaled_twist(np.zeros(4))
    assert np.all(tau == 0) and log_det == 0


def test_classify_motions_uses_noise_levels():
    z = np.array([0.0 + 0.001j, 0.0 + 0.001j, 0.5j])
    disp = np.array([0.001, 5.0, 1.0])
    kind = M.classify_motions(z, disp, var_z=np.full(3, 1e-4), var_d=np.full(3, 0.01), threshold=3.0)
    assert kind.tolist() == [M.IDENTITY, M.TRANSLATION, M.ROTATION]


# ----------------------------------------------------------------- entropies
def test_kde_entropy_of_gaussian_centres_is_close_to_the_truth():
    rng = np.random.default_rng(0)
    n, sigma = 400, 2.0
    centre = sigma * (rng.normal(size=n) + 1j * rng.normal(size=n))
    kind = np.full(n, M.ROTATION, np.int8)
    H, _ = M.motion_entropy(kind, centre, np.zeros(n), np.ones(n), log_det_correction=False)
    assert abs(H - np.log(2 * np.pi * np.e * sigma**2)) < 0.2
    H_tight, _ = M.motion_entropy(kind, centre / 10, np.zeros(n), np.ones(n), log_det_correction=False)
    assert np.isclose(H - H_tight, 2 * np.log(10), atol=0.05)  # entropy shifts by log|scale| per dimension


def test_entropy_mixes_motion_types_and_log_det():
    rng = np.random.default_rng(1)
    n = 200
    kind = np.where(np.arange(n) < 150, M.ROTATION, M.TRANSLATION).astype(np.int8)
    centre = rng.normal(size=n) + 1j * rng.normal(size=n)
    direction = rng.normal(0, 0.1, n)
    theta = np.full(n, 0.5)
    H0, d = M.motion_entropy(kind, centre, direction, theta, log_det_correction=False)
    H1, _ = M.motion_entropy(kind, centre, direction, theta, log_det_correction=True)
    assert d["n_rotation"] == 150 and d["n_translation"] == 50
    expected = -(150 * -3 * np.log(0.5) + 50 * -np.log(0.5)) / n
    assert np.isclose(H1 - H0, expected)


def test_motion_entropy_needs_two_samples():
    with pytest.raises(ValueError, match="at least 2"):
        M.motion_entropy(np.array([M.ROTATION], np.int8), np.zeros(1, complex), np.zeros(1), np.ones(1))


def test_maximum_spanning_tree():
    W = np.array([[np.nan, 5, 1, 0], [5, np.nan, 4, 1], [1, 4, np.nan, 3], [0, 1, 3, np.nan]])
    assert M.maximum_spanning_tree(W) == [(0, 1), (1, 2), (2, 3)]


# ----------------------------------------------------------------- the paper's experiments
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("paper", [False, True])
def test_chain_with_revolute_and_prismatic_joint(seed, paper):
    traj = chain3(seed=seed)
    kw = dict(tree="mutual_information", kernel="gaussian", threshold=3.0) if paper else {}
    skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true, **kw)
    assert _undirected(skel.edges) == {(0, 1), (1, 2)}
    mi = skel.state["mutual_information"]
    assert mi.shape == (3, 3) and np.allclose(mi, mi.T, equal_nan=True) and np.isnan(np.diag(mi)).all()
    assert mi[0, 2] < min(mi[0, 1], mi[1, 2])
    # The prismatic pair's relative motion is mostly pure translation.
    est = sf.get_method("mi-tree")(labels=traj.labels_true, **kw).fit(traj)
    np.testing.assert_array_equal(est.mutual_information_, mi)
    # The revolute joint is located to within a few pixels (1-pixel noise, 100-pixel segments).
    row = skel.edges.index((0, 1)) if (0, 1) in skel.edges else skel.edges.index((1, 0))
    err = np.linalg.norm(skel.joints[row] - traj.joints_true[0], axis=-1)
    assert np.median(err) < 2.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_humanoid_torso(seed):
    traj = torso5(seed=seed)
    skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    assert _undirected(skel.edges) == _undirected(traj.edges_true)
    assert skel.edges[0][0] in (0, 2)  # rooted at the largest segment (ties: first)
    paper = sf.fit(traj, method="mi-tree", labels=traj.labels_true, tree="mutual_information",
                   kernel="gaussian", threshold=3.0)
    assert _undirected(paper.edges) == _undirected(traj.edges_true)
    # Every joint of the true tree is found where it is.
    for k, (p, c) in enumerate(traj.edges_true):
        row = [tuple(sorted(e)) for e in skel.edges].index(tuple(sorted((p, c))))
        err = np.linalg.norm(skel.joints[row] - traj.joints_true[k], axis=-1)
        assert np.median(err) < 3.0


def test_segment_of_copies_is_dropped_not_fitted(monkeypatch):
    # A BVH end site on its joint, or a C3D marker repeated unlabelled: a segment made of copies of
    # one trajectory has no extent, so its similarity would be 0 / 0 and its joints NaN.
    import warnings

    from stickfigure import segmentation

    traj = chain3(seed=0, frames=40)
    xy = np.concatenate([traj.xy, traj.xy[:1], traj.xy[:1]])
    lab = np.concatenate([traj.labels_true, [3, 3]])
    with pytest.raises(ValueError, match="copies"):
        sf.fit(xy, method="mi-tree", labels=lab)
    monkeypatch.setattr(segmentation, "affinity_propagation_segments", lambda xy, random_state=None: lab)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        skel = sf.fit(xy, method="mi-tree", random_state=0)
    assert skel.info["dropped_singletons"] == [3]
    assert skel.n_sticks == 3 and np.all(skel.labels[-2:] == -1)
    assert np.all(np.isfinite(skel.joints))


def test_planar_random_figures_known_answer():
    hits = 0
    for seed in range(6):
        traj = sf.synthetic.random_figure(n_sticks=4, frames=100, planar=True, noise=0.01, seed=seed)
        skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
        hits += _undirected(skel.edges) == _undirected(traj.edges_true)
    assert hits >= 5


def test_noise_estimate_ignores_smooth_model_error():
    traj = sf.synthetic.random_figure(n_sticks=4, frames=120, noise=0.01, seed=3)
    poses = M.fit_spm_poses(traj.xy, traj.labels_true, 4)
    assert 0.7 < poses.noise / traj.meta["noise_std"] < 1.4


# ----------------------------------------------------------------- skeleton, impute, files
def test_skeleton_contents_and_impute(tmp_path):
    traj = torso5(seed=3, frames=80)
    skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    P, F, _ = traj.shape
    assert skel.motions.shape == (5, F, 2, 4) and skel.local.shape == (P, 3)
    assert skel.joints.shape == (4, F, 2)
    # The fitted similarities reproduce the points to noise level.
    rms = np.sqrt(np.nanmean((skel.predict() - traj.xy) ** 2))
    assert rms < 1.5
    hidden_traj, hidden = traj.missing_at_random(0.2, random_state=0)
    # The method's contract (Skeleton.impute dispatches to it and keeps observed entries).
    filled = sf.get_method("mi-tree").impute_skeleton(skel, hidden_traj)
    err = np.sqrt(np.mean((filled[hidden] - traj.xy[hidden]) ** 2))
    assert err < 2.0
    # Save, load, impute again: same answer.
    path = skel.save(tmp_path / "model.json")
    again = sf.Skeleton.load(path)
    np.testing.assert_allclose(sf.get_method("mi-tree").impute_skeleton(again, hidden_traj), filled)
    assert again.info["mutual_information"][0][0] is None


def test_impute_with_few_visible_points():
    traj = chain3(seed=4, frames=40)
    skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    xy = traj.xy.copy()
    seg2 = np.flatnonzero(traj.labels_true == 2)
    xy[seg2[1:], 10] = np.nan  # one visible point: translation from it, rotation interpolated
    xy[seg2, 11] = np.nan  # none visible: pose interpolated in time
    filled = sf.get_method("mi-tree").impute_skeleton(skel, traj.with_xy(xy))
    assert np.isfinite(filled).all()
    assert np.linalg.norm(filled[seg2, 10] - traj.xy[seg2, 10], axis=-1).max() < 40


def test_deterministic():
    traj = torso5(seed=5, frames=60)
    a = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    b = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    assert a.edges == b.edges
    np.testing.assert_array_equal(a.state["mutual_information"], b.state["mutual_information"])


def test_single_segment_and_gapped_labels():
    traj = chain3(seed=0, frames=30)
    one = sf.fit(traj, method="mi-tree", labels=np.zeros(traj.n_points, int))
    assert one.n_sticks == 1 and one.edges == []
    lab = traj.labels_true * 2  # segment ids 0, 2, 4
    skel = sf.fit(traj, method="mi-tree", labels=lab)
    assert skel.n_sticks == 3 and skel.info["segment_ids"] == [0, 2, 4]


def test_bad_input():
    traj = chain3(seed=0, frames=30)
    with pytest.raises(ValueError, match="2D"):
        sf.fit(np.zeros((4, 10, 3)) + np.arange(10)[None, :, None], method="mi-tree", labels=[0, 0, 1, 1])
    with pytest.raises(ValueError, match="labels"):
        sf.fit(traj, method="mi-tree", labels=[0, 1])
    lab = traj.labels_true.copy()
    lab[0] = 7
    with pytest.raises(ValueError, match="single point"):
        sf.fit(traj, method="mi-tree", labels=lab)
    with pytest.raises(ValueError, match="tree"):
        sf.fit(traj, method="mi-tree", labels=traj.labels_true, tree="minimum")
    with pytest.raises(ValueError, match="kernel"):
        sf.fit(traj, method="mi-tree", labels=traj.labels_true, kernel="epanechnikov")
    with pytest.raises(ValueError, match="threshold"):
        sf.fit(traj, method="mi-tree", labels=traj.labels_true, threshold=-1)
    with pytest.raises(ValueError, match="reference_frame"):
        sf.fit(traj, method="mi-tree", labels=traj.labels_true, reference_frame=99)
    with pytest.raises(ValueError, match="n_references"):
        sf.fit(traj, method="mi-tree", labels=traj.labels_true, n_references=0)


def test_entropies_averaged_over_reference_frames():
    """The default averages the entropies of several reference frames; one reference
    frame reproduces the single-t1 estimate of mutual_information_matrix."""
    from stickfigure.models import mitree

    traj = torso5(seed=3, frames=60)
    poses = mitree.fit_spm_poses(traj.xy, traj.labels_true, 5)
    refs = mitree.reference_frames(poses, 5)
    assert len(refs) == 5 and refs == sorted(set(refs)) and refs[0] == 0 and refs[-1] == 59
    assert mitree.reference_frames(poses, 1) == [0]
    skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    assert skel.info["reference_frames"] == refs
    runs = [mitree.mutual_information_matrix(poses, reference_frame=r, threshold=2.0)[1]["conditional_entropy"] for r in refs]
    np.testing.assert_allclose(skel.state["conditional_entropy"], np.mean(runs, axis=0))
    one = sf.fit(traj, method="mi-tree", labels=traj.labels_true, n_references=1)
    single = mitree.mutual_information_matrix(poses, reference_frame=0, threshold=2.0)[1]["conditional_entropy"]
    np.testing.assert_allclose(one.state["conditional_entropy"], single)


def test_default_segmentation_runs():
    traj = torso5(seed=0, frames=60)
    skel = sf.fit(traj, method="mi-tree", random_state=0)
    assert skel.info["segmentation"] == "affinity_propagation"
    assert skel.n_sticks >= 2 and len(skel.edges) == skel.n_sticks - 1


def test_heat_map_and_tree_plot():
    from stickfigure.plot import mitree as plot_mitree

    traj = torso5(seed=0, frames=40)
    skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
    fig = plot_mitree.figure(skel, traj)
    assert len(fig.axes) >= 3
    import matplotlib.pyplot as plt

    plt.close(fig)
    with pytest.raises(ValueError, match="mi-tree"):
        plot_mitree.plot_mutual_information(sf.Skeleton(method="sfm", labels=np.zeros(3, int), n_sticks=1))


@pytest.mark.slow
def test_random_3d_figures_with_true_segmentation():
    """The acceptance scene: random 3D figures, true segmentation, mean edge F1 >= 0.9."""
    f1 = []
    for seed in range(24):
        rng = np.random.default_rng(10_000 + seed)
        traj = sf.synthetic.random_figure(n_sticks=int(rng.integers(3, 8)), frames=int(rng.integers(90, 181)),
                                          noise=0.01, seed=seed)
        skel = sf.fit(traj, method="mi-tree", labels=traj.labels_true)
        got, true = _undirected(skel.edges), _undirected(traj.edges_true)
        f1.append(2 * len(got & true) / (len(got) + len(true)))
    assert np.mean(f1) >= 0.9
