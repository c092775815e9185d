"""Shared fixtures: the real-data directory and a few small synthetic figures."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

import stickfigure as sf  # noqa: E402


def _data_dir() -> Path | None:
    env = os.environ.get("STICKFIGURE_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data directory (STICKFIGURE_DATA); skips when it is absent."""
    d = _data_dir()
    if d is None and os.environ.get("STICKFIGURE_REQUIRE_DATA"):
        pytest.fail("STICKFIGURE_REQUIRE_DATA is set but the data directory was not found "
                    f"(STICKFIGURE_DATA={os.environ.get('STICKFIGURE_DATA')!r})")
    if d is None:
        pytest.skip("real data not found: set STICKFIGURE_DATA to the shared data directory")
    return d


@pytest.fixture(scope="session")
def small_figure():
    """A 3-stick random 3D figure seen from a random view (2D), 60 frames, 1% noise."""
    return sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.01, seed=7)


@pytest.fixture(scope="session")
def arm_figure():
    """The 4-joint arm of Meeds et al."""
    return sf.synthetic.arm(seed=0)
