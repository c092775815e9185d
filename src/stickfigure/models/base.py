"""The estimator contract every method follows, and the method registry.

Each method is a scikit-learn-style estimator: parameters in ``__init__``,
``fit(traj)`` returns ``self``, learned state ends in ``_``. ``fit`` always
produces a :class:`~stickfigure.skeleton.Skeleton` in ``skeleton_``; the
shortcuts ``labels_``, ``n_sticks_``, ``edges_`` and ``log_likelihood_`` mirror it.

A method registers itself under a name with :func:`register`; the top-level
:func:`stickfigure.fit` looks methods up by that name, and
:meth:`Skeleton.impute` finds the method's ``impute_skeleton`` the same way, so
a saved model can be re-used without knowing which class produced it.
"""

from __future__ import annotations

from typing import Any, Callable, ClassVar, TypeVar

import numpy as np
from sklearn.base import BaseEstimator

from .._threads import blas_threads
from .._validation import check_random_state
from ..skeleton import Skeleton
from ..trajectories import Trajectories, as_trajectories

__all__ = ["StickEstimator", "register", "get_method", "available_methods", "check_fit_input"]

_REGISTRY: dict[str, type["StickEstimator"]] = {}
_T = TypeVar("_T", bound=type["StickEstimator"])


def register(name: str) -> Callable[[_T], _T]:
    """Class decorator registering an estimator under ``name``."""

    def deco(cls: _T) -> _T:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise ValueError(f"method name {name!r} is already registered to {_REGISTRY[name].__name__}")
        cls.method_name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def _load_builtin_methods() -> None:
    # Importing the package's method modules fills the registry.
    from .. import models  # noqa: F401

    models._import_methods()


def get_method(name: str) -> type["StickEstimator"]:
    """The estimator class registered under ``name``.

    Raises
    ------
    ValueError
        If no method has that name; the message lists the known ones.
    """
    _load_builtin_methods()
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY))
        raise ValueError(f"unknown method {name!r}; available methods: {known}") from None


def available_methods() -> list[str]:
    """Names of all registered methods, sorted."""
    _load_builtin_methods()
    return sorted(_REGISTRY)


def check_fit_input(X: Any, *, min_points: int = 1, min_frames: int = 2, method: str = "") -> Trajectories:
    """Validate the data a method is fitted to.

    Parameters
    ----------
    X : Trajectories or array_like, shape (P, F, D)
    min_points, min_frames : int
        What the method needs at least.

    Raises
    ------
    ValueError
        Too few points or frames, or points that are never observed.
    """
    traj = as_trajectories(X, "traj")
    who = f"{method} needs" if method else "need"
    if traj.n_points < min_points:
        raise ValueError(f"{who} at least {min_points} points, got {traj.n_points}")
    if traj.n_frames < min_frames:
        raise ValueError(f"{who} at least {min_frames} frames, got {traj.n_frames}")
    never = np.flatnonzero(~traj.observed.any(axis=1))
    if never.size:
        raise ValueError(
            f"{never.size} point(s) are never observed (e.g. point {never[0]}); drop them with "
            "traj.drop_unobserved() before fitting"
        )
    return traj


class StickEstimator(BaseEstimator):
    """Base class of every method.

    Subclasses set ``min_points``/``min_frames``, implement ``_fit(traj, rng)``
    returning a :class:`Skeleton`, and ``impute_skeleton(skeleton, traj)``.
    """

    method_name: ClassVar[str] = ""
    min_points: ClassVar[int] = 1
    min_frames: ClassVar[int] = 2

    def fit(self, X: Trajectories | np.ndarray, y: Any = None) -> "StickEstimator":
        """Learn the skeleton of ``X``.

        Parameters
        ----------
        X : Trajectories or ndarray, shape (P, F, D)
            Point trajectories, NaN where missing.
        y : ignored

        Returns
        -------
        self
        """
        traj = check_fit_input(X, min_points=self.min_points, min_frames=self.min_frames, method=self.method_name)
        rng = check_random_state(getattr(self, "random_state", None))
        with blas_threads():
            skeleton = self._fit(traj, rng)
        skeleton.params = {**self.get_params(deep=False), **skeleton.params}
        skeleton.params.pop("random_state", None)
        skeleton.params["random_state"] = _seed_repr(getattr(self, "random_state", None))
        if skeleton.point_names is None and traj.names is not None:
            skeleton.point_names = list(traj.names)
        self.skeleton_ = skeleton
        self.labels_ = skeleton.labels
        self.n_sticks_ = skeleton.n_sticks
        self.edges_ = skeleton.edges
        self.log_likelihood_ = skeleton.log_likelihood
        return self

    def _fit(self, traj: Trajectories, rng: np.random.Generator) -> Skeleton:  # pragma: no cover - abstract
        raise NotImplementedError(f"{type(self).__name__} must implement _fit")

    def impute(self, X: Trajectories | np.ndarray) -> np.ndarray:
        """Fill the missing entries of ``X`` with the fitted structure (see :meth:`Skeleton.impute`)."""
        if not hasattr(self, "skeleton_"):
            raise ValueError(f"this {type(self).__name__} is not fitted yet; call fit() first")
        return self.skeleton_.impute(X)

    @classmethod
    def impute_skeleton(cls, skeleton: Skeleton, traj: Trajectories) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError(f"{cls.__name__} must implement impute_skeleton")


def _seed_repr(seed: Any) -> Any:
    if seed is None or isinstance(seed, (int, np.integer)):
        return None if seed is None else int(seed)
    return repr(seed)
