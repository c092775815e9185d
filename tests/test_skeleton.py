"""The result type: validation and JSON+NPZ round trip."""

import json

import numpy as np
import pytest

import stickfigure as sf


def _skel(**kw):
    args = dict(
        method="sfm",
        labels=np.array([0, 0, 1, 1, -1]),
        n_sticks=2,
        edges=[(0, 1)],
        joints=np.arange(12.0).reshape(1, 6, 2),
        motions=np.random.default_rng(0).normal(size=(2, 6, 2, 4)),
        local=np.random.default_rng(1).normal(size=(5, 3)),
        log_likelihood=-12.5,
        params={"alpha": 1.0, "shape": (2, 3)},
        point_names=list("abcde"),
        state={"L": np.eye(3), "names": np.array(["x", "y"])},
        info={"stages": [1.0, 2.0], "best": np.int64(1)},
    )
    args.update(kw)
    return sf.Skeleton(**args)


def test_round_trip(tmp_path):
    s = _skel()
    path = s.save(tmp_path / "model.json")
    assert path.exists() and (tmp_path / "model.npz").exists()
    t = sf.Skeleton.load(path)
    for name in ("labels", "joints", "edge_joints", "motions", "local"):
        np.testing.assert_array_equal(getattr(t, name), getattr(s, name))
    assert t.edges == s.edges and t.n_sticks == 2 and t.log_likelihood == -12.5
    assert t.params["shape"] == [2, 3] and t.info["best"] == 1 and t.point_names == list("abcde")
    np.testing.assert_array_equal(t.state["L"], np.eye(3))
    assert list(t.state["names"]) == ["x", "y"]
    no_tmp = [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert no_tmp == []


def test_load_detects_mismatch_and_garbage(tmp_path):
    s = _skel()
    path = s.save(tmp_path / "a.json")
    _skel(log_likelihood=1.0, labels=np.array([0, 1, 1, 1, 1])).save(tmp_path / "b.json")
    doc = json.loads(path.read_text())
    doc["arrays"]["file"] = "b.npz"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="checksum"):
        sf.Skeleton.load(path)
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a stickfigure model"):
        sf.Skeleton.load(tmp_path / "c.json")


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"edges": [(0, 1), (1, 0)]}, "forest"),
        ({"n_sticks": 1, "edges": [], "motions": None}, "n_sticks"),
        ({"motions": np.zeros((2, 6, 2, 3))}, "motions"),
        ({"local": np.zeros((4, 3))}, "local"),
    ],
)
def test_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        _skel(**kw)


def test_parents_and_summary():
    s = _skel(labels=np.array([0, 1, 1, 2, 2]), n_sticks=3, edges=[(0, 1), (1, 2)], joints=None,
              motions=None, local=None)
    par = s.parents()
    assert sorted(par.tolist()) == sorted([-1, 1, 2]) or (par == -1).sum() == 1
    assert "stick 1: 2 points" in s.summary()
