"""stickfigure: learn articulated skeletons from the motion of tracked points.

Quick use::

    import stickfigure as sf
    traj = sf.synthetic.random_figure(n_sticks=4, seed=0)
    skel = sf.fit(traj, method="em", random_state=0)
    print(skel.summary())
"""

from __future__ import annotations

from typing import Any

from . import synthetic
from .models import available_methods, get_method
from .skeleton import Skeleton
from .trajectories import Trajectories

__version__ = "0.1.0"

__all__ = [
    "Trajectories",
    "Skeleton",
    "fit",
    "load",
    "save",
    "available_methods",
    "get_method",
    "synthetic",
    "__version__",
]


def fit(traj: Any, method: str = "em", random_state: Any = None, **params: Any) -> Skeleton:
    """Learn a skeleton from point trajectories.

    Parameters
    ----------
    traj : Trajectories or ndarray, shape (P, F, D)
        Point trajectories, NaN where missing.
    method : str
        A registered method name (see :func:`available_methods`).
    random_state : None, int or numpy Generator
        Seed; the same seed gives the same skeleton.
    **params
        Parameters of the method's estimator class.

    Returns
    -------
    Skeleton
    """
    cls = get_method(method)
    try:
        est = cls(random_state=random_state, **params)
    except TypeError as exc:
        raise TypeError(f"bad parameter for method {method!r}: {exc}") from None
    return est.fit(traj).skeleton_


def load(path: Any, **options: Any) -> Trajectories:
    """Load trajectories from a file; the format is chosen from the file type.

    See :mod:`stickfigure.io` for the supported formats and their options.
    """
    from .io import load as _load

    return _load(path, **options)


def save(traj: Trajectories, path: Any, **options: Any) -> None:
    """Write trajectories as ``.csv`` or ``.npz`` (see :mod:`stickfigure.io`)."""
    from .io import save as _save

    _save(traj, path, **options)
