"""Hopkins 155, SLEAP, dispatch, and clear errors for truncated or malformed files of every kind."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import scipy.io

import stickfigure as sf
from stickfigure.io import SUPPORTED, load

HOPKINS = {  # sequence: (P, F, number of motions)
    "1R2RC": (459, 29, 3), "arm": (77, 30, 2), "articulated": (150, 31, 3), "dancing": (268, 40, 5),
    "head": (99, 60, 2), "people1": (504, 41, 2), "truck1": (188, 30, 2), "two_cranes": (94, 30, 3),
}


# ------------------------------------------------------------------ Hopkins
@pytest.mark.data
@pytest.mark.parametrize("seq", sorted(HOPKINS))
def test_hopkins_sequences(data_dir, seq):
    path = data_dir / "hopkins155" / seq / f"{seq}_truth.mat"
    t = load(path)
    P, F, k = HOPKINS[seq]
    assert t.shape == (P, F, 2) and t.n_parts_true == k and t.edges_true is None
    raw = scipy.io.loadmat(str(path))
    np.testing.assert_array_equal(t.labels_true, raw["s"].ravel().astype(int) - 1)  # 1-based -> 0-based
    assert t.image_size == (int(raw["width"].item()), int(raw["height"].item()))
    np.testing.assert_allclose(t.xy[:, :, 0], raw["y"][0] / raw["y"][2])
    # pixel coordinates, inside (or at the border of) the image
    assert np.nanmin(t.xy) > -50 and np.nanmax(t.xy[..., 0]) < t.image_size[0] + 50
    assert t.meta["source"] == str(path) and t.meta["units"] == "px" and t.meta["sequence"] == seq


def test_hopkins_optional_fields(tmp_path):
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(size=(2, 6, 4)), np.ones((1, 6, 4))])
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    s = np.array([[1], [1], [2], [2], [3], [3]], np.uint8)
    scipy.io.savemat(tmp_path / "a_truth.mat", {"y": K @ x.reshape(3, -1), "s": s})  # wrong shape on purpose
    with pytest.raises(ValueError, match="a_truth.mat.*3 x P x F"):
        load(tmp_path / "a_truth.mat")
    scipy.io.savemat(tmp_path / "b_truth.mat", {"x": x, "K": K, "s": s})  # no y, no width/height
    t = load(tmp_path / "b_truth.mat")
    assert t.image_size is None and t.labels_true.tolist() == [0, 0, 1, 1, 2, 2]
    np.testing.assert_allclose(t.xy[:, :, 0], 500 * x[0] + 320)
    scipy.io.savemat(tmp_path / "c_truth.mat", {"y": (K @ x.reshape(3, -1)).reshape(3, 6, 4)[:2]})  # 2D, no s
    t = load(tmp_path / "c_truth.mat")
    assert t.labels_true is None and t.shape == (6, 4, 2)
    scipy.io.savemat(tmp_path / "d_truth.mat", {"y": x, "s": s, "points": 7, "frames": 4})
    with pytest.raises(ValueError, match="'points' says 7"):
        load(tmp_path / "d_truth.mat")
    scipy.io.savemat(tmp_path / "e_truth.mat", {"y": x, "s": s - 1})
    with pytest.raises(ValueError, match="1-based"):
        load(tmp_path / "e_truth.mat")
    scipy.io.savemat(tmp_path / "f.mat", {"foo": np.zeros(3)})
    with pytest.raises(ValueError, match="unknown MATLAB content.*foo"):
        load(tmp_path / "f.mat")


def test_hopkins_matlab_v73(tmp_path):
    import h5py
    path = tmp_path / "v73_truth.mat"
    y = np.concatenate([np.arange(30.0).reshape(2, 5, 3), np.ones((1, 5, 3))])
    with h5py.File(path, "w", userblock_size=512) as f:
        f["y"] = y.T  # HDF5 stores MATLAB arrays transposed
        f["s"] = np.array([[1, 1, 2, 2, 2]], float).T
        f["width"] = np.array([[640.0]])
        f["height"] = np.array([[480.0]])
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write((header.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02IM").ljust(512, b"\x00"))
    t = load(path)
    assert t.shape == (5, 3, 2) and t.labels_true.tolist() == [0, 0, 1, 1, 1] and t.image_size == (640, 480)
    np.testing.assert_allclose(t.xy[:, :, 0], y[0])


# -------------------------------------------------------------------- SLEAP
@pytest.mark.data
def test_sleap_clip(data_dir):
    import h5py

    path = data_dir / "video" / "clip.slp"
    t = load(path)
    assert t.shape == (26, 1500, 2) and t.meta["tracks"] == ["female", "male"] and t.meta["n_figures"] == 2
    assert t.names[0] == "female/head" and t.names[13] == "male/head" and len(t.meta["nodes"]) == 13
    assert t.labels_true.tolist() == list(range(26)) and t.part_names == t.names
    assert len(t.edges_true) == 24 and (1, 0) in t.edges_true and (14, 13) in t.edges_true  # thorax-head
    assert t.video == str(data_dir / "video" / "clip.mp4") and t.image_size == (1024, 1024)
    assert t.meta["frame_offset"] == 0 and len(t.meta["labelled_frames"]) == 1500
    # independent check of one instance against the raw tables
    with h5py.File(path, "r") as f:
        inst = f["instances"][:]
        pts = f["points"][:]
        frames = f["frames"][:]
    i = 101
    fidx = frames["frame_idx"][frames["frame_id"] == inst["frame_id"][i]][0]
    raw = pts[inst["point_id_start"][i]:inst["point_id_end"][i]]
    mine = t.xy[inst["track"][i] * 13:(inst["track"][i] + 1) * 13, fidx]
    np.testing.assert_array_equal(mine[:, 0], raw["x"])  # NaN where the node is missing
    assert np.isnan(t.xy).any(axis=2).sum() == np.isnan(pts["x"]).sum()
    male = load(path, track="male")
    np.testing.assert_array_equal(male.xy, t.xy[13:])
    assert male.edges_true == t.edges_true[:12]
    with pytest.raises(ValueError, match="tracks: female, male"):
        load(path, track="dog")


def _write_slp(path, format_id=1.2, with_video_shape=True):
    """A small SLEAP file from scratch: 3 nodes, untracked instances, a gap, a prediction."""
    import h5py
    reduce = lambda k: {"py/reduce": [{"py/type": "sleap.skeleton.EdgeType"}, {"py/tuple": [k]}]}  # noqa: E731
    meta = {
        "version": "2.0.0",
        "nodes": [{"name": "a", "weight": 1.0}, {"name": "b", "weight": 1.0}, {"name": "c", "weight": 1.0}],
        "skeletons": [{
            "directed": True, "graph": {"name": "s"}, "multigraph": True,
            "nodes": [{"id": 1}, {"id": 0}, {"id": 2}],  # skeleton order: b, a, c
            "links": [{"source": 1, "target": 0, "type": reduce(1)},
                      {"source": 0, "target": 2, "type": reduce(2)},   # a symmetry, not a bone
                      {"source": 1, "target": 2, "type": {"py/id": 1}}],
        }],
    }
    fdt = [("frame_id", "<u8"), ("video", "<u4"), ("frame_idx", "<u8"), ("instance_id_start", "<u8"),
           ("instance_id_end", "<u8")]
    idt = [("instance_id", "<i8"), ("instance_type", "u1"), ("frame_id", "<u8"), ("skeleton", "<u4"),
           ("track", "<i4"), ("from_predicted", "<i8"), ("score", "<f4"), ("point_id_start", "<u8"),
           ("point_id_end", "<u8")]
    pdt = [("x", "<f8"), ("y", "<f8"), ("visible", "?"), ("complete", "?")]
    qdt = pdt + [("score", "<f8")]
    frames = np.array([(0, 0, 3, 0, 2), (1, 0, 5, 2, 3), (2, 0, 6, 3, 5), (3, 0, 4, 5, 6)], fdt)
    # instances: frame 3 two, frame 5 one, frame 6 two (user); frame 4 one prediction
    inst = np.array([(0, 0, 0, 0, -1, -1, 0, 0, 3), (1, 0, 0, 0, -1, -1, 0, 3, 6),
                     (2, 0, 1, 0, -1, -1, 0, 6, 9), (3, 0, 2, 0, -1, -1, 0, 9, 12),
                     (4, 0, 2, 0, -1, -1, 0, 12, 15), (5, 1, 3, 0, -1, -1, 0.9, 0, 3)], idt)
    pts = np.zeros(15, pdt)
    pts["x"] = np.arange(15) * 10.0
    pts["y"] = np.arange(15) * 10.0 + 1
    pts["visible"] = True
    pts["visible"][4] = False  # instance 1, node a: invisible
    pred = np.zeros(3, qdt)
    pred["x"], pred["y"], pred["visible"] = [100.0, 200, 300], [1.0, 2, 3], True
    backend = {"filename": "missing_video.mp4"}
    if with_video_shape:
        backend["shape"] = [10, 480, 640, 1]
    with h5py.File(path, "w") as f:
        g = f.create_dataset("metadata", data=np.zeros(1))
        g.attrs["format_id"] = format_id
        g.attrs["json"] = json.dumps(meta)
        f["frames"] = frames
        f["instances"] = inst
        f["points"] = pts
        f["pred_points"] = pred
        f["tracks_json"] = np.array([], dtype="S1")
        f["videos_json"] = np.array([json.dumps({"backend": backend}).encode()])
    return path


def test_sleap_untracked_gaps_and_predictions(tmp_path):
    path = _write_slp(tmp_path / "s.slp")
    t = load(path)
    assert t.names == ["instance0/b", "instance0/a", "instance0/c", "instance1/b", "instance1/a", "instance1/c"]
    assert t.shape == (6, 4, 2) and t.meta["frame_offset"] == 3 and t.meta["labelled_frames"] == [0, 2, 3]
    assert t.edges_true == [(0, 1), (0, 2), (3, 4), (3, 5)]  # the symmetry link is not a bone
    assert t.image_size == (640, 480) and t.video == "missing_video.mp4"
    np.testing.assert_array_equal(t.xy[0, 0], [0, 1])        # frame 3, instance 0, node b
    np.testing.assert_array_equal(t.xy[3, 0], [30, 31])      # frame 3, instance 1
    assert np.isnan(t.xy[4, 0]).all()                       # invisible node
    assert np.isnan(t.xy[:, 1]).all()                       # frame 4: only a prediction
    assert np.isnan(t.xy[3:, 2]).all()                      # frame 5: one animal
    both = load(path, instances="all")
    np.testing.assert_array_equal(both.xy[:3, 1], [[100, 1], [200, 2], [300, 3]])
    np.testing.assert_array_equal(both.xy[:, [0, 2, 3]], t.xy[:, [0, 2, 3]])  # user labels kept
    one = load(path, instance=1)
    np.testing.assert_array_equal(one.xy, t.xy[3:])
    with pytest.raises(ValueError, match="instances must be"):
        load(path, instances="some")
    with pytest.raises(ValueError, match="only one labelled frame"):
        load(path, instances="predicted")
    old = load(_write_slp(tmp_path / "old.slp", format_id=1.0, with_video_shape=False))
    np.testing.assert_array_equal(old.xy[0, 0], [-0.5, 0.5])  # legacy pixel-corner convention
    assert old.image_size is None


# -------------------------------------------------------- dispatch + errors
def test_unknown_extension_and_missing_file(tmp_path):
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(ValueError, match=r"unknown file type '\.txt'.*\.c3d.*\.bvh.*\.slp"):
        load(tmp_path / "x.txt")
    (tmp_path / "v.mp4").write_bytes(b"")
    with pytest.raises(ValueError, match="stickfigure.track"):
        load(tmp_path / "v.mp4")
    with pytest.raises(FileNotFoundError, match="nope.c3d"):
        load(tmp_path / "nope.c3d")
    with pytest.raises(TypeError, match="unknown option.*valid: markers_per_bone"):
        load(tmp_path / "x.bvh" if False else _bvh(tmp_path), colour="red")
    with pytest.raises(TypeError, match="path must be"):
        load(42)
    d = tmp_path / "dir.csv"
    d.mkdir()
    with pytest.raises(ValueError, match="directory"):
        load(d)


def _bvh(tmp_path):
    p = tmp_path / "mini.bvh"
    p.write_text("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 3 Xposition Yposition Zposition\n"
                 "End Site\n{\nOFFSET 0 1 0\n}\n}\nMOTION\nFrames: 2\nFrame Time: 0.1\n0 0 0\n1 1 1\n")
    return p


def test_supported_table_lists_every_reader():
    assert set(SUPPORTED) == {".c3d", ".bvh", ".amc", ".mat", ".slp", ".csv", ".npz"}


_REAL = ["mocap/85_02.c3d", "mocap/HDM_dg_06-03_03_120.c3d", "mocap/131_01.bvh",
         "mocap/HDM_dg_06-03_03_120.amc", "mocap/mcdemodata.mat", "hopkins155/arm/arm_truth.mat",
         "video/clip.slp"]


def _copy_truncated(data_dir, rel, tmp_path, fraction):
    src = data_dir / rel
    dst = tmp_path / src.name
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    if src.suffix == ".amc":
        shutil.copy(src.parent / "HDM_dg.asf", tmp_path / "HDM_dg.asf")
    return dst


@pytest.mark.data
@pytest.mark.parametrize("rel", _REAL)
@pytest.mark.parametrize("fraction", [0.0, 0.003, 0.5, 0.97])
def test_truncated_real_files_give_one_line_errors(data_dir, tmp_path, rel, fraction):
    path = _copy_truncated(data_dir, rel, tmp_path, fraction)
    with pytest.raises(ValueError) as info:
        load(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg, msg
    # no chained library traceback behind the message
    assert info.value.__cause__ is None and (info.value.__context__ is None or info.value.__suppress_context__)


@pytest.mark.data
def test_truncated_asf(data_dir, tmp_path):
    text = (data_dir / "mocap" / "HDM_dg.asf").read_text(encoding="latin-1")
    shutil.copy(data_dir / "mocap" / "HDM_dg_06-03_03_120.amc", tmp_path)
    for cut in (len(text) // 3, len(text) - 30):
        (tmp_path / "HDM_dg.asf").write_text(text[:cut], encoding="latin-1")
        with pytest.raises(ValueError, match=r"HDM_dg\.asf.*(truncated|no :hierarchy|not closed)"):
            load(tmp_path / "HDM_dg_06-03_03_120.amc")


@pytest.mark.parametrize("suffix", [".c3d", ".bvh", ".amc", ".mat", ".slp", ".csv", ".npz"])
@pytest.mark.parametrize("garbage", [b"", b"\x00\x01\x02" * 300, "ceci n'est pas un fichier\n".encode() * 40])
def test_garbage_files_give_one_line_errors(tmp_path, suffix, garbage):
    path = tmp_path / f"junk{suffix}"
    path.write_bytes(garbage)
    if suffix == ".amc":
        (tmp_path / "junk.asf").write_text(_ASF_MINI)
    with pytest.raises(ValueError) as info:
        load(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg, msg


_ASF_MINI = """:version 1.10
:units
  length 1
  angle deg
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
     length 1
     axis 0 0 0 XYZ
    dof rz
  end
