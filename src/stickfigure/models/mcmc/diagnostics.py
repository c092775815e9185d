"""Convergence diagnostics of the chains (ArviZ) and posterior summaries.

How to read them
----------------
* ``rhat`` compares the spread within each chain with the spread between
  chains (rank-normalised split R-hat). Values below 1.01 are excellent, below
  1.1 acceptable; above 1.1 the chains have not mixed -- typically one chain is
  stuck in a different tree -- and the posterior summaries mix modes.
* ``ess`` is the effective number of independent draws (bulk ESS). Fewer than
  about 100 makes posterior frequencies (e.g. of the number of sticks) rough.
* The number of sticks is discrete and often constant within a chain; then its
  R-hat is undefined (reported as None) and the log-joint is the quantity to look at.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

__all__ = ["convergence", "n_sticks_posterior"]


def _finite_or_none(v: Any) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def convergence(log_joint: np.ndarray, n_sticks: np.ndarray) -> dict[str, dict[str, float | None]]:
    """R-hat and bulk effective sample size of the log-joint and the number of sticks.

    Parameters
    ----------
    log_joint, n_sticks : ndarray, shape (n_chains, n_draws)
        Kept draws of every chain.

    Returns
    -------
    dict
        ``{"rhat": {"log_joint": ..., "n_sticks": ...}, "ess": {...}}``; None where undefined
        (a single chain, too few draws or a constant quantity).
    """
    out: dict[str, dict[str, float | None]] = {"rhat": {}, "ess": {}}
    arrays = {"log_joint": np.asarray(log_joint, float), "n_sticks": np.asarray(n_sticks, float)}
    C, D = arrays["log_joint"].shape
    if D < 4:
        for name in arrays:
            out["rhat"][name] = out["ess"][name] = None
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import arviz as az

        for name, a in arrays.items():
            if np.ptp(a) == 0:
                out["rhat"][name] = None
                out["ess"][name] = None
                continue
            out["rhat"][name] = _finite_or_none(az.rhat(a)) if C >= 2 else None
            out["ess"][name] = _finite_or_none(az.ess(a))
    return out


def n_sticks_posterior(n_sticks: np.ndarray) -> dict[int, float]:
    """Posterior probability of each number of sticks from the kept draws."""
    vals, counts = np.unique(np.asarray(n_sticks).ravel(), return_counts=True)
    total = counts.sum()
    return {int(v): float(c / total) for v, c in zip(vals, counts)}
