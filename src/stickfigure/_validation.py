"""Input checks shared by every public entry point.

Every check raises :class:`ValueError` (or :class:`TypeError` for a wrong
kind of object) with a one-line message that names the argument, what was
expected and what was received, in the style of scikit-image.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "as_float_array",
    "check_random_state",
    "check_labels",
    "check_edges",
    "check_positive",
]


def as_float_array(
    a: Any,
    name: str,
    *,
    ndim: int | None = None,
    shape: tuple[int | None, ...] | None = None,
    shape_text: str | None = None,
    allow_nan: bool = True,
) -> np.ndarray:
    """Return ``a`` as a float64 array after checking its shape and values.

    Parameters
    ----------
    a : array_like
        The value to check.
    name : str
        Argument name used in error messages.
    ndim : int, optional
        Required number of dimensions.
    shape : tuple of int or None, optional
        Required shape; ``None`` entries match any length.
    shape_text : str, optional
        Human description of the expected shape, e.g. ``"(P points, F frames, D)"``.
    allow_nan : bool
        Whether NaN marks a missing value. Infinite values are always rejected.
    """
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a numeric array, got {type(a).__name__}: {exc}") from None
    want = shape_text or (str(shape) if shape is not None else f"{ndim} dimensions")
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have shape {want}, got an array of shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
            raise ValueError(f"{name} must have shape {want}, got an array of shape {arr.shape}")
    if np.isinf(arr).any():
        raise ValueError(f"{name} contains {int(np.isinf(arr).sum())} infinite values; use NaN for missing data")
    if not allow_nan and np.isnan(arr).any():
        raise ValueError(f"{name} contains {int(np.isnan(arr).sum())} NaN values; missing data is not allowed here")
    return arr


def check_random_state(seed: Any) -> np.random.Generator:
    """Turn ``seed`` into a :class:`numpy.random.Generator`.

    ``None`` gives fresh entropy, an int or :class:`~numpy.random.SeedSequence`
    a reproducible stream, and a Generator is returned unchanged.
    """
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None or isinstance(seed, (int, np.integer, np.random.SeedSequence)):
        return np.random.default_rng(seed)
    if isinstance(seed, np.random.RandomState):
        return np.random.default_rng(seed.randint(0, 2**31 - 1))
    raise TypeError(f"random_state must be None, an int or a numpy Generator, got {type(seed).__name__}")


def check_labels(labels: Any, n_points: int, name: str = "labels") -> np.ndarray:
    """Check an integer label vector of shape (P,) with -1 meaning 'no label'."""
    arr = np.asarray(labels)
    if arr.shape != (n_points,):
        raise ValueError(f"{name} must have shape ({n_points},) (one per point), got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise ValueError(f"{name} must hold integers (-1 for none)")
    arr = arr.astype(np.int64)
    if arr.size and arr.min() < -1:
        raise ValueError(f"{name} must be >= -1 (-1 means no label), got {arr.min()}")
    return arr


def check_edges(edges: Any, n_nodes: int | None, name: str = "edges") -> list[tuple[int, int]]:
    """Check a list of (a, b) node pairs; returns a list of int tuples."""
    if edges is None:
        return []
    arr = np.asarray(edges, dtype=np.int64).reshape(-1, 2) if len(edges) else np.zeros((0, 2), np.int64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must be a list of (a, b) pairs, got shape {arr.shape}")
    if arr.size and arr.min() < 0:
        raise ValueError(f"{name} refers to a negative node index")
    if n_nodes is not None and arr.size and arr.max() >= n_nodes:
        raise ValueError(f"{name} refers to node {arr.max()}, but there are only {n_nodes}")
    if arr.size and np.any(arr[:, 0] == arr[:, 1]):
        raise ValueError(f"{name} contains a self-loop")
    return [(int(a), int(b)) for a, b in arr]


def check_positive(value: Any, name: str, *, integer: bool = False, allow_zero: bool = False) -> Any:
    """Check that a scalar parameter is positive (or non-negative)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be {bound}, got {value!r}")
    if integer:
        if v != int(v):
            raise ValueError(f"{name} must be an integer, got {value!r}")
        return int(v)
    return v