:hierarchy
  begin
    root a
  end
"""


@pytest.mark.parametrize(
    "text, match",
    [
        ("HIERARCHY\nROOT r\n{\nOFFSET 0 0\n", "no MOTION"),
        ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 2 Xposition Wobble\n}\nMOTION\nFrames: 2\n"
         "Frame Time: 0.1\n0 0\n0 0\n", "bad CHANNELS"),
        ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 1 Xposition\n}\nMOTION\nFrames: 3\nFrame Time: 0.1\n0\n1\n",
         "truncated motion data.*2 complete frames"),
        ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 1 Xposition\n}\nMOTION\nFrames: 2\nFrame Time: 0\n0\n1\n",
         "Frame Time must be > 0"),
        ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 1 Xposition\n\nMOTION\nFrames: 2\nFrame Time: 0.1\n0\n1\n",
         "not closed"),
        ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 1 Xposition\n}\nMOTION\nFrames: 2\nFrame Time: 0.1\n0\nx\n",
         "non-numeric motion value 'x'"),
    ],
)
def test_malformed_bvh(tmp_path, text, match):
    path = tmp_path / "m.bvh"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        load(path)


def test_malformed_amc(tmp_path):
    (tmp_path / "s.asf").write_text(_ASF_MINI)
    cases = {
        "1\nroot 0 0 0 0 0 0\na 1\n2\nroot 0 0 0 0 0 0\n": "missing from 1 frame",
        "1\nroot 0 0 0 0 0 0\na 1 2\n2\nroot 0 0 0 0 0 0\na 1 2\n": "has 2 values.*1 dof",
        "1\nroot 0 0 0 0 0 0\nzz 1\n2\nroot 0 0 0 0 0 0\nzz 1\n": "'zz' is not in the skeleton",
        "root 0 0 0 0 0 0\n": "frame number",
        "1\nroot 0 0 0 0 0 0\na 1\n": "at least 2",
    }
    for text, match in cases.items():
        (tmp_path / "s_1.amc").write_text(text)
        with pytest.raises(ValueError, match=match):
            load(tmp_path / "s_1.amc")


def test_load_options_are_checked(tmp_path):
    bvh = _bvh(tmp_path)
    with pytest.raises(ValueError, match="markers_per_bone must be >= 0"):
        load(bvh, markers_per_bone=-2)
    with pytest.raises(TypeError, match="random_state"):
        load(bvh, markers_per_bone=2, random_state="seed")
    t = load(bvh)
    assert t.names == ["r", "r_End"] and t.xy[1, 1].tolist() == [1, 2, 1]
    assert isinstance(sf.load(bvh), sf.Trajectories)
