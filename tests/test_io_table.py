"""stickfigure's own files: CSV long format and NPZ archive, round trips and bad input."""

from __future__ import annotations

import os
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import stickfigure as sf
from stickfigure.io import load, save

_names = st.text(
    alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), min_size=0, max_size=8
)


@st.composite
def trajectories(draw, with_truth: bool = True):
    P = draw(st.integers(1, 5))
    F = draw(st.integers(2, 6))
    D = draw(st.sampled_from([2, 3]))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    # Values of very different magnitudes, to test the exact float round trip.
    xy = rng.normal(size=(P, F, D)) * 10.0 ** rng.integers(-6, 6, size=(P, 1, 1))
    missing = rng.random((P, F)) < draw(st.sampled_from([0.0, 0.3, 0.9]))
    xy[missing] = np.nan
    names = draw(st.lists(_names, min_size=P, max_size=P, unique=True))
    kw = {}
    if with_truth and draw(st.booleans()):
        k = draw(st.integers(1, 3))
        kw["labels_true"] = rng.integers(-1, k, size=P)
        kw["part_names"] = [f"part {i}, \"q\"" for i in range(k)]
        kw["edges_true"] = [(i, i + 1) for i in range(k - 1)]
    if draw(st.booleans()):
        kw["frame_rate"] = float(draw(st.floats(0.5, 1000, allow_nan=False)))
    if D == 2 and draw(st.booleans()):
        kw["image_size"] = (draw(st.integers(1, 4000)), draw(st.integers(1, 4000)))
    if D == 3:
        kw["up_axis"] = draw(st.sampled_from([0, 1, 2]))
    meta = {"frame_offset": draw(st.integers(0, 500))}
    return sf.Trajectories(xy, names=names, meta=meta, allow_unobserved=True, **kw)


def _same(a: sf.Trajectories, b: sf.Trajectories) -> None:
    assert a.shape == b.shape
    np.testing.assert_array_equal(a.xy, b.xy)  # exact, NaN in the same places
    assert a.names == b.names
    assert a.frame_rate == b.frame_rate
    assert a.image_size == b.image_size
    if a.labels_true is None:
        assert b.labels_true is None
    else:
        np.testing.assert_array_equal(a.labels_true, b.labels_true)
    assert a.part_names == b.part_names
    assert a.edges_true == b.edges_true
    if a.n_dims == 3:
        assert a.up_axis == b.up_axis
    assert a.meta.get("frame_offset", 0) == b.meta.get("frame_offset", 0)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(traj=trajectories())
def test_csv_round_trip(tmp_path, traj):
    path = tmp_path / "t.csv"
    save(traj, path)
    back = load(path)
    _same(traj, back)
    assert back.meta["source"] == str(path) and back.meta["format"] == "csv"


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(traj=trajectories())
def test_npz_round_trip(tmp_path, traj):
    path = tmp_path / "t.npz"
    save(traj, path)
    back = load(path)
    _same(traj, back)


def test_npz_keeps_joints_meta_and_has_no_pickle(tmp_path):
    traj = sf.synthetic.random_figure(n_sticks=3, frames=10, seed=1)
    traj = traj.copy(meta={**traj.meta, "unlabelled": np.zeros(traj.n_points, bool), "units": "mm"},
                     video="clip.mp4")
    path = sf.io.save(traj, tmp_path / "sub" / "t.npz")  # creates the folder
    with np.load(path, allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)
        assert z["names"].dtype.kind == "U" if "names" in z.files else True
    back = load(path)
    np.testing.assert_array_equal(back.joints_true, traj.joints_true)
    np.testing.assert_array_equal(back.meta["unlabelled"], traj.meta["unlabelled"])
    assert back.meta["units"] == "mm" and back.meta["generator"] == "random_figure"
    assert back.video == "clip.mp4"


def test_csv_format_as_documented(tmp_path):
    path = tmp_path / "hand.csv"
    path.write_text(
        "# a comment\n# frame_rate: 25\n# image_size: 640 480\n"
        "point,frame,x,y,label_true\n"
        "a,10,1.5,2,0\n"
        "a,12,3,4,0\n"
        "b,11,,,1\n"      # an empty observation
        "b,12,5,nan,1\n"  # a partly missing one counts as missing
        "c,11,7,8,1\n"
    )
    t = load(path)
    assert t.names == ["a", "b", "c"] and t.shape == (3, 3, 2)
    assert t.frame_rate == 25 and t.image_size == (640, 480)
    assert t.meta["frame_offset"] == 10
    np.testing.assert_array_equal(t.labels_true, [0, 1, 1])
    assert t.xy[0, 0].tolist() == [1.5, 2.0] and np.isnan(t.xy[0, 1]).all()
    assert np.isnan(t.xy[1]).all() and t.xy[2, 1].tolist() == [7.0, 8.0]


