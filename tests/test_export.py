"""Posing a skeleton, joint angles (known answers on the arm) and BVH round trips through the BVH loader."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stickfigure as sf
from stickfigure import export
from stickfigure.geometry import affine_factorization


def truth_skeleton(traj: sf.Trajectories, *, motions: bool = True, joints: bool = True) -> sf.Skeleton:
    """The skeleton a perfect method would return: true sticks, tree and joints.

    Stick motions come from an affine factorisation of each true stick's points
    (rank 3, as in :func:`stickfigure.geometry.affine_factorization`). Other
    test modules import this helper.
    """
    S = int(traj.labels_true.max()) + 1
    P, F, D = traj.shape
    kw = {}
    if motions:
        M = np.zeros((S, F, D, 4))
        local = np.zeros((P, 3))
        for s in range(S):
            m = traj.labels_true == s
            fz = affine_factorization(traj.xy[m], rank=3, random_state=0)
            M[s], local[m] = fz.motions, fz.shape
        kw = {"motions": M, "local": local}
    return sf.Skeleton(method="truth", labels=traj.labels_true, n_sticks=S, edges=traj.edges_true,
                       joints=traj.joints_true if joints else None, n_dims=D, **kw)


@pytest.fixture(scope="module")
def planar():
    return sf.synthetic.random_figure(n_sticks=4, frames=50, planar=True, noise=0.005, seed=3)


@pytest.fixture(scope="module")
def planar_skeleton(planar):
    return truth_skeleton(planar)


def _scale(traj):
    return float(np.nanstd(traj.xy))


# ---------------------------------------------------------------------- pose
def test_pose_refits_joints_on_the_training_frames(planar, planar_skeleton):
    p = export.pose(planar_skeleton, planar)
    P, F, D = planar.shape
    E = len(planar.edges_true)
    assert p.joints.shape == (E, F, D) and p.directions.shape == (4, F, D)
    # Joints re-posed through the stick motions land on the true joints.
    err = np.linalg.norm(p.joints - planar.joints_true, axis=2)
    assert err.max() < 0.03 * _scale(planar)
    np.testing.assert_allclose(np.linalg.norm(p.directions, axis=2), 1.0, atol=1e-9)
    # Every stick is drawn; segments meet at the joints.
    assert set(p.segment_stick.tolist()) == set(range(4))
    assert p.frames.tolist() == list(range(F))


def test_pose_on_new_frames_and_frame_offset(planar, planar_skeleton):
    later = planar.slice(frames=slice(20, 50))
    occluded, hidden = sf.synthetic.occlude(later, seed=1)
    p = export.pose(planar_skeleton, occluded)
    assert p.frames[0] == 20
    err = np.linalg.norm(p.joints - later.joints_true, axis=2)
    # Frames where the bar hides most of a stick fall back on the smoothness prior of fit_motions.
    assert np.median(err) < 0.01 * _scale(planar) and err.max() < 0.1 * _scale(planar)
    # Hidden points take the stick motions' predictions.
    miss = np.linalg.norm(p.points[hidden] - later.xy[hidden], axis=1)
    assert np.median(miss) < 0.02 * _scale(planar) and miss.max() < 0.15 * _scale(planar)


def test_pose_needs_traj_without_motions(planar):
    sk = truth_skeleton(planar, motions=False)
    with pytest.raises(ValueError, match="no stick motions"):
        export.pose(sk)
    p = export.pose(sk, planar)  # observed points and the stored joints
    np.testing.assert_allclose(p.joints, planar.joints_true)


def test_pose_rejects_mismatched_data(planar_skeleton):
    other = sf.synthetic.random_figure(n_sticks=2, frames=20, seed=0)
    with pytest.raises(ValueError, match="points"):
        export.pose(planar_skeleton, other)
    with pytest.raises(TypeError, match="Skeleton"):
        export.pose("model.json")


# -------------------------------------------------------------- joint angles
def test_joint_angles_known_answer_on_the_arm():
    """The arm's joints bend by fold * sin(pi u) * linspace(1, 0.8): the exported angles are those bends."""
    S, F = 4, 33
    arm = sf.synthetic.arm(n_joints=S, n_frames=F, noise=0.0, seed=0)
    sk = truth_skeleton(arm, motions=False)
    angles, table = export.joint_angles(sk, arm)
    assert angles.shape == (S - 1, F)
    assert [(r["parent_stick"], r["child_stick"]) for r in table] == [(0, 1), (1, 2), (2, 3)]
    u = np.linspace(0, 1, F)
    expected = np.degrees(np.radians(150.0) * np.sin(np.pi * u))[None, :] * np.linspace(1.0, 0.8, S - 1)[:, None]
    # Stick 1 runs joint to joint, exactly along its axis; the root (centroid -> child joint)
    # and the leaf (joint -> centroid) go through their points' centroid, slightly off
    # their axes because the points are jittered sideways: a constant offset.
    np.testing.assert_allclose(angles[1], expected[1], atol=1e-6)
    for e in (0, 2):
        off = angles[e] - expected[e]
        assert np.abs(off).max() < 4.0 and np.ptp(off) < 1e-6


