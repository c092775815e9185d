"""Motion-capture readers: C3D, BVH, ASF/AMC, MoCap Toolbox; real files and synthetic known answers."""

from __future__ import annotations

import numpy as np
import pytest

import stickfigure as sf
from stickfigure.io import load
from stickfigure.io.markersets import SEGMENTS, contract_tree, segment_ground_truth, segment_of


# ------------------------------------------------------------ marker names
@pytest.mark.parametrize(
    "name, segment",
    [
        ("Male:LFHD", "head"), ("dg:RBHD", "head"), ("C7", "thorax"), ("Daniel:T10", "thorax"),
        ("RBAC", "thorax"), ("RBAK", "thorax"), ("lsho", "thorax"), ("LUPA", "l_upperarm"),
        ("RELB", "r_upperarm"), ("LFRM", "l_forearm"), ("RWRB", "r_forearm"), ("LFIN", "l_hand"),
        ("LFWT", "pelvis"), ("RBWT", "pelvis"), ("LASI", "pelvis"), ("SACR", "pelvis"),
        ("RTHI", "r_thigh"), ("LKNE", "l_thigh"), ("LSHN", "l_shin"), ("RTIB", "r_shin"),
        ("LANK", "l_shin"), ("RHEE", "r_foot"), ("LTOE", "l_foot"), ("RMT5", "r_foot"),
        ("Head_FL", "head"), ("Hip_BR", "pelvis"), ("Radius_L", "l_forearm"), ("Knee_R", "r_thigh"),
        ("BigToe_L", "l_foot"), ("l_knee", "l_thigh"), ("LeftAnkle", "l_shin"), (" Subj:LWRA ", "l_forearm"),
        ("LFIN2", "l_hand"), ("RTHI1", "r_thigh"), ("ARIEL", "head"), ("LKNI", "l_thigh"), ("RMED", "r_shin"),
        ("*12", None), ("KNEE", None), ("marker7", None), ("", None), ("L5", None),
    ],
)
def test_marker_names_map_to_segments(name, segment):
    assert segment_of(name) == segment


def test_segment_tree_contracts_over_missing_segments():
    labels, parts, edges, joints = segment_ground_truth(["LFHD", "LWRA", "LFIN", "C7", "*1"])
    assert parts == ["thorax", "head", "l_forearm", "l_hand"]  # SEGMENTS order
    assert labels.tolist() == [1, 2, 3, 0, -1]
    named = {(parts[a], parts[b]) for a, b in edges}
    assert named == {("thorax", "head"), ("thorax", "l_forearm"), ("l_forearm", "l_hand")}
    assert "thorax~l_forearm" in joints and "neck" in joints
    # No pelvis: the two subtrees under it are joined at the first of them.
    assert contract_tree({"r": None, "a": "r", "b": "r", "c": "a"}, ["a", "b", "c"]) == [("a", "c"), ("a", "b")]


def test_several_subjects_get_their_own_parts():
    labels, parts, edges, _ = segment_ground_truth(["LFHD", "C7", "LFHD", "C7"], groups=["A", "A", "B", "B"])
    assert parts == ["A:thorax", "A:head", "B:thorax", "B:head"]
    assert labels.tolist() == [1, 0, 3, 2] and edges == [(0, 1), (2, 3)]


def test_full_vicon_set_gives_the_body_tree():
    names = ["LFHD", "RFHD", "LBHD", "RBHD", "C7", "T10", "CLAV", "STRN", "RBAK", "LSHO", "LUPA", "LELB",
             "LFRM", "LWRA", "LWRB", "LFIN", "RSHO", "RUPA", "RELB", "RFRM", "RWRA", "RWRB", "RFIN", "LFWT",
             "RFWT", "LBWT", "RBWT", "LTHI", "LKNE", "LSHN", "LANK", "LHEE", "LTOE", "LMT5", "RTHI", "RKNE",
             "RSHN", "RANK", "RHEE", "RTOE", "RMT5"]
    labels, parts, edges, joints = segment_ground_truth(names)
    assert parts == list(SEGMENTS) and (labels >= 0).all()
    assert len(edges) == 14 and "~" not in "".join(joints)


# ---------------------------------------------------------------------- C3D
@pytest.mark.data
def test_cmu_c3d(data_dir):
    t = load(data_dir / "mocap" / "85_02.c3d")
    assert t.shape == (41, 810, 3) and t.frame_rate == 120 and t.up_axis == 2
    assert t.meta["units"] == "mm" and t.meta["source"].endswith("85_02.c3d")
    assert t.meta["n_figures"] == 1  # one subject (prefix "Male:")
    assert all(":" not in n for n in t.names) and "LFHD" in t.names
    assert not t.meta["unlabelled"].any() and (t.labels_true >= 0).all()
    assert t.part_names == list(SEGMENTS) and len(t.edges_true) == 14
    # z is up: the head is above the feet.
    head = t.xy[t.labels_true == t.part_names.index("head")].mean(axis=(0, 1))
    feet = t.xy[t.labels_true == t.part_names.index("l_foot")].mean(axis=(0, 1))
    assert head[2] - feet[2] > 1000


