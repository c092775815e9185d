"""Tests of the measures the em benchmarks report (benchmarks/bench_em.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks package
from benchmarks.bench_em import articulation, skin_sd_like  # noqa: E402


def _rigid(seed: int, frames: int = 40) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(8, 3))
    R = Rotation.random(frames, random_state=seed).as_matrix()  # (F, 3, 3)
    path = np.cumsum(rng.normal(size=(1, frames, 3)), axis=1) * 3.0
    return np.einsum("pi,fji->pfj", shape, R) + path  # (P, F, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_articulation_is_zero_for_a_rigid_figure_whatever_its_path(seed):
    assert articulation(_rigid(seed)) < 1e-9


def test_articulation_grows_with_the_bend():
    # Two rigid halves; the second turns about the origin by an angle that swings
    # through +-amp over the frames: more swing, more articulation.
    X = _rigid(3)
    half = X.shape[0] // 2
    t = np.linspace(0.0, 2 * np.pi, X.shape[1])
    centred = X - X[:half].mean(axis=0)

    def bent(amp: float) -> np.ndarray:
        R = Rotation.from_rotvec(np.outer(amp * np.sin(t), [0.0, 0.0, 1.0])).as_matrix()
        Y = centred.copy()
        Y[half:] = np.einsum("fij,pfj->pfi", R, centred[half:])
        return Y

    values = [articulation(bent(a)) for a in (0.0, 0.2, 0.6)]
    assert values[0] < 1e-9 < values[1] < values[2]


def test_articulation_leaves_out_points_missing_in_a_frame():
    X = _rigid(4)
    X[0, 5] = np.nan
    assert articulation(X) < 1e-9


def test_articulation_names_bad_input():
    with pytest.raises(ValueError, match=r"\(P, F, 3\)"):
        articulation(np.zeros((5, 10, 2)))
    X = _rigid(5)
    X[:6, 3] = np.nan
    with pytest.raises(ValueError, match="at least 3 points"):
        articulation(X)


def test_skin_sd_like_recovers_each_segments_skin_motion_and_scales_by_the_waist():
    import stickfigure as sf

    # A "recorded" take: a rigid pelvis pair and a rigid 3-marker segment, each moved by known skin
    # motion, and a 1-marker hand; the distances' spread gives each segment's sd back.
    F = 6000
    pts = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.5, 0], [0.05, 0.6, 0], [-0.05, 0.55, 0.05], [0, 0.9, 0]])
    R = Rotation.from_rotvec(np.linspace(0, 1, F)[:, None] * [0.3, 0.2, 0.1]).as_matrix()
    xy = np.einsum("pi,fji->pfj", pts, R)
    names = ["LFWT", "RFWT", "A", "B", "C", "HAND"]
    labels = np.array([0, 0, 1, 1, 1, 2])
    rec = sf.Trajectories(xy=xy, names=names, labels_true=labels, edges_true=[(0, 1), (1, 2)],
                          part_names=["pelvis", "arm", "hand"])
    truth = np.array([0.004, 0.004, 0.002, 0.002, 0.002, 0.0])
    rec = sf.synthetic.skin_motion(rec, truth, seed=0, timescale=3.0)
    sd = skin_sd_like(rec, rec)
    np.testing.assert_allclose(sd[:5], truth[:5], rtol=0.15)
    assert sd[5] == pytest.approx(np.median([sd[0], sd[2]]))  # one marker: the median over segments
    # A take twice as wide at the waist gets twice the motion.
    big = rec.with_xy(rec.xy * 2.0)
    np.testing.assert_allclose(skin_sd_like(big, rec), 2.0 * sd, rtol=1e-6)