def test_joint_angles_sign_and_3d(planar, planar_skeleton):
    a2, _ = export.joint_angles(planar_skeleton, planar)
    assert np.all((a2 > -180) & (a2 <= 180))
    # Mirroring the data (x -> -x) flips every signed angle.
    mirrored = planar.with_xy(planar.xy * np.array([-1.0, 1.0]))
    mirrored.joints_true = planar.joints_true * np.array([-1.0, 1.0])
    am, _ = export.joint_angles(truth_skeleton(mirrored), mirrored)
    np.testing.assert_allclose(am, -a2, atol=1.0)
    walker3d = sf.synthetic.walker(n_frames=20, project=False, seed=0)
    a3, _ = export.joint_angles(truth_skeleton(walker3d))
    assert a3.shape == (10, 20) and np.all((a3 >= 0) & (a3 <= 180))


def test_joint_angles_motion_path_agrees_with_observed_path(planar, planar_skeleton):
    with_motion, _ = export.joint_angles(planar_skeleton, planar)
    observed_only, _ = export.joint_angles(truth_skeleton(planar, motions=False), planar)
    diff = (with_motion - observed_only + 180) % 360 - 180
    assert np.abs(diff).max() < 3.0


def test_angles_csv_round_trip(tmp_path, planar, planar_skeleton):
    path = export.write_angles_csv(planar_skeleton, tmp_path / "angles.csv", traj=planar.slice(frames=slice(10, 30)))
    angles, table = export.joint_angles(planar_skeleton, planar.slice(frames=slice(10, 30)))
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["frame", "joint", "parent_stick", "child_stick", "angle_deg"]
    E, F = angles.shape
    assert len(rows) == E * F
    assert int(rows[0]["frame"]) == 10 and int(rows[-1]["frame"]) == 29
    back = np.array([float(r["angle_deg"]) for r in rows]).reshape(F, E).T
    np.testing.assert_allclose(back, angles, atol=1e-4)
    for r in rows[:E]:
        t = table[int(r["joint"])]
        assert (int(r["parent_stick"]), int(r["child_stick"])) == (t["parent_stick"], t["child_stick"])


# ----------------------------------------------------------------------- BVH
def _node_truth(p: export.Pose, s: int) -> np.ndarray:
    """Where write_bvh puts stick s: its parent joint, or its centroid for a root."""
    hit = np.flatnonzero(p.child_stick == s)
    return p.joints[hit[0]] if hit.size else p.centroids[s]


@pytest.mark.parametrize("image", [False, True])
def test_bvh_round_trip_2d(tmp_path, planar, image):
    traj = planar
    if image:  # pixel coordinates, y down: the BVH stands the figure upright
        xy = 200 + 100 * planar.xy * np.array([1.0, -1.0])
        traj = planar.copy(xy=xy, joints_true=200 + 100 * planar.joints_true * np.array([1.0, -1.0]),
                           image_size=(400, 400))
    sk = truth_skeleton(traj)
    path = export.write_bvh(sk, tmp_path / "fig.bvh", traj)
    back = sf.load(path, merge_rigid=False)
    assert back.n_frames == traj.n_frames and back.frame_rate == pytest.approx(30.0)
    p = export.pose(sk, traj)
    scale = _scale(traj)
    for s in range(sk.n_sticks):
        fk = back.xy[back.names.index(f"stick{s}")]
        want = export.bvh_coordinates(_node_truth(p, s), traj, 2)
        assert np.abs(fk - want).max() < 1e-4 * scale, s
        assert np.abs(fk[:, 2]).max() == 0.0  # the z = 0 plane
    if image:  # upright: the BVH y is minus the image y
        j = back.xy[back.names.index("stick1")]
        np.testing.assert_allclose(j[:, 1], -_node_truth(p, 1)[:, 1], atol=1e-4 * scale)
    # End sites: the leaves' far ends, up to how much the far end moves on its stick.
    leaves = [s for s in range(sk.n_sticks) if s not in p.parent_stick]
    for s in leaves:
        fk = back.xy[back.names.index(f"stick{s}_End")]
        want = export.bvh_coordinates(p.far_ends[s], traj, 2)
        assert np.linalg.norm(fk - want, axis=1).max() < 0.05 * scale


def test_bvh_rigid_keeps_lengths_and_rotations_are_joint_angles(tmp_path, planar, planar_skeleton):
    path = export.write_bvh(planar_skeleton, tmp_path / "rigid.bvh", planar, lengths="rigid")
    text = path.read_text()
    assert text.count("CHANNELS 3 Zrotation Xrotation Yrotation") == 3
    back = sf.load(path, merge_rigid=False)
    p = export.pose(planar_skeleton, planar)
    # A planar figure's sticks are rigid in the image: rigid bones reproduce the joints up to the noise.
    for s in range(4):
        fk = back.xy[back.names.index(f"stick{s}")]
        want = export.bvh_coordinates(_node_truth(p, s), planar, 2)
        assert np.linalg.norm(fk - want, axis=1).max() < 0.05 * _scale(planar)
    # A child's Zrotation is its joint angle minus the mean joint angle.
    rows = np.array([[float(v) for v in line.split()] for line in text.split("Frame Time:")[1].splitlines()[1:]])
    angles, table = export.joint_angles(planar_skeleton, planar)
    order = [int(line.split("stick")[1]) for line in text.splitlines() if "JOINT" in line or "ROOT" in line]
    col = 6  # the root's 6 channels come first
    for s in order[1:]:
        e = [r["child_stick"] for r in table].index(s)
        z = rows[:, col]
        dev = (angles[e] - z + 180) % 360 - 180
        assert np.ptp(dev) < 1e-3, s
        col += 3