def _distance_std(t: sf.Trajectories, part: int) -> np.ndarray:
    ii = np.flatnonzero(t.labels_true == part)
    d = np.linalg.norm(t.xy[ii][:, None] - t.xy[ii][None], axis=-1)
    return np.nanstd(d, axis=-1)[np.triu_indices(len(ii), 1)]


@pytest.mark.data
@pytest.mark.parametrize("name", ["85_02.c3d", "HDM_dg_06-03_03_120.c3d"])
def test_c3d_markers_on_one_segment_keep_their_distances(data_dir, name):
    t = load(data_dir / "mocap" / name)
    stds = {p: _distance_std(t, i) for i, p in enumerate(t.part_names) if (t.labels_true == i).sum() > 1}
    # Bones are rigid up to skin motion (measured: <= 9.3 mm, 16.5 mm for HDM05's foot,
    # whose toe marker sits on the toe joint); the thorax includes the acromion
    # markers, which ride on the shoulder girdle (up to 29 mm).
    for part, s in stds.items():
        assert np.median(s) < 10, (part, s)
        assert s.max() < (35 if part == "thorax" else 20), (part, s)
    # A pair on different segments (thigh to shin) varies far more.
    ia, ib = t.names.index("LTHI"), t.names.index("LANK")
    assert np.nanstd(np.linalg.norm(t.xy[ia] - t.xy[ib], axis=-1)) > 30


@pytest.mark.data
def test_hdm05_c3d_unlabelled_markers_are_flagged(data_dir):
    t = load(data_dir / "mocap" / "HDM_dg_06-03_03_120.c3d")
    assert t.shape == (44, 202, 3)
    assert t.meta["unlabelled"].tolist() == [True] * 3 + [False] * 41
    assert t.names[:4] == ["*0", "*1", "*2", "LFHD"]
    assert (t.labels_true[:3] == -1).all() and (t.labels_true[3:] >= 0).all()
    assert t.meta["n_figures"] == 1  # the labelled markers name one subject
    # slicing keeps the per-point flags aligned
    s = t.slice(points=[0, 5])
    assert s.meta["unlabelled"].tolist() == [True, False]


def _write_c3d(path, labels, pts, rate=100.0, analog=0, extra=None):
    import ezc3d
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    for (group, name), value in (extra or {}).items():
        c.add_parameter(group, name, value)
    P, F = pts.shape[:2]
    data = np.ones((4, P, F))
    data[:3] = pts.transpose(2, 0, 1)
    c["data"]["points"] = data
    if analog:
        c["parameters"]["ANALOG"]["RATE"]["value"] = [rate * 10]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = tuple(f"a{i}" for i in range(analog))
        c["data"]["analogs"] = np.random.default_rng(0).random((1, analog, F * 10))
    c.write(str(path))
    return path


def test_c3d_without_prefix_with_gaps_analogs_and_other_rate(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5, 30, 3)) * 100
    pts[1, 5:9] = np.nan      # a gap (written with a negative residual)
    pts[2, 10] = 0.0          # the other gap convention
    pts[4] = np.nan           # never observed: dropped
    path = _write_c3d(tmp_path / "s.c3d", ["LKNE", "LTHI", "*7", "RANK", "LHEE"], pts, rate=250.0, analog=3,
                      extra={("POINT", "UNITS"): "m", ("POINT", "Y_SCREEN"): "+Y"})
    t = load(path)
    assert t.names == ["LKNE", "LTHI", "*7", "RANK"] and t.meta["dropped_points"] == ["LHEE"]
    assert t.frame_rate == 250 and t.meta["units"] == "m" and t.up_axis == 1
    assert t.meta["analog_channels"] == 3
    assert np.isnan(t.xy[1, 5:9]).all() and np.isnan(t.xy[2, 10]).all()
    np.testing.assert_allclose(t.xy[0], pts[0], rtol=1e-6, atol=1e-3)  # float32 storage
    assert t.meta["unlabelled"].tolist() == [False, False, True, False]
    assert t.part_names == ["l_thigh", "r_shin"] and t.labels_true.tolist() == [0, 0, -1, 1]
    assert load(path, zeros_as_missing=False).xy[2, 10].tolist() == [0, 0, 0]
    assert load(path, up_axis=2).up_axis == 2
    assert load(path, drop_unobserved=False).n_points == 5
    assert t.meta["n_figures"] == 1  # labelled, no subject prefix: one figure
    none = load(_write_c3d(tmp_path / "u.c3d", ["*0", "*1", "*2"], pts[:3]))
    assert none.meta["n_figures"] is None  # nothing labelled: the figures are unknown


