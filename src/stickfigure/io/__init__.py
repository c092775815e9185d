"""Readers for motion-capture, tracking and benchmark files, and writers for our own.

``load(path, **options)`` picks the reader from the file type:

=============  ===============================================  ==========================================
extension      what                                             options
=============  ===============================================  ==========================================
``.c3d``       C3D motion capture (ezc3d)                       zeros_as_missing, drop_unobserved, up_axis
``.bvh``       Biovision hierarchy, joints by FK                markers_per_bone, random_state,
                                                                marker_spread, merge_rigid,
                                                                position_mode, scale, units, marker_set
``.amc``       Acclaim motion + its ``.asf`` skeleton, FK       asf, frame_rate, markers_per_bone, ...
``.mat``       Hopkins 155 ``*_truth.mat`` or MoCap Toolbox     take, drop_unobserved, up_axis (toolbox)
``.slp``       SLEAP labels (h5py)                              instances, track, instance, video_index,
                                                                drop_unobserved
``.csv``       stickfigure long format (see :mod:`.table`)      -
``.npz``       stickfigure archive (see :mod:`.table`)          -
=============  ===============================================  ==========================================

``save(traj, path)`` writes ``.csv`` or ``.npz``. Every loaded
:class:`~stickfigure.trajectories.Trajectories` records ``meta["source"]`` (the
path), ``meta["format"]`` and ``meta["units"]`` (None when the file does not
say). Formats that describe whole figures also record ``meta["n_figures"]``: 1
for ASF/AMC and the MoCap Toolbox, the ROOT hierarchies of a BVH, the subjects
of a C3D (1 when its labels carry no subject prefix; None when no marker is
labelled), the tracks of a SLEAP file. ``EMSkeleton(max_trees="auto")`` joins
a learned forest down to that many trees. Bad files raise a one-line
:class:`ValueError` that names the file; a missing file raises
:class:`FileNotFoundError`; an unknown option raises :class:`TypeError` listing
the reader's options. See ``docs/formats.md``.
"""

from __future__ import annotations

import inspect
import os
import struct
import zipfile
from pathlib import Path
from typing import Any, Callable

from ..trajectories import Trajectories
from ._common import FormatError, OptionError, OptionTypeError, check_file, fail
from .asfamc import load_amc
from .bvh import load_bvh
from .c3d import load_c3d
from .hopkins import hopkins_from_vars, load_hopkins, read_mat
from .mocaptoolbox import is_mocaptoolbox, list_takes, load_mocaptoolbox
from .sleap import load_slp
from .table import load_csv, load_npz, save_csv, save_npz

__all__ = [
    "load", "save", "SUPPORTED", "WRITABLE",
    "load_c3d", "load_bvh", "load_amc", "load_hopkins", "load_mocaptoolbox", "load_slp",
    "load_csv", "load_npz", "save_csv", "save_npz", "list_takes",
]

#: Readable file types and what they hold.
SUPPORTED: dict[str, str] = {
    ".c3d": "C3D motion capture",
    ".bvh": "Biovision hierarchy (BVH)",
    ".amc": "Acclaim motion (with its .asf skeleton)",
    ".mat": "Hopkins 155 *_truth.mat or MoCap Toolbox data",
    ".slp": "SLEAP labels",
    ".csv": "stickfigure long-format CSV",
    ".npz": "stickfigure NPZ archive",
}

#: Writable file types.
WRITABLE: dict[str, Callable[..., Path]] = {".csv": save_csv, ".npz": save_npz}


def _load_mat(path: Path, *, take: str | None = None, drop_unobserved: bool = True,
              up_axis: int | None = None) -> Trajectories:
    """A ``.mat`` file: Hopkins 155 when it has track arrays, else MoCap Toolbox takes."""
    variables = read_mat(path)
    if is_mocaptoolbox(variables):
        return load_mocaptoolbox(path, take=take, drop_unobserved=drop_unobserved, up_axis=up_axis,
                                 variables=variables)
    if "y" in variables or "x" in variables:
        given = {k: v for k, v in (("take", take), ("up_axis", up_axis)) if v is not None}
        if given:
            raise OptionTypeError(f"option(s) {', '.join(given)} do not apply to Hopkins 155 files")
        return hopkins_from_vars(path, variables)
    raise fail(path, "unknown MATLAB content: expected Hopkins 155 tracks ('y', 's') or MoCap Toolbox "
                     f"takes; found variables {', '.join(sorted(variables)) or 'none'}")


