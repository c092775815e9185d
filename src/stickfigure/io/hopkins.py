"""Hopkins 155 motion-segmentation sequences (``<seq>_truth.mat``).

Each file holds feature tracks over F frames (Tron & Vidal, CVPR 2007):

``y``       3 x P x F homogeneous pixel coordinates (divided by the third row
            here; a 2 x P x F array is taken as is)
``x``       the same points in normalised camera coordinates (``y = K x``); used
            with ``K`` when ``y`` is absent
``s``       P ground-truth motion labels, 1-based → ``labels_true`` (0-based)
``width``, ``height``   image size → ``image_size`` (optional)
``points``, ``frames``  P and F (optional; checked when present)

There is no joint tree (``edges_true`` is None). Pixel coordinates have y down.
MATLAB v7.3 (HDF5) files are read with h5py, whose arrays are transposed
relative to MATLAB's.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..trajectories import Trajectories
from ._common import check_file, fail

__all__ = ["load_hopkins", "read_mat"]


def read_mat(path: Path) -> dict[str, Any]:
    """Variables of a MATLAB file (v4/v5 via scipy, v7.3 via h5py), without the ``__`` entries."""
    import scipy.io
    from scipy.io.matlab import MatReadError

    try:
        raw = scipy.io.loadmat(str(path), squeeze_me=False, struct_as_record=True)
    except NotImplementedError:  # MATLAB v7.3 is HDF5
        import h5py

        try:
            with h5py.File(path, "r") as f:
                # h5py sees MATLAB arrays transposed.
                return {k: np.asarray(v).T for k, v in f.items() if isinstance(v, h5py.Dataset)}
        except OSError as exc:
            raise fail(path, f"malformed MATLAB v7.3 file ({exc})") from None
    except (MatReadError, ValueError, TypeError, OSError, EOFError, IndexError, KeyError, MemoryError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise fail(path, f"not a readable MATLAB file or truncated ({msg})") from None
    return {k: v for k, v in raw.items() if not k.startswith("__")}


def _scalar(m: dict[str, Any], key: str) -> float | None:
    v = m.get(key)
    if v is None:
        return None
    v = np.asarray(v)
    if v.size != 1 or not np.issubdtype(v.dtype, np.number):
        return None
    return float(v.ravel()[0])


def hopkins_from_vars(path: Path, m: dict[str, Any]) -> Trajectories:
    """Build trajectories from the variables of a Hopkins 155 file."""
    if "y" in m:
        y = np.asarray(m["y"], dtype=float)
        coords = "pixels"
    elif "x" in m and "K" in m:
        x = np.asarray(m["x"], dtype=float)
        K = np.asarray(m["K"], dtype=float)
        if x.ndim != 3 or x.shape[0] != 3 or K.shape != (3, 3):
            raise fail(path, f"x must be 3 x P x F and K 3 x 3, got {x.shape} and {K.shape}")
        y = np.einsum("ij,jpf->ipf", K, x)
        coords = "pixels (K @ x)"
    elif "x" in m:
        y = np.asarray(m["x"], dtype=float)
        coords = "normalised camera coordinates"
    else:
        raise fail(path, f"no track array: expected 'y' (or 'x'), found variables {sorted(m)}")
    if y.ndim != 3 or y.shape[0] not in (2, 3):
        raise fail(path, f"track array must be 3 x P x F (or 2 x P x F), got shape {y.shape}")
    if y.shape[0] == 3:
        w = y[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = y[:2] / np.where(w == 0, np.nan, w)
    else:
        xy = y
    xy = np.transpose(xy, (1, 2, 0)).copy()  # (P, F, 2)
    xy[~np.isfinite(xy)] = np.nan
    P, F = xy.shape[:2]
    for key, n in (("points", P), ("frames", F)):
        v = _scalar(m, key)
        if v is not None and int(v) != n:
            raise fail(path, f"'{key}' says {int(v)} but the tracks have {n} (truncated or inconsistent file)")
    labels = None
    if "s" in m:
        s = np.asarray(m["s"]).ravel()
        if s.size != P:
            raise fail(path, f"'s' has {s.size} labels for {P} tracks")
        if not np.issubdtype(s.dtype, np.number) or not np.all(np.isfinite(s.astype(float))):
            raise fail(path, "'s' must hold integer labels")
        s = s.astype(np.int64)
        if s.size and s.min() < 1:
            raise fail(path, f"'s' labels must be 1-based (>= 1), got {s.min()}")
        labels = s - 1
    width, height = _scalar(m, "width"), _scalar(m, "height")
    image_size = (int(width), int(height)) if width and height and coords != "normalised camera coordinates" else None
    return Trajectories(
        xy=xy,
        names=[f"track{i}" for i in range(P)],
        image_size=image_size,
        labels_true=labels,
        part_names=[f"motion{k + 1}" for k in range(int(labels.max()) + 1)] if labels is not None and P else None,
        edges_true=None,
        meta={"source": str(path), "format": "hopkins155", "units": "px" if coords.startswith("pixels") else None,
              "coordinates": coords, "sequence": path.name.removesuffix("_truth.mat").removesuffix(".mat")},
    )


def load_hopkins(path: str | os.PathLike) -> Trajectories:
    """Load a Hopkins 155 ``*_truth.mat`` file.

    Returns
    -------
    Trajectories
        2D pixel positions (P, F, 2), y down, ``labels_true`` from ``s`` (0-based),
        ``image_size`` from ``width``/``height``; ``edges_true`` None.
    """
    path = check_file(path)
    return hopkins_from_vars(path, read_mat(path))
