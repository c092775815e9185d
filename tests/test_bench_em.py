"""Tests of the measures the em benchmarks report (benchmarks/bench_em.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks package
from benchmarks.bench_em import articulation  # noqa: E402


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