def test_c3d_two_subjects_keep_prefixes(tmp_path):
    pts = np.random.default_rng(1).normal(size=(4, 6, 3))
    path = _write_c3d(tmp_path / "two.c3d", ["A:LFHD", "A:C7", "B:LFHD", "B:C7"], pts)
    t = load(path)
    assert t.names == ["A:LFHD", "A:C7", "B:LFHD", "B:C7"] and t.meta["subjects"] == ["A", "B"]
    assert t.part_names == ["A:thorax", "A:head", "B:thorax", "B:head"]
    assert t.meta["n_figures"] == 2


# ---------------------------------------------------------------------- BVH
def _axis_rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return {"X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


_BVH = """HIERARCHY
ROOT A
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation
  JOINT B
  {
    OFFSET 0 2 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT C
    {
      OFFSET 1 0 0
      CHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation
      End Site
      {
        OFFSET 0 0 1
      }
    }
    JOINT D
    {
      OFFSET 0 1.5 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0.5 0 0
      }
      End Site
      {
        OFFSET 0 0.5 0
      }
    }
  }
  JOINT E
  {
    OFFSET -1 0 0
    CHANNELS 2 Xrotation Zrotation
    End Site
    {
      OFFSET -1 0 0
    }
  }
}
MOTION
Frames: {F}
Frame Time: 0.02
{ROWS}
"""
# joint: (parent, offset, channels)
_SPEC = {
    "A": (None, [0, 0, 0], ["Xposition", "Yposition", "Zposition", "Yrotation", "Xrotation", "Zrotation"]),
    "B": ("A", [0, 2, 0], ["Zrotation", "Yrotation", "Xrotation"]),
    "C": ("B", [1, 0, 0], ["Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"]),
    "D": ("B", [0, 1.5, 0], ["Zrotation", "Xrotation", "Yrotation"]),
    "E": ("A", [-1, 0, 0], ["Xrotation", "Zrotation"]),
}
_ENDS = [("C_End", "C", [0, 0, 1]), ("D_End", "D", [0.5, 0, 0]), ("D_End1", "D", [0, 0.5, 0]),
         ("E_End", "E", [-1, 0, 0])]


def _expected_bvh(motion: np.ndarray) -> dict[str, np.ndarray]:
    """Independent forward kinematics with 4x4 matrices, one frame at a time."""
    out: dict[str, list] = {}
    for row in motion:
        it = iter(row)
        G = {}
        for name, (parent, offset, chans) in _SPEC.items():
            M = np.eye(4)
            M[:3, 3] = offset
            for ch in chans:
                v = next(it)
                T = np.eye(4)
                if ch.endswith("position"):
                    T[:3, 3] = np.eye(3)["XYZ".index(ch[0])] * v
                else:
                    T[:3, :3] = _axis_rot(ch[0], v)
                M = M @ T
            G[name] = (G[parent] @ M) if parent else M
            out.setdefault(name, []).append(G[name][:3, 3])
        for name, joint, offset in _ENDS:
            out.setdefault(name, []).append((G[joint] @ np.r_[offset, 1.0])[:3])
    return {k: np.array(v) for k, v in out.items()}


def _write_bvh(path, F=7, seed=0):
    rng = np.random.default_rng(seed)
    motion = rng.uniform(-90, 90, size=(F, 20))
    motion[:, 9:12] = rng.normal(size=(F, 3))  # C's position channels: small slides
    rows = "\n".join(" ".join(f"{v:.6f}" for v in r) for r in motion)
    path.write_text(_BVH.replace("{F}", str(F)).replace("{ROWS}", rows))
    return np.round(motion, 6)


def test_bvh_forward_kinematics_matches_independent_computation(tmp_path):
    motion = _write_bvh(tmp_path / "t.bvh")
    t = load(tmp_path / "t.bvh", merge_rigid=False)
    expected = _expected_bvh(motion)
    assert t.names == ["A", "B", "C", "C_End", "D", "D_End", "D_End1", "E", "E_End"]
    for i, n in enumerate(t.names):
        np.testing.assert_allclose(t.xy[i], expected[n], atol=1e-9, err_msg=n)
    assert t.frame_rate == pytest.approx(50) and t.up_axis == 1 and t.meta["units"] is None
    assert t.meta["n_figures"] == 1  # one ROOT
    # Parts are the joints' frames; a joint point belongs to its parent's part, except the
    # root and C, which slides (position channels) and is fixed only in its own frame.
    label = dict(zip(t.names, (t.part_names[k] for k in t.labels_true)))
    assert label == {"A": "A", "B": "A", "C": "C", "C_End": "C", "D": "B", "D_End": "D", "D_End1": "D",
                     "E": "A", "E_End": "E"}
    named = {(t.part_names[a], t.part_names[b]) for a, b in t.edges_true}
    assert named == {("A", "B"), ("B", "C"), ("B", "D"), ("A", "E")}
    for e, (a, b) in enumerate(t.edges_true):  # the joint is the child frame's origin
        np.testing.assert_allclose(t.joints_true[e], expected[t.part_names[b]], atol=1e-9)


def test_bvh_position_modes(tmp_path):
    motion = _write_bvh(tmp_path / "t.bvh", F=3)
    assert load(tmp_path / "t.bvh").meta["position_mode"] == "add"  # C's channels are small slides
    t = load(tmp_path / "t.bvh", position_mode="replace", merge_rigid=False)
    # the root's position channels are its position
    np.testing.assert_allclose(t.xy[0], motion[:, :3], atol=1e-9)
    with pytest.raises(ValueError, match="position_mode"):
        load(tmp_path / "t.bvh", position_mode="absolute")


def test_bvh_exporter_writing_full_translations_is_read_as_replace(tmp_path):
    """Some exporters put 6 channels on every joint, with positions equal to OFFSET."""
    rng = np.random.default_rng(3)
    F = 6
    rows = []
    for _ in range(F):
        root = [5 + rng.normal(), 40 + rng.normal(), rng.normal()]
        rows.append(root + list(rng.uniform(-30, 30, 3)) + [0, -18, 0] + list(rng.uniform(-30, 30, 3)))
    text = ("HIERARCHY\nROOT Hips\n{\n OFFSET 5 40 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation "
            "Xrotation Yrotation\n JOINT Knee\n {\n  OFFSET 0 -18 0\n  CHANNELS 6 Xposition Yposition "
            "Zposition Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -20 0\n  }\n }\n}\n"
            f"MOTION\nFrames: {F}\nFrame Time: 0.0333333\n" + "\n".join(" ".join(map(str, r)) for r in rows))
    (tmp_path / "full.bvh").write_text(text)
    t = load(tmp_path / "full.bvh")
    assert t.meta["position_mode"] == "replace"
    np.testing.assert_allclose(t.xy[0], np.array(rows)[:, :3])  # the root where its channels say
    np.testing.assert_allclose(np.linalg.norm(t.xy[1] - t.xy[0], axis=-1), 18)  # not 36


@pytest.mark.data
def test_cmu_bvh_joint_positions(data_dir):
    t = load(data_dir / "mocap" / "131_01.bvh")
    assert t.shape == (38, 994, 3) and t.frame_rate == pytest.approx(120, rel=1e-4) and t.up_axis == 1
    from stickfigure.io.bvh import read_bvh

    nodes = read_bvh(data_dir / "mocap" / "131_01.bvh").nodes
    assert [n.name for n in nodes] == t.names
    # Every bone keeps its OFFSET length in every frame.
    for i, n in enumerate(nodes):
        if n.parent >= 0:
            d = np.linalg.norm(t.xy[i] - t.xy[n.parent], axis=-1)
            np.testing.assert_allclose(d, np.linalg.norm(n.offset), atol=1e-9)
    # Points of one part keep their distances; the joints CMU never moves are welded.
    for p in range(t.n_parts_true):
        ii = np.flatnonzero(t.labels_true == p)
        d = np.linalg.norm(t.xy[ii][:, None] - t.xy[ii][None], axis=-1)
        assert np.ptp(d, axis=-1).max() < 1e-9
    assert t.meta["part_frames"]["Hips"] == ["Hips", "LHipJoint", "RHipJoint"]
    assert len(t.edges_true) == t.n_parts_true - 1  # a tree


@pytest.mark.data
def test_bvh_virtual_markers(data_dir):
    path = data_dir / "mocap" / "131_01.bvh"
    t = load(path, markers_per_bone=3, random_state=0)
    assert t.meta["points"] == "virtual markers" and t.n_parts_true == load(path).n_parts_true
    assert np.bincount(t.labels_true).min() >= 3
    for p in range(t.n_parts_true):
        ii = np.flatnonzero(t.labels_true == p)
        d = np.linalg.norm(t.xy[ii][:, None] - t.xy[ii][None], axis=-1)
        assert np.ptp(d, axis=-1).max() < 1e-9
        # not collinear: the part's rest shape has rank >= 2
        x = t.xy[ii, 0] - t.xy[ii, 0].mean(0)
        assert np.linalg.svd(x, compute_uv=False)[1] > 1e-3 * np.abs(x).max()
    # each joint is fixed relative to the markers of both parts it joins
    for e, (a, b) in enumerate(t.edges_true):
        for part in (a, b):
            ii = np.flatnonzero(t.labels_true == part)
            d = np.linalg.norm(t.xy[ii] - t.joints_true[e][None], axis=-1)
            assert np.ptp(d, axis=-1).max() < 1e-9
    again = load(path, markers_per_bone=3, random_state=0)
    np.testing.assert_array_equal(t.xy, again.xy)
    assert not np.allclose(t.xy, load(path, markers_per_bone=3, random_state=1).xy)


# MotionBuilder names (the widely shared CMU conversion): joint, parent, OFFSET, end site OFFSET.
_MB_JOINTS = [
    ("Hips", None, (0, 0, 0), None),
    ("LeftUpLeg", "Hips", (1.2, -1.6, 0.6), None), ("LeftLeg", "LeftUpLeg", (0.5, -7.0, 0), None),
    ("LeftFoot", "LeftLeg", (0.3, -6.6, 0), None), ("LeftToeBase", "LeftFoot", (0, -0.4, 2.2), (0, 0, 1.1)),
    ("RightUpLeg", "Hips", (-1.2, -1.6, 0.6), None), ("RightLeg", "RightUpLeg", (-0.5, -7.0, 0), None),
    ("RightFoot", "RightLeg", (-0.3, -6.6, 0), None), ("RightToeBase", "RightFoot", (0, -0.4, 2.2), (0, 0, 1.1)),
    ("Spine", "Hips", (0, 2.0, 0), None), ("Spine1", "Spine", (0, 2.0, 0), None),
    ("Neck", "Spine1", (0, 1.6, 0.1), None), ("Head", "Neck", (0, 1.6, 0), (0, 1.6, 0)),
    ("LeftShoulder", "Spine1", (0.2, 1.2, 0), None), ("LeftArm", "LeftShoulder", (2.8, 0.3, 0), None),
    ("LeftForeArm", "LeftArm", (0, -4.3, 0), None), ("LeftHand", "LeftForeArm", (0, -3.3, 0), (0, -1.2, 0)),
    ("RightShoulder", "Spine1", (-0.2, 1.2, 0), None), ("RightArm", "RightShoulder", (-2.8, 0.3, 0), None),
    ("RightForeArm", "RightArm", (0, -4.3, 0), None), ("RightHand", "RightForeArm", (0, -3.3, 0), (0, -1.2, 0)),
]


def _write_mb_bvh(path, F=9, seed=0):
    """A CMU-named BVH (MotionBuilder names) with random poses."""
    def block(name, depth):
        joint, parent, off, end = next(j for j in _MB_JOINTS if j[0] == name)
        pad = "  " * depth
        kind = "ROOT" if parent is None else "JOINT"
        chans = ("CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation" if parent is None
                 else "CHANNELS 3 Zrotation Yrotation Xrotation")
        out = [f"{pad}{kind} {name}", f"{pad}{{", f"{pad}  OFFSET {off[0]} {off[1]} {off[2]}", f"{pad}  {chans}"]
        for child in (j[0] for j in _MB_JOINTS if j[1] == name):
            out += block(child, depth + 1)
        if end is not None:
            out += [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {end[0]} {end[1]} {end[2]}", f"{pad}  }}"]
        return out + [f"{pad}}}"]

    rng = np.random.default_rng(seed)
    motion = rng.uniform(-40, 40, size=(F, 3 + 3 * len(_MB_JOINTS)))
    rows = "\n".join(" ".join(f"{v:.6f}" for v in r) for r in motion)
    path.write_text("HIERARCHY\n" + "\n".join(block("Hips", 0)) + f"\nMOTION\nFrames: {F}\nFrame Time: 0.01\n"
                    + rows + "\n")


