"""Evaluation protocols: the held-out imputation test of Ross, Tarlow & Zemel.

The protocol (their section 5): learn a model on the first 70% of the frames;
on the remaining 30%, hide observations with a vertical bar sweeping across
the scene plus 5% dropped at random (:func:`stickfigure.synthetic.occlude`,
10-15% in all); fit the learned model, kept fixed, to the visible entries of
the test frames (:meth:`Skeleton.impute`); report the root-mean-square error
of the predictions of the hidden entries. The training frames may be occluded
too (``occlude_train``) or have a fraction of their entries withheld at random
(``train_missing``, the paper goes up to 75%).

:func:`compare_methods` runs several methods on the same split and the same
hidden entries, so their errors are comparable.
"""

from __future__ import annotations

import time
from typing import Any, Iterable, Mapping

import numpy as np

from ._validation import check_random_state
from .metrics import imputation_rmse, score_skeleton
from .synthetic import occlude
from .trajectories import Trajectories, as_trajectories

__all__ = ["imputation_protocol", "compare_methods", "make_split"]


def make_split(
    traj: Trajectories | np.ndarray,
    *,
    train_fraction: float = 0.7,
    occlude_train: bool = False,
    train_missing: float = 0.0,
    random_state: Any = None,
) -> dict[str, Any]:
    """The data of one protocol run: training frames and occluded test frames.

    Parameters
    ----------
    traj : Trajectories or ndarray, shape (P, F, D)
    train_fraction : float
        Share of frames (from the start) used for learning.
    occlude_train : bool
        Also occlude the training frames with :func:`synthetic.occlude`.
    train_missing : float
        Withhold this share of the (remaining) training entries at random, in [0, 1).
    random_state : None, int or Generator

    Returns
    -------
    dict
        ``train`` (Trajectories), ``test`` (the complete test frames),
        ``test_occluded``, ``hidden`` (P, F_test) mask of hidden test entries,
        ``seed`` (int, for the method).
    """
    traj = as_trajectories(traj)
    if not 0 <= train_missing < 1:
        raise ValueError(f"train_missing must be in [0, 1), got {train_missing!r}")
    rng = check_random_state(random_state)
    seeds = rng.integers(0, 2**31 - 1, size=4)
    train, test = traj.split(train_fraction)
    if occlude_train:
        train, _ = occlude(train, seed=int(seeds[0]))
    if train_missing > 0:
        train, _ = train.missing_at_random(train_missing, random_state=int(seeds[1]))
    never = np.flatnonzero(~train.observed.any(axis=1))
    if never.size:
        raise ValueError(f"{never.size} point(s) are never observed in the training frames after occlusion "
                         f"(e.g. point {never[0]}); use less occlusion or a larger train_fraction")
    test_occluded, hidden = occlude(test, seed=int(seeds[2]))
    return {"train": train, "test": test, "test_occluded": test_occluded, "hidden": hidden, "seed": int(seeds[3])}


def _run(split: Mapping[str, Any], method: str, params: Mapping[str, Any], score: bool) -> dict[str, Any]:
    from . import fit
    from .models import get_method

    t0 = time.perf_counter()
    skeleton = fit(split["train"], method=method, random_state=split["seed"], **params)
    t_fit = time.perf_counter() - t0
    test_occ: Trajectories = split["test_occluded"]
    t0 = time.perf_counter()
    # The method's impute_skeleton, with the observed entries kept (what Skeleton.impute does).
    filled = np.asarray(get_method(skeleton.method).impute_skeleton(skeleton, test_occ), dtype=float)
    obs = test_occ.observed
    filled[obs] = test_occ.xy[obs]
    t_imp = time.perf_counter() - t0
    hidden = split["hidden"]
    test: Trajectories = split["test"]
    out: dict[str, Any] = {
        "method": method,
        "params": dict(params),
        "rmse": imputation_rmse(filled, test.xy, hidden),
        "rmse_point": imputation_rmse(filled, test.xy, hidden, per="point"),
        "n_hidden": int(hidden.sum()),
        "hidden_fraction": float(hidden.sum() / max(test.observed.sum(), 1)),
        "train_frames": split["train"].n_frames,
        "test_frames": test.n_frames,
        "train_missing_fraction": split["train"].missing_fraction,
        "fit_time_s": t_fit,
        "impute_time_s": t_imp,
        "skeleton": skeleton,
        "imputed": filled,
    }
    noise = test.meta.get("noise_std")
    if noise:
        out["noise_std"] = float(noise)
        out["rmse_over_noise"] = out["rmse"] / float(noise)
    if score:
        out["scores"] = score_skeleton(skeleton, split["train"])
    return out


def imputation_protocol(
    traj: Trajectories | np.ndarray,
    method: str,
    *,
    train_fraction: float = 0.7,
    occlude_train: bool = False,
    train_missing: float = 0.0,
    random_state: Any = None,
    score: bool = True,
    **params: Any,
) -> dict[str, Any]:
    """The Ross et al. held-out imputation test for one method.

    Parameters
    ----------
    traj : Trajectories or ndarray, shape (P, F, D)
    method : str
        A registered method name.
    train_fraction : float
        Learn on this leading share of the frames (paper: 0.7).
    occlude_train : bool
        Occlude the training frames too (bar + 5% at random).
    train_missing : float
        Withhold this share of the training entries at random (paper: up to 0.75).
    random_state : None, int or Generator
        Seeds the occlusions and the method.
    score : bool
        Also score the learned skeleton against the training frames' ground truth.
    **params
        Parameters of the method.

    Returns
    -------
    dict
        ``rmse`` (per coordinate, comparable with a noise std), ``rmse_point``
        (per point), ``n_hidden``, ``hidden_fraction``, ``skeleton``, ``imputed``
        (P, F_test, D), ``fit_time_s``, ``impute_time_s``, frame counts,
        ``noise_std`` and ``rmse_over_noise`` for synthetic data, ``scores``.
    """
    split = make_split(traj, train_fraction=train_fraction, occlude_train=occlude_train,
                       train_missing=train_missing, random_state=random_state)
    return _run(split, method, params, score)


def compare_methods(
    traj: Trajectories | np.ndarray,
    methods: Iterable[str] | Mapping[str, Mapping[str, Any]],
    *,
    train_fraction: float = 0.7,
    occlude_train: bool = False,
    train_missing: float = 0.0,
    random_state: Any = None,
    score: bool = True,
) -> list[dict[str, Any]]:
    """Run several methods on one split with the same hidden entries.

    Parameters
    ----------
    traj : Trajectories or ndarray
    methods : list of names, or {name: params}
    train_fraction, occlude_train, train_missing, random_state, score
        As in :func:`imputation_protocol`; the split and the method seed are
        drawn once and shared.

    Returns
    -------
    list of dict
        One :func:`imputation_protocol` result per method, in order.
    """
    items = list(methods.items()) if isinstance(methods, Mapping) else [(m, {}) for m in methods]
    if not items:
        raise ValueError("methods is empty")
    split = make_split(traj, train_fraction=train_fraction, occlude_train=occlude_train,
                       train_missing=train_missing, random_state=random_state)
    return [_run(split, name, dict(params or {}), score) for name, params in items]