def test_bvh_round_trip_3d(tmp_path):
    walker = sf.synthetic.walker(n_frames=24, project=False, seed=2)  # z up
    sk = truth_skeleton(walker)
    path = export.write_bvh(sk, tmp_path / "walker.bvh", walker, frame_rate=24)
    back = sf.load(path, merge_rigid=False)
    assert back.frame_rate == pytest.approx(24.0) and back.up_axis == 1
    p = export.pose(sk, walker)
    for s in range(sk.n_sticks):
        fk = back.xy[back.names.index(f"stick{s}")]
        want = export.bvh_coordinates(_node_truth(p, s), walker, 3)
        assert np.abs(fk - want).max() < 1e-4, s
    # The up axis: the data's z (height) becomes the BVH's y.
    head = back.xy[back.names.index("stick2")]
    np.testing.assert_allclose(head[:, 1], _node_truth(p, 2)[:, 2], atol=1e-4)


def test_bvh_forest_hangs_from_a_figure_root(tmp_path, planar):
    sk = truth_skeleton(planar)
    cut = sf.Skeleton(method="truth", labels=sk.labels, n_sticks=4, edges=sk.edges[:1], joints=sk.joints[:1],
                      motions=sk.motions, local=sk.local)
    path = export.write_bvh(cut, tmp_path / "forest.bvh")
    assert path.read_text().startswith("HIERARCHY\nROOT figure\n")
    back = sf.load(path, merge_rigid=False)
    assert {f"stick{s}" for s in range(4)} <= set(back.names)
    p = export.pose(cut)
    for s in range(4):
        fk = back.xy[back.names.index(f"stick{s}")]
        np.testing.assert_allclose(fk, export.bvh_coordinates(_node_truth(p, s), None, 2), atol=1e-4)


def test_bvh_errors(tmp_path, planar, planar_skeleton):
    no_joints = sf.Skeleton(method="truth", labels=planar_skeleton.labels, n_sticks=4, edges=planar_skeleton.edges,
                            motions=planar_skeleton.motions, local=planar_skeleton.local)
    with pytest.raises(ValueError, match="no joint positions"):
        export.write_bvh(no_joints, tmp_path / "x.bvh")
    with pytest.raises(ValueError, match="lengths"):
        export.write_bvh(planar_skeleton, tmp_path / "x.bvh", lengths="stretchy")
    with pytest.raises(ValueError, match="frame_rate"):
        export.write_bvh(planar_skeleton, tmp_path / "x.bvh", frame_rate=-1)
    assert not (tmp_path / "x.bvh").exists()


# ------------------------------------------------------------------ property
@settings(max_examples=25, deadline=None)
@given(phi=st.floats(-np.pi, np.pi), scale=st.floats(0.1, 10.0), shift=st.tuples(st.floats(-50, 50),
                                                                                 st.floats(-50, 50)))
def test_joint_angles_invariant_to_similarity_transforms(phi, scale, shift):
    """Rotating, scaling and moving the whole scene in the image leaves every joint angle unchanged."""
    arm = sf.synthetic.arm(n_frames=12, noise=0.01, seed=4)
    c, s = np.cos(phi), np.sin(phi)
    T = scale * np.array([[c, -s], [s, c]])
    moved = arm.copy(xy=arm.xy @ T.T + np.asarray(shift), joints_true=arm.joints_true @ T.T + np.asarray(shift))
    a0, _ = export.joint_angles(truth_skeleton(arm, motions=False), arm)
    a1, _ = export.joint_angles(truth_skeleton(moved, motions=False), moved)
    diff = (a1 - a0 + 180) % 360 - 180
    assert np.abs(diff).max() < 1e-6


def test_pose_uses_the_methods_own_joints_on_its_training_frames(planar, planar_skeleton):
    shifted = planar_skeleton.joints + 0.01  # make stored joints distinguishable from any re-fit
    sk = sf.Skeleton(method="truth", labels=planar_skeleton.labels, n_sticks=4, edges=planar_skeleton.edges,
                     joints=shifted, motions=planar_skeleton.motions, local=planar_skeleton.local)
    np.testing.assert_array_equal(export.pose(sk, planar).joints, shifted)
    # Another clip of the same length: the stored motions do not fit it, the joints are re-posed.
    reversed_clip = planar.slice(frames=np.arange(planar.n_frames)[::-1])
    p = export.pose(sk, reversed_clip)
    assert not np.allclose(p.joints, shifted)
    err = np.linalg.norm(p.joints - planar.joints_true[:, ::-1], axis=2)
    assert np.median(err) < 0.03 * _scale(planar)