# marker -> its bone's two joints (MotionBuilder names; pelvis markers: the hips and the spine's base)
_MB_BONE_OF = {"FHD": ("Head", "Head_End"), "BHD": ("Head", "Head_End"), "UPA": ("Arm", "ForeArm"),
               "ELB": ("Arm", "ForeArm"), "FRM": ("ForeArm", "Hand"), "WRA": ("ForeArm", "Hand"),
               "WRB": ("ForeArm", "Hand"), "FIN": ("Hand", "Hand_End"), "THI": ("UpLeg", "Leg"),
               "KNE": ("UpLeg", "Leg"), "SHN": ("Leg", "Foot"), "ANK": ("Leg", "Foot"),
               "HEE": ("Foot", "ToeBase"), "TOE": ("Foot", "ToeBase"), "MT5": ("Foot", "ToeBase"),
               "SHO": ("Shoulder", "Arm")}


def test_bvh_cmu41_marker_set_rides_its_bones(tmp_path):
    """Known answer: every marker keeps its distances to its bone's two joints, and sits on the named side."""
    _write_mb_bvh(tmp_path / "mb.bvh")
    t = load(tmp_path / "mb.bvh", marker_set="cmu41")
    joints = load(tmp_path / "mb.bvh")
    J = dict(zip(joints.names, joints.xy))
    assert t.n_points == 41 and len(set(t.names)) == 41 and t.meta["marker_set"] == "cmu41"
    labels, parts, edges, _ = segment_ground_truth(t.names)
    assert parts == list(SEGMENTS) and t.part_names == parts and t.edges_true == edges
    np.testing.assert_array_equal(t.labels_true, labels)
    thigh = np.linalg.norm(J["LeftLeg"][0] - J["LeftUpLeg"][0])
    for name, x in zip(t.names, t.xy):
        side, base = (name[0], name[1:]) if name[1:] in _MB_BONE_OF else ("", name)
        if base in _MB_BONE_OF:
            a, b = _MB_BONE_OF[base]
            side = {"L": "Left", "R": "Right"}[side]
            a = a if a == "Head" else side + a
            b = b if b == "Head_End" else side + b
        elif base in ("FWT", "BWT") or name in ("LFWT", "RFWT", "LBWT", "RBWT"):
            a, b = "LeftUpLeg", "Spine"
        else:  # the thorax's central markers ride Spine1 (or Spine for T10)
            a, b = ("Spine", "Spine1") if name == "T10" else ("Spine1", "Neck")
        for j in (a, b):
            d = np.linalg.norm(x - J[j], axis=-1)
            assert np.ptp(d) < 1e-9 * thigh, (name, j)
    x = dict(zip(t.names, t.xy[:, 0]))
    # the knee marker: 0.12 thigh lengths from the knee, on the bone's end (the table's offset)
    np.testing.assert_allclose(np.linalg.norm(x["LKNE"] - J["LeftLeg"][0]), 0.12 * thigh, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(x["RKNE"] - J["RightLeg"][0]), 0.12 * thigh, rtol=1e-9)
    # mirrored: each left marker is as far from its side's joint as the right one from its own
    np.testing.assert_allclose(np.linalg.norm(x["LTHI"] - J["LeftUpLeg"][0]),
                               np.linalg.norm(x["RTHI"] - J["RightUpLeg"][0]), rtol=1e-9)


