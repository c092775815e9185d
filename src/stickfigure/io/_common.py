"""Helpers shared by the format readers: file checks and one-line format errors."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["FormatError", "OptionError", "OptionTypeError", "check_file", "fail", "drop_never_observed",
           "positive_option", "rng_option"]


class FormatError(ValueError):
    """A file that cannot be read; the message names the file and the problem."""


def check_file(path: str | os.PathLike) -> Path:
    """Return ``path`` as a :class:`Path`; FileNotFoundError if it does not exist."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no such file: {p}")
    if p.is_dir():
        raise FormatError(f"cannot read {p}: it is a directory, not a file")
    return p


def fail(path: str | os.PathLike, problem: str) -> FormatError:
    """The error to raise for an unreadable ``path`` (use as ``raise fail(path, "...")``)."""
    problem = " ".join(str(problem).split())  # one line
    return FormatError(f"cannot read {path}: {problem}")


def drop_never_observed(xy: np.ndarray, names: list[str], *per_point: Any
                        ) -> tuple[np.ndarray, list[str], list[str], list[Any]]:
    """Remove points that are NaN in every frame.

    Returns
    -------
    xy, names : the kept points
    dropped : names of the removed points
    per_point : each extra (P,) array or list restricted to the kept points
    """
    keep = ~np.isnan(xy).any(axis=2).all(axis=1)
    dropped = [n for n, k in zip(names, keep) if not k]
    out = []
    for a in per_point:
        if a is None:
            out.append(None)
        elif isinstance(a, np.ndarray):
            out.append(a[keep])
        else:
            out.append([v for v, k in zip(a, keep) if k])
    return xy[keep], [n for n, k in zip(names, keep) if k], dropped, out


class OptionError(ValueError):
    """A bad option value passed to a reader (not a problem of the file)."""


class OptionTypeError(TypeError):
    """An option of the wrong type passed to a reader."""


def positive_option(value: Any, name: str, **kwargs: Any) -> Any:
    """:func:`~stickfigure._validation.check_positive` raising the option errors above."""
    from .._validation import check_positive

    try:
        return check_positive(value, name, **kwargs)
    except ValueError as exc:
        raise OptionError(str(exc)) from None
    except TypeError as exc:
        raise OptionTypeError(str(exc)) from None


def rng_option(seed: Any) -> Any:
    """:func:`~stickfigure._validation.check_random_state` raising :class:`OptionTypeError`."""
    from .._validation import check_random_state

    try:
        return check_random_state(seed)
    except TypeError as exc:
        raise OptionTypeError(str(exc)) from None
