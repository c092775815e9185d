"""Tests of the "yan-pollefeys" baseline (local subspace affinity + MST of subspace angles)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import stickfigure as sf
from stickfigure.models import yan_pollefeys as YP

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks package (in_phase_legs)
from benchmarks.bench_topology import _legs_joined, in_phase_legs  # noqa: E402


def _undirected(edges):
    return {tuple(sorted(e)) for e in edges}


def _f1(got, true):
    got, true = _undirected(got), _undirected(true)
    return 2 * len(got & true) / (len(got) + len(true)) if got or true else 1.0


def test_connected_parts_have_intersecting_subspaces():
    traj = sf.synthetic.random_figure(n_sticks=3, frames=120, noise=0.002, seed=1)
    bases, ranks, motions, local = YP.motion_subspaces(traj.xy, traj.labels_true, 3)
    assert ranks.tolist() == [3, 3, 3]  # 3D sticks turning in 3D
    assert all(b.shape == (traj.n_frames * 2, 4) for b in bases)
    assert motions.shape == (3, traj.n_frames, 2, 4) and local.shape == (traj.n_points, 3)
    D = YP.subspace_distances(bases)
    assert np.allclose(D, D.T) and np.all(np.diag(D) == 0)
    true = _undirected(traj.edges_true)
    adjacent = [D[i, j] for i, j in true]
    other = [D[i, j] for i in range(3) for j in range(i + 1, 3) if (i, j) not in true]
    assert max(adjacent) < min(other)
    assert max(adjacent) < 0.05  # ~0: the joint's trajectory is in both subspaces


def test_joint_trajectories_at_the_subspace_intersection():
    traj = sf.synthetic.random_figure(n_sticks=3, frames=100, noise=0.005, seed=2)
    skel = sf.fit(traj, method="yan-pollefeys", labels=traj.labels_true)
    assert skel.joints.shape == (2, traj.n_frames, 2)
    # The joints of the true edges, from the fitted parts' motions (whatever tree was chosen).
    par = [p for p, _ in traj.edges_true]
    chi = [c for _, c in traj.edges_true]
    _, _, joints, rms = YP.joint_trajectories(skel.motions[par], skel.motions[chi])
    err = np.linalg.norm(joints - traj.joints_true, axis=-1)
    assert np.all(np.median(err, axis=1) < 0.1)  # stick lengths ~1
    assert np.all(rms < 0.05)


def test_joint_least_squares_known_answer():
    rng = np.random.default_rng(0)
    E, F = 1, 30
    Mp = rng.normal(size=(E, F, 2, 4))
    Mc = rng.normal(size=(E, F, 2, 4))
    xp, xc = np.array([0.3, -0.2, 0.5]), np.array([-0.4, 0.1, 0.2])
    # Make the child's translation put x_c where the parent puts x_p: an exact joint.
    Mc[..., 3] = np.einsum("efdk,k->efd", Mp[..., :3], xp) + Mp[..., 3] - np.einsum("efdk,k->efd", Mc[..., :3], xc)
    gp, gc, joints, rms = YP.joint_trajectories(Mp, Mc)
    np.testing.assert_allclose(gp[0], xp, atol=1e-6)
    np.testing.assert_allclose(gc[0], xc, atol=1e-6)
    assert rms[0] < 1e-6 and joints.shape == (1, F, 2)


def test_random_figures_with_true_segmentation():
    f1 = []
    for seed in range(6):
        traj = sf.synthetic.random_figure(n_sticks=4, frames=100, noise=0.01, seed=seed)
        skel = sf.fit(traj, method="yan-pollefeys", labels=traj.labels_true)
        f1.append(_f1(skel.edges, traj.edges_true))
    assert np.mean(f1) >= 0.75


def test_known_failure_joins_legs_moving_in_phase():
    """Ross et al., Fig. 7: limbs moving in phase have dependent motions and get joined."""
    joined = 0
    for seed in range(4):
        traj = in_phase_legs(frames=100, seed=seed)
        skel = sf.fit(traj, method="yan-pollefeys", labels=traj.labels_true)
        joined += bool(_legs_joined(skel, traj))
    assert joined >= 3


def test_impute_save_load(tmp_path):
    traj = sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.005, seed=4)
    skel = sf.fit(traj, method="yan-pollefeys", labels=traj.labels_true)
    assert skel.motions.shape == (3, 60, 2, 4) and skel.local.shape == (traj.n_points, 3)
    assert np.sqrt(np.mean((skel.predict() - traj.xy) ** 2)) < 0.02
    hidden_traj, hidden = traj.missing_at_random(0.2, random_state=1)
    filled = sf.get_method("yan-pollefeys").impute_skeleton(skel, hidden_traj)
    assert np.sqrt(np.mean((filled[hidden] - traj.xy[hidden]) ** 2)) < 0.05
    again = sf.Skeleton.load(skel.save(tmp_path / "yp.json"))
    assert again.edges == skel.edges
    np.testing.assert_allclose(sf.get_method("yan-pollefeys").impute_skeleton(again, hidden_traj), filled)


def test_missing_data_with_given_labels():
    traj = sf.synthetic.random_figure(n_sticks=3, frames=80, noise=0.005, seed=5)
    gappy, _ = traj.missing_at_random(0.15, random_state=0)
    skel = sf.fit(gappy, method="yan-pollefeys", labels=traj.labels_true)
    assert _undirected(skel.edges) == _undirected(traj.edges_true)


def test_end_to_end_segmentation():
    traj = sf.synthetic.random_figure(n_sticks=3, frames=100, noise=0.005, seed=6, points_per_stick=10)
    est = sf.get_method("yan-pollefeys")(random_state=0).fit(traj)
    assert est.affinity_.shape == (traj.n_points, traj.n_points)
    assert est.skeleton_.info["segmentation"] == "local_subspace_affinity+spectral"
    assert len(est.skeleton_.edges) == est.skeleton_.n_sticks - 1
    a = sf.fit(traj, method="yan-pollefeys", random_state=0)
    np.testing.assert_array_equal(a.labels, est.skeleton_.labels)  # same seed, same answer


def test_number_of_parts_estimated():
    """The LSA's eigengap says one part on every random figure; the BIC over the
    spectral clusterings must find several and segment far better than one part."""
    from sklearn.metrics import adjusted_rand_score

    found, ari = [], []
    for seed in range(3):
        traj = sf.synthetic.random_figure(n_sticks=4, frames=100, noise=0.01, seed=seed)
        skel = sf.fit(traj, method="yan-pollefeys", random_state=0)
        sel = skel.info["n_segments_selection"]
        assert sel["chosen"] == skel.n_sticks and len(sel["bic"]) >= 4
        found.append(skel.n_sticks)
        ari.append(adjusted_rand_score(traj.labels_true, skel.labels))
    assert min(found) >= 2 and max(found) <= 8
    assert np.mean(ari) >= 0.3


def test_bad_input():
    traj = sf.synthetic.random_figure(n_sticks=2, frames=30, seed=0)
    with pytest.raises(ValueError, match="n_segments"):
        sf.fit(traj, method="yan-pollefeys", n_segments=0)
    with pytest.raises(ValueError, match="n_angles"):
        sf.fit(traj, method="yan-pollefeys", labels=traj.labels_true, n_angles=0)
    with pytest.raises(ValueError, match="labels"):
        sf.fit(traj, method="yan-pollefeys", labels=[0, 1])
    with pytest.raises(ValueError, match="at least 5 points"):
        sf.fit(traj.xy[:4], method="yan-pollefeys")