def test_bvh_cmu41_pelvis_and_head_band_are_flat(tmp_path):
    """Known answer (io/placement.py): mirrored marker pairs on one bone are coplanar, so the placed
    pelvis and head band are flat sticks (third singular value 0), while the thorax's markers span 3D."""
    _write_mb_bvh(tmp_path / "mb.bvh")
    t = load(tmp_path / "mb.bvh", marker_set="cmu41")
    x = dict(zip(t.names, t.xy[:, 0]))
    joints = load(tmp_path / "mb.bvh")
    J = dict(zip(joints.names, joints.xy[:, 0]))
    thigh = np.linalg.norm(J["LeftLeg"] - J["LeftUpLeg"])

    def third(names):
        pts = np.stack([x[n] for n in names])
        return np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)[2] / thigh

    assert third(["LFWT", "RFWT", "LBWT", "RBWT"]) < 1e-9
    assert third(["LFHD", "RFHD", "LBHD", "RBHD"]) < 1e-9
    assert third(["C7", "CLAV", "STRN", "RBAC"]) > 0.01


def test_bvh_marker_set_errors(tmp_path):
    _write_mb_bvh(tmp_path / "mb.bvh", F=2)
    with pytest.raises(ValueError, match="marker_set must be one of 'cmu41'"):
        load(tmp_path / "mb.bvh", marker_set="plug-in-gait")
    with pytest.raises(ValueError, match="not both"):
        load(tmp_path / "mb.bvh", marker_set="cmu41", markers_per_bone=3)
    _write_bvh(tmp_path / "abc.bvh", F=2)
    with pytest.raises(ValueError, match="needs CMU joint names; no bone for the thigh"):
        load(tmp_path / "abc.bvh", marker_set="cmu41")