def _asf_alone(path: Path, **_: Any) -> Trajectories:
    beside = sorted(p for p in path.parent.glob("*") if p.suffix.lower() == ".amc")
    if len(beside) == 1:
        hint = f"load({str(beside[0])!r}, asf={str(path)!r})"
    elif beside:
        hint = (f"load('<take>.amc', asf={str(path)!r}) with one of "
                f"{', '.join(p.name for p in beside[:5])}{' ...' if len(beside) > 5 else ''}")
    else:
        hint = f"load('<take>.amc', asf={str(path)!r}); no .amc file lies beside it"
    raise OptionError(f"{path} is an ASF skeleton without motion: the motion is in an .amc file; {hint}")


_READERS: dict[str, Callable[..., Trajectories]] = {
    ".c3d": load_c3d,
    ".bvh": load_bvh,
    ".amc": load_amc,
    ".asf": _asf_alone,
    ".mat": _load_mat,
    ".slp": load_slp,
    ".csv": load_csv,
    ".npz": load_npz,
}

_VIDEO = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"}

# Exceptions that a malformed file can raise deep inside a parser or library.
_MALFORMED = (KeyError, IndexError, AttributeError, TypeError, UnicodeDecodeError, EOFError, struct.error,
              zipfile.BadZipFile, OSError, RuntimeError, OverflowError, MemoryError, ValueError)


def load(path: str | os.PathLike, **options: Any) -> Trajectories:
    """Load trajectories from a file, choosing the reader from its extension.

    Parameters
    ----------
    path : path-like
        A ``.c3d``, ``.bvh``, ``.amc``, ``.mat``, ``.slp``, ``.csv`` or ``.npz`` file.
    **options
        Options of the format's reader (see the table in :mod:`stickfigure.io`).

    Returns
    -------
    Trajectories

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        Unknown file type, or a truncated or malformed file (one line naming it).
    TypeError
        An option the reader does not take.
    """
    if isinstance(path, Trajectories):
        raise TypeError("load() takes a file path; this is already a Trajectories")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or path-like, got {type(path).__name__}")
    p = Path(path)
    suffix = p.suffix.lower()
    reader = _READERS.get(suffix)
    if reader is None:
        kinds = ", ".join(f"{k} ({v})" for k, v in SUPPORTED.items())
        video = " (for a video, track points first: stickfigure.track)" if suffix in _VIDEO else ""
        raise ValueError(f"unknown file type {suffix or '(none)'!r} for {p}{video}; supported: {kinds}")
    check_file(p)
    params = inspect.signature(reader).parameters
    accepts_any = any(v.kind is inspect.Parameter.VAR_KEYWORD for v in params.values())
    if not accepts_any:
        valid = [n for n, v in params.items() if v.kind is inspect.Parameter.KEYWORD_ONLY]
        unknown = sorted(set(options) - set(valid))
        if unknown:
            raise TypeError(f"unknown option(s) {', '.join(unknown)} for {suffix} files; "
                            f"valid: {', '.join(valid) or 'none'}")
    try:
        return reader(p, **options)
    except (FormatError, FileNotFoundError, OptionError, OptionTypeError):
        raise
    except ValueError as exc:
        msg = _one_line(exc)
        if str(p) in msg:
            raise ValueError(msg) from None
        raise fail(p, msg) from None
    except _MALFORMED as exc:
        raise fail(p, f"malformed {SUPPORTED.get(suffix, suffix)} file ({_one_line(exc)})") from None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    first = text.splitlines()[0] if text else ""
    return first or type(exc).__name__


def save(traj: Trajectories, path: str | os.PathLike, **options: Any) -> Path:
    """Write trajectories as ``.csv`` or ``.npz`` (atomically).

    Parameters
    ----------
    traj : Trajectories
    path : path-like
        Target file; the extension picks the format.

    Returns
    -------
    Path
        The written file.
    """
    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories, got {type(traj).__name__}")
    p = Path(path)
    writer = WRITABLE.get(p.suffix.lower())
    if writer is None:
        raise ValueError(f"cannot write {p.suffix or '(no extension)'!r} files; supported: "
                         f"{', '.join(WRITABLE)}")
    if options:
        raise TypeError(f"unknown option(s) {', '.join(sorted(options))} for {p.suffix} files; valid: none")
    return writer(traj, p)