def test_csv_3d_header(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("point,frame,x,y,z\np,0,1,2,3\np,1,4,5,6\n")
    t = load(path)
    assert t.shape == (1, 2, 3) and t.xy[0, 1].tolist() == [4, 5, 6]


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "no header"),
        ("# only comments\n", "no header"),
        ("name,time,u,v\na,0,1,2\n", "header must start"),
        ("point,frame,x,y\n", "no data rows"),
        ("point,frame,x,y\na,0,1\n", "line 2: 3 columns"),
        ("point,frame,x,y\na,zero,1,2\na,1,1,2\n", "not an integer"),
        ("point,frame,x,y\na,0,1,oops\na,1,1,2\n", "not a number"),
        ("point,frame,x,y\na,0,1,2\na,0,3,4\n", "several rows for frame 0"),
        ("point,frame,x,y,label_true\na,0,1,2,0\na,1,1,2,1\n", "two different label_true"),
        ("point,frame,x,y\na,0,1,inf\na,1,1,2\n", "infinite"),
        ("# frame_rate: fast\npoint,frame,x,y\na,0,1,2\na,1,1,2\n", "frame_rate"),
        ("point,frame,x,y\na,0,1,2\n", "at least 2 frames"),
    ],
)
def test_bad_csv_gives_one_line_error_naming_the_file(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        load(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg


def test_truncated_csv(tmp_path):
    traj = sf.synthetic.random_figure(n_sticks=2, frames=8, seed=0)
    good = save(traj, tmp_path / "t.csv")
    text = good.read_text()
    cut = tmp_path / "cut.csv"
    cut.write_text(text[: len(text) // 2].rsplit(",", 1)[0])  # ends inside a row
    with pytest.raises(ValueError, match="cut.csv.*columns"):
        load(cut)


@pytest.mark.parametrize("data", [b"", b"PK\x03\x04garbage", b"\x00" * 100])
def test_bad_npz(tmp_path, data):
    path = tmp_path / "bad.npz"
    path.write_bytes(data)
    with pytest.raises(ValueError, match="bad.npz") as info:
        load(path)
    assert "\n" not in str(info.value)


def test_truncated_npz_and_pickled_npz(tmp_path):
    traj = sf.synthetic.random_figure(n_sticks=2, frames=8, seed=0)
    good = save(traj, tmp_path / "t.npz")
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ValueError, match="cut.npz"):
        load(cut)
    pickled = tmp_path / "p.npz"
    np.savez(pickled, xy=np.zeros((2, 3, 2)), names=np.array([{"a": 1}, None], dtype=object))
    with pytest.raises(ValueError, match="pickle"):
        load(pickled)
    no_xy = tmp_path / "noxy.npz"
    np.savez(no_xy, a=np.zeros(3))
    with pytest.raises(ValueError, match="no 'xy'"):
        load(no_xy)


def test_save_errors_and_atomicity(tmp_path):
    traj = sf.synthetic.random_figure(n_sticks=2, frames=8, seed=0)
    with pytest.raises(ValueError, match=r"cannot write '\.txt'.*\.csv, \.npz"):
        save(traj, tmp_path / "t.txt")
    with pytest.raises(TypeError, match="Trajectories"):
        save(np.zeros((2, 3, 2)), tmp_path / "t.csv")
    dup = traj.copy(names=["same"] * traj.n_points)
    with pytest.raises(ValueError, match="unique names"):
        save(dup, tmp_path / "d.csv")
    assert not list(tmp_path.glob("*d.csv*"))  # nothing half-written
    # Overwriting keeps a complete file.
    save(traj, tmp_path / "t.csv")
    save(traj.slice(frames=slice(0, 4)), tmp_path / "t.csv")
    assert load(tmp_path / "t.csv").n_frames == 4
    assert [p.name for p in tmp_path.iterdir()] == ["t.csv"]
    # an atomic write still gets the permissions a plain open() would give (not mkstemp's 0600)
    mask = os.umask(0o022)
    try:
        save(traj, tmp_path / "perm.npz")
    finally:
        os.umask(mask)
    assert (tmp_path / "perm.npz").stat().st_mode & 0o777 == 0o644


def test_npz_is_a_zip_of_plain_arrays(tmp_path):
    traj = sf.synthetic.arm(seed=0)
    path = save(traj, tmp_path / "arm.npz")
    with zipfile.ZipFile(path) as z:
        assert "xy.npy" in z.namelist() and "meta_json.npy" in z.namelist()


def test_top_level_load_save_delegate(tmp_path):
    traj = sf.synthetic.arm(seed=0)
    sf.save(traj, tmp_path / "a.csv")
    assert sf.load(tmp_path / "a.csv").shape == traj.shape