@pytest.mark.data
def test_bvh_cmu41_marker_set_matches_the_cmu_take(data_dir):
    """131_01 with the 41 markers: the recorded CMU take's names, segments and body tree; rigid per bone."""
    t = load(data_dir / "mocap" / "131_01.bvh", marker_set="cmu41")
    take = load(data_dir / "mocap" / "85_02.c3d")
    assert sorted(t.names) == sorted(take.names)
    assert t.part_names == take.part_names and t.edges_true == take.edges_true
    by_name = dict(zip(take.names, take.labels_true))
    assert [by_name[n] for n in t.names] == list(t.labels_true)
    x = dict(zip(t.names, t.xy))
    for a, b in (("LFHD", "RBHD"), ("LTHI", "LKNE"), ("RSHN", "RANK"), ("LFWT", "RBWT"), ("LHEE", "LMT5")):
        assert np.ptp(np.linalg.norm(x[a] - x[b], axis=-1)) < 1e-9
    # the elbow bends: the upper-arm marker to the wrist is not rigid (by a tenth of the thigh or more)
    thigh = np.linalg.norm(x["LKNE"][0] - x["LTHI"][0])
    assert np.ptp(np.linalg.norm(x["LUPA"] - x["LWRA"], axis=-1)) > 0.1 * thigh


