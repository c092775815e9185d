"""Skeleton-learning methods, each a registered estimator.

=================  ==========================================================
name               what it is
=================  ==========================================================
``sfm``            single-body affine structure from motion (Tomasi-Kanade)
``multibody-sfm``  subspace clustering + one factorisation per rigid body
``em``             Ross, Tarlow & Zemel: variational EM + greedy joint merging
``mcmc``           Meeds et al.: nonparametric Bayesian tree prior, MCMC
``mi-tree``        Taycher et al.: mutual information of rigid motions + MST
``yan-pollefeys``  local subspace affinity + spectral clustering + MST
=================  ==========================================================
"""

from __future__ import annotations

import importlib

from .base import StickEstimator, available_methods, check_fit_input, get_method, register

__all__ = ["StickEstimator", "available_methods", "check_fit_input", "get_method", "register"]

# Modules that define registered methods; imported on first use of the registry
# (they import plotting-free but heavy code, so not at package import).
_METHOD_MODULES = ("sfm", "em", "mcmc", "mitree", "yan_pollefeys")
_imported = False


def _import_methods() -> None:
    global _imported
    if _imported:
        return
    for mod in _METHOD_MODULES:
        importlib.import_module(f"{__name__}.{mod}")
    _imported = True