# ------------------------------------------------------------------ ASF/AMC
_ASF = """# test skeleton
:version 1.10
:name test
:units
  mass 1.0
  length 0.5
  angle {ANGLE}
:documentation
  two bones
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name a
     direction 1 0 0
     length 2
     axis 0 0 {AXIS} XYZ
    dof rx ry rz
    limits (-180.0 180.0)
           (-180.0 180.0)
           (-180.0 180.0)
  end
  begin
     id 2
     name b
     direction 0 1 0
     length 1
     axis 0 0 0 XYZ
    dof rz
    limits (-180.0 180.0)
  end
:hierarchy
  begin
    root a
    a b
  end
"""


def _write_acclaim(folder, asf_name="sk.asf", amc_name="sk_01.amc", radians=False):
    k = np.pi / 180 if radians else 1.0
    (folder / asf_name).write_text(_ASF.replace("{ANGLE}", "rad" if radians else "deg")
                                   .replace("{AXIS}", repr(90 * k)))
    frames = [  # root (tx ty tz rx ry rz), a (rx ry rz), b (rz)
        ([0, 0, 0, 0, 0, 0], [0, 0, 90], [0]),
        ([0, 0, 0, 0, 0, 0], [90, 0, 0], [0]),
        ([1, 2, 3, 0, 90, 0], [0, 0, 0], [90]),
    ]
    lines = [":FULLY-SPECIFIED", ":RADIANS" if radians else ":DEGREES"]
    for i, (r, a, b) in enumerate(frames, start=1):
        rr = r[:3] + [v * k for v in r[3:]]
        lines += [str(i), "root " + " ".join(map(str, rr)), "a " + " ".join(str(v * k) for v in a),
                  "b " + " ".join(str(v * k) for v in b)]
    (folder / amc_name).write_text("\n".join(lines) + "\n")
    return folder / amc_name


@pytest.mark.parametrize("radians", [False, True])
def test_acclaim_known_answers(tmp_path, radians):
    amc = _write_acclaim(tmp_path, radians=radians)
    t = load(amc, merge_rigid=False)  # finds sk.asf beside it
    assert t.names == ["root", "a", "b"] and t.meta["units"] is None and t.up_axis == 1
    a, b = t.xy[1], t.xy[2]
    # lengths are divided by the unit 0.5: a is 4 long, b 2.
    # Frame 1: a turns 90 deg about its axis frame's z (= global z): +x -> +y.
    np.testing.assert_allclose(a[0], [0, 4, 0], atol=1e-9)
    np.testing.assert_allclose(b[0], [-2, 4, 0], atol=1e-9)  # b's +y turned with a
    # Frame 2: rx = 90 in a's axis frame, whose x is the global y (axis z = 90):
    # a turns about global y, +x -> -z. This pins the C M C^-1 convention.
    np.testing.assert_allclose(a[1], [0, 0, -4], atol=1e-9)
    # Frame 3: root moved by (1, 2, 3) / 0.5 and turned 90 deg about y; b turns about z.
    np.testing.assert_allclose(t.xy[0, 2], [2, 4, 6], atol=1e-9)
    np.testing.assert_allclose(a[2], [2, 4, 2], atol=1e-9)
    np.testing.assert_allclose(b[2], [2, 4, 2] + np.array([0, 0, 2.0]), atol=1e-9)
    assert [t.part_names[i] for i in t.labels_true] == ["root", "a", "b"]
    assert t.edges_true == [(0, 1), (1, 2)]
    np.testing.assert_allclose(t.joints_true[1], a, atol=1e-9)  # b starts where a ends


def test_acclaim_skeleton_lookup(tmp_path):
    (tmp_path / "cmu").mkdir()
    amc = _write_acclaim(tmp_path / "cmu", asf_name="131.asf", amc_name="131_01.amc")
    assert load(amc).meta["skeleton"].endswith("131.asf")
    assert load(amc).meta["frame_rate_source"].startswith("default")
    (tmp_path / "hdm").mkdir()
    amc = _write_acclaim(tmp_path / "hdm", asf_name="HDM_dg.asf", amc_name="HDM_dg_06-03_03_120.amc")
    (tmp_path / "hdm" / "HDM_bd.asf").write_text((tmp_path / "hdm" / "HDM_dg.asf").read_text())
    t = load(amc)
    assert t.meta["skeleton"].endswith("HDM_dg.asf") and t.frame_rate == 120
    assert t.meta["n_figures"] == 1
    assert load(amc, frame_rate=30).frame_rate == 30
    with pytest.raises(ValueError, match=r"ASF skeleton without motion.*HDM_dg_06-03_03_120\.amc"):
        load(tmp_path / "hdm" / "HDM_dg.asf")
    (tmp_path / "none").mkdir()
    lone = tmp_path / "none" / "x.amc"
    lone.write_text(amc.read_text())
    with pytest.raises(FileNotFoundError, match="no .asf skeleton beside"):
        load(lone)
    assert load(lone, asf=tmp_path / "hdm" / "HDM_dg.asf").n_frames == 3


@pytest.mark.data
def test_hdm05_amc(data_dir):
    t = load(data_dir / "mocap" / "HDM_dg_06-03_03_120.amc")
    assert t.shape == (31, 202, 3) and t.frame_rate == 120 and t.meta["units"] == "in"
    assert t.meta["skeleton"].endswith("HDM_dg.asf")
    # bones without dof (hip joints) and the clavicles that never move are welded
    assert t.meta["part_frames"]["root"] == ["root", "lhipjoint", "rhipjoint"]
    assert len(t.edges_true) == t.n_parts_true - 1
    for p in range(t.n_parts_true):
        ii = np.flatnonzero(t.labels_true == p)
        d = np.linalg.norm(t.xy[ii][:, None] - t.xy[ii][None], axis=-1)
        assert np.ptp(d, axis=-1).max() < 1e-9


@pytest.mark.data
def test_hdm05_markers_ride_on_the_amc_skeleton(data_dir):
    """C3D markers (mm, z up) and AMC forward kinematics of the same take agree.

    Each marker, expressed in the frame of the bone that carries it best, should
    stay put: the residual is skin motion plus HDM05's skeleton fit. Measured:
    median 13.6 mm, max 24.9 mm; with intrinsic instead of fixed-axis Euler angles
    the median is 70 mm.
    """
    from stickfigure.io.asfamc import asf_amc_rig, read_amc, read_asf

    mocap = data_dir / "mocap"
    markers = load(mocap / "HDM_dg_06-03_03_120.c3d")
    assert markers.meta["units"] == "mm"
    asf = read_asf(mocap / "HDM_dg.asf")
    rig = asf_amc_rig(asf, read_amc(mocap / "HDM_dg_06-03_03_120.amc", asf))
    perm = np.eye(3)[[2, 0, 1]]  # AMC (x, y, z), y up -> C3D (z, x, y), z up
    R = np.einsum("ij,bfjk->bfik", perm, rig.rotation)
    o = np.einsum("ij,bfj->bfi", perm, rig.origin) * 25.4  # inches -> mm
    m = markers.xy[~markers.meta["unlabelled"]]
    local = np.einsum("bfji,pbfj->pbfi", R, m[:, None] - o[None])  # (P, bones, F, 3)
    resid = np.sqrt(local.var(axis=2).sum(-1)).min(axis=1)
    assert np.median(resid) < 20 and resid.max() < 35, np.round(resid, 1)


# ---------------------------------------------------------- MoCap Toolbox
@pytest.mark.data
def test_mocaptoolbox_takes(data_dir):
    path = data_dir / "mocap" / "mcdemodata.mat"
    first = load(path)
    assert first.meta["take"] == "dance1" and set(first.meta["takes"]) >= {"walk1", "walk2", "dance1", "dance2"}
    walk = load(path, take="walk1")
    assert walk.shape == (28, 351, 3) and walk.frame_rate == 60 and walk.up_axis == 2
    assert np.isnan(walk.xy).any() and walk.meta["units"] == "mm" and walk.meta["n_figures"] == 1
    assert walk.part_names == list(SEGMENTS) and (walk.labels_true >= 0).all() and len(walk.edges_true) == 14
    assert walk.joints_true.shape == (14, 351, 3)
    assert len(walk.meta["joint_names"]) == 20 and len(walk.meta["joint_edges"]) == 19
    # The knee joint (m2jpar: the knee marker) is the Knee_L marker.
    e = walk.meta["edge_joints"].index("l_knee")
    np.testing.assert_array_equal(walk.joints_true[e], walk.xy[walk.names.index("Knee_L")])
    # the joint between two parts is near the markers of both
    head = walk.part_names.index("head")
    assert np.nanmean(np.linalg.norm(walk.joints_true[walk.meta["edge_joints"].index("neck")]
                                     - np.nanmean(walk.xy[walk.labels_true == head], axis=0), axis=-1)) < 400
    with pytest.raises(ValueError, match="takes: dance1, dance2, walk1, walk2"):
        load(path, take="run")
