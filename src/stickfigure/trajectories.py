"""The data model: point trajectories with gaps, and optional ground truth.

Conventions
-----------
* ``xy`` has shape (P points, F frames, D) with D = 2 (image or projected
  coordinates) or D = 3 (motion capture); NaN marks a missing observation.
  A point is either fully observed in a frame or fully missing: a NaN in any
  coordinate hides the whole observation.
* 2D data that carry an ``image_size`` are in pixel coordinates with the y axis
  pointing *down* (video, Hopkins 155, SLEAP). 2D data without an image size,
  such as projected motion capture, have the y axis pointing *up*.
* 3D data carry ``up_axis``, the index of the vertical axis (2 for the z-up
  C3D/HDM05 convention, 1 for the y-up BVH/ASF convention).
* Ground truth, when the source has it: ``labels_true`` (P,) gives the true rigid
  part of each point (-1 where unknown), ``edges_true`` the joints between
  parts, ``part_names`` names the parts and ``joints_true`` (J, F, D) gives the
  joint positions, row ``j`` being the joint of ``edges_true[j]``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._validation import as_float_array, check_edges, check_labels, check_random_state

__all__ = ["Trajectories", "as_trajectories", "ISOMETRIC_VIEW", "NAMED_VIEWS", "view_angles", "view_rotation"]

#: Azimuth and elevation (degrees) of the isometric view used by Ross et al.
ISOMETRIC_VIEW = (45.0, float(np.degrees(np.arctan(1.0 / np.sqrt(2.0)))))


NAMED_VIEWS = {"isometric": ISOMETRIC_VIEW, "front": (-90.0, 0.0), "side": (0.0, 0.0), "top": (-90.0, 90.0)}
"""The views :meth:`Trajectories.project` knows by name, as (azimuth, elevation) in degrees."""


def view_angles(view: str | tuple[float, float]) -> tuple[float, float]:
    """(azimuth, elevation) in degrees of a view name in ``NAMED_VIEWS`` or of an angle pair."""
    if isinstance(view, str):
        if view not in NAMED_VIEWS:
            raise ValueError(f"view must be one of {sorted(NAMED_VIEWS)} or (azimuth, elevation), got {view!r}")
        return NAMED_VIEWS[view]
    try:
        az, el = (float(v) for v in view)
    except (TypeError, ValueError):
        raise ValueError(f"view must be a name or (azimuth, elevation) in degrees, got {view!r}") from None
    return az, el


def view_rotation(azimuth: float, elevation: float, up_axis: int = 2) -> np.ndarray:
    """Rotation whose first two rows project 3D points onto a camera's image plane.

    The camera sits at the given azimuth (about the vertical axis, degrees) and
    elevation (above the horizontal plane, degrees) and looks at the origin.

    Parameters
    ----------
    azimuth, elevation : float
        Viewing direction in degrees.
    up_axis : {0, 1, 2}
        Index of the data's vertical axis.

    Returns
    -------
    ndarray, shape (3, 3)
        Rows: image right, image up, and the direction towards the camera, all
        in the data's coordinates.
    """
    if up_axis not in (0, 1, 2):
        raise ValueError(f"up_axis must be 0, 1 or 2, got {up_axis!r}")
    a, e = np.radians(azimuth), np.radians(elevation)
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.array([-np.sin(e) * np.cos(a), -np.sin(e) * np.sin(a), np.cos(e)])
    toward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    R = np.stack([right, up, toward])  # in a z-up frame
    # A cyclic permutation takes the data's axes to a z-up frame without a reflection.
    perm = [(up_axis + 1) % 3, (up_axis + 2) % 3, up_axis]
    to_z_up = np.eye(3)[perm]
    return R @ to_z_up


@dataclass(eq=False)
class Trajectories:
    """Trajectories of P tracked points over F frames, NaN where missing.

    Parameters
    ----------
    xy : array_like, shape (P, F, D)
        Positions, D = 2 or 3. NaN marks a missing observation.
    names : sequence of str, optional
        One name per point (marker label, keypoint name, ...).
    frame_rate : float, optional
        Frames per second.
    image_size : (width, height), optional
        Size in pixels of the images the 2D points were tracked in.
    labels_true : array_like of int, shape (P,), optional
        True rigid part of each point, -1 where unknown.
    edges_true : list of (int, int), optional
        Joints between true parts.
    part_names : sequence of str, optional
        Names of the true parts.
    joints_true : array_like, shape (J, F, D), optional
        True joint positions, one per entry of ``edges_true``.
    video : str, optional
        Path of the video the points were tracked in.
    up_axis : int
        Vertical axis of 3D data.
    meta : dict
        Anything else the source provides (JSON-serialisable values or arrays
        of shape (P,)), e.g. ``meta["unlabelled"]`` for C3D markers without a label.
        ``meta["n_figures"]`` (int), where the source says how many separate figures
        the points belong to (one subject of a motion-capture take), is read by the
        ``em`` method's ``max_trees="auto"``; set it for data of your own.
    allow_unobserved : bool
        Accept points that are never observed (useful for held-out test frames);
        fitting a model still rejects them.

    Raises
    ------
    ValueError
        If ``xy`` has the wrong shape, infinite values, fewer than 2 frames, or a
        point that is never observed (unless ``allow_unobserved``), or if the
        optional fields do not match it.
    """

    xy: np.ndarray
    names: list[str] | None = None
    frame_rate: float | None = None
    image_size: tuple[int, int] | None = None
    labels_true: np.ndarray | None = None
    edges_true: list[tuple[int, int]] | None = None
    part_names: list[str] | None = None
    joints_true: np.ndarray | None = None
    video: str | None = None
    up_axis: int = 2
    meta: dict[str, Any] = field(default_factory=dict)
    allow_unobserved: bool = field(default=False, repr=False)

    def __post_init__(self) -> None:
        xy = as_float_array(self.xy, "xy", ndim=3, shape_text="(P points, F frames, D) with D = 2 or 3")
        P, F, D = xy.shape
        if D not in (2, 3):
            raise ValueError(f"xy must have shape (P points, F frames, D) with D = 2 or 3, got D = {D}")
        if P < 1:
            raise ValueError("xy has no points (P = 0)")
        if F < 2:
            raise ValueError(f"xy must have at least 2 frames, got {F}")
        # A partly-NaN observation is treated as missing as a whole.
        missing = np.isnan(xy).any(axis=2)
        if missing.any():
            xy = xy.copy()
            xy[missing] = np.nan
        if not self.allow_unobserved:
            never = np.flatnonzero(missing.all(axis=1))
            if never.size:
                which = ", ".join(self._point_label(int(p)) for p in never[:5])
                more = f" and {never.size - 5} more" if never.size > 5 else ""
                raise ValueError(f"{never.size} point(s) are never observed: {which}{more}")
        self.xy = xy
        if self.names is not None:
            self.names = [str(n) for n in self.names]
            if len(self.names) != P:
                raise ValueError(f"names must have one entry per point ({P}), got {len(self.names)}")
        if self.frame_rate is not None:
            self.frame_rate = float(self.frame_rate)
            if not np.isfinite(self.frame_rate) or self.frame_rate <= 0:
                raise ValueError(f"frame_rate must be > 0, got {self.frame_rate}")
        if self.image_size is not None:
            if D != 2 or len(self.image_size) != 2:
                raise ValueError("image_size (width, height) applies to 2D data only")
            self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        if self.labels_true is not None:
            self.labels_true = check_labels(self.labels_true, P, "labels_true")
        n_parts = None
        if self.labels_true is not None and self.labels_true.size:
            n_parts = int(self.labels_true.max()) + 1
        if self.part_names is not None:
            self.part_names = [str(n) for n in self.part_names]
            n_parts = max(n_parts or 0, len(self.part_names))
        if self.edges_true is not None:
            self.edges_true = check_edges(self.edges_true, n_parts, "edges_true")
        if self.joints_true is not None:
            J = len(self.edges_true or [])
            self.joints_true = as_float_array(
                self.joints_true, "joints_true", shape=(J, F, D), shape_text=f"({J} joints, {F} frames, {D})"
            )
        if self.up_axis not in (0, 1, 2):
            raise ValueError(f"up_axis must be 0, 1 or 2, got {self.up_axis!r}")
        self.meta = dict(self.meta)

    def _point_label(self, p: int) -> str:
        if self.names is not None and p < len(self.names):
            return f"{p} ({self.names[p]})"
        return str(p)

    # ------------------------------------------------------------------ sizes
    @property
    def n_points(self) -> int:
        """Number of points P."""
        return self.xy.shape[0]

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return self.xy.shape[1]

    @property
    def n_dims(self) -> int:
        """Dimension D of the positions (2 or 3)."""
        return self.xy.shape[2]

    @property
    def shape(self) -> tuple[int, int, int]:
        """(P, F, D)."""
        return self.xy.shape  # type: ignore[return-value]

    @property
    def observed(self) -> np.ndarray:
        """Mask of observed entries, shape (P, F)."""
        return ~np.isnan(self.xy[..., 0])

    @property
    def missing_fraction(self) -> float:
        """Fraction of (point, frame) observations that are missing."""
        return float(1.0 - self.observed.mean())

    @property
    def n_parts_true(self) -> int | None:
        """Number of true parts, if known."""
        if self.labels_true is None:
            return None
        n = int(self.labels_true.max()) + 1 if self.labels_true.size else 0
        if self.part_names is not None:
            n = max(n, len(self.part_names))
        return n

    def __repr__(self) -> str:
        P, F, D = self.shape
        extra = []
        if self.frame_rate:
            extra.append(f"{self.frame_rate:g} fps")
        if self.missing_fraction > 0:
            extra.append(f"{100 * self.missing_fraction:.1f}% missing")
        if self.labels_true is not None:
            extra.append(f"{self.n_parts_true} true parts")
        if self.meta.get("source"):
            extra.append(f"from {self.meta['source']}")
        tail = (", " + ", ".join(extra)) if extra else ""
        return f"Trajectories({P} points x {F} frames x {D}D{tail})"

    # ------------------------------------------------------------ derivations
    def copy(self, **changes: Any) -> "Trajectories":
        """Return a copy, with any fields replaced by ``changes``."""
        fields = {
            f.name: getattr(self, f.name) for f in dataclasses.fields(self)
        }
        for k in ("xy", "labels_true", "joints_true"):
            if fields[k] is not None:
                fields[k] = np.array(fields[k], copy=True)
        fields["meta"] = dict(self.meta)
        unknown = set(changes) - set(fields)
        if unknown:
            raise TypeError(f"unknown Trajectories field(s): {', '.join(sorted(unknown))}")
        fields.update(changes)
        return Trajectories(**fields)

    def with_xy(self, xy: np.ndarray, *, allow_unobserved: bool = True) -> "Trajectories":
        """Same metadata and ground truth, new positions of the same shape."""
        xy = np.asarray(xy, dtype=float)
        if xy.shape != self.xy.shape:
            raise ValueError(f"xy must have shape {self.xy.shape}, got {xy.shape}")
        return self.copy(xy=xy, allow_unobserved=allow_unobserved)

    def slice(self, frames: Any = None, points: Any = None) -> "Trajectories":
        """Select frames and/or points.

        Parameters
        ----------
        frames : slice, int array or bool mask of shape (F,), optional
        points : slice, int array or bool mask of shape (P,), optional

        Returns
        -------
        Trajectories
            Points that lose all their observations are kept (as all-NaN rows).
            Ground truth follows the selected points; parts keep their numbers.
        """
        fidx = _index(frames, self.n_frames, "frames")
        pidx = _index(points, self.n_points, "points")
        if fidx.size < 2:
            raise ValueError(f"a slice must keep at least 2 frames, got {fidx.size}")
        if pidx.size < 1:
            raise ValueError("a slice must keep at least 1 point")
        xy = self.xy[np.ix_(pidx, fidx)]
        meta = dict(self.meta)
        for k, v in self.meta.items():
            if isinstance(v, np.ndarray) and v.shape[:1] == (self.n_points,):
                meta[k] = v[pidx]
        meta["frame_offset"] = int(self.meta.get("frame_offset", 0)) + int(fidx[0])
        return Trajectories(
            xy=xy,
            names=[self.names[i] for i in pidx] if self.names is not None else None,
            frame_rate=self.frame_rate,
            image_size=self.image_size,
            labels_true=self.labels_true[pidx] if self.labels_true is not None else None,
            edges_true=self.edges_true,
            part_names=self.part_names,
            joints_true=self.joints_true[:, fidx] if self.joints_true is not None else None,
            video=self.video,
            up_axis=self.up_axis,
            meta=meta,
            allow_unobserved=True,
        )

    def split(self, train_fraction: float = 0.7) -> tuple["Trajectories", "Trajectories"]:
        """Split by frames: the first ``train_fraction`` for training, the rest for testing.

        This is the held-out protocol of Ross et al. (learn on the first 70% of
        frames, test on the last 30%).
        """
        if not 0 < train_fraction < 1:
            raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
        F = self.n_frames
        n_train = int(round(train_fraction * F))
        if n_train < 2 or F - n_train < 2:
            raise ValueError(f"cannot split {F} frames at {train_fraction}: both parts need at least 2 frames")
        return self.slice(frames=slice(0, n_train)), self.slice(frames=slice(n_train, F))

    def project(
        self,
        view: str | tuple[float, float] = "isometric",
        *,
        scale: float = 1.0,
        distance: float | None = None,
    ) -> "Trajectories":
        """Project 3D trajectories to 2D, by a scaled-orthographic or a pinhole camera.

        Parameters
        ----------
        view : "isometric", "front", "side", "top" or (azimuth, elevation) in degrees
            The camera direction about the data's vertical axis ``up_axis``.
            ``"isometric"`` is the view Ross et al. used for motion capture.
        scale : float
            Uniform image scale: of the scaled-orthographic camera, or of the pinhole
            camera at the scene centre's depth.
        distance : float, optional
            A pinhole (perspective) camera this far from the scene centre (the mean of all
            observed positions over all frames), in the data's units, looking at the centre
            from ``view``. A point's image is its orthographic image times
            ``distance / depth``, so a point at the centre's depth keeps ``scale`` and one
            nearer the camera is drawn larger; ``meta["projection"]["magnification"]``
            gives the range of ``distance / depth`` over the points. ``None`` (default):
            scaled orthographic, the limit of an infinitely distant camera.

        Returns
        -------
        Trajectories
            2D data with the y axis up; ground truth and joints are projected too.

        Raises
        ------
        ValueError
            For 2D data, an unknown view, a ``distance`` that is not a positive finite
            number, or a camera at or inside the scene (a point at depth zero or behind).
        """
        if self.n_dims != 3:
            raise ValueError(f"project() needs 3D trajectories, these are {self.n_dims}D")
        az, el = view_angles(view)
        R = view_rotation(az, el, self.up_axis)  # rows: image right, image up, towards the camera
        meta = dict(self.meta)
        meta["projection"] = {"azimuth": az, "elevation": el, "scale": float(scale)}
        if distance is None:
            P2 = float(scale) * R[:2]  # (2, 3)
            xy = self.xy @ P2.T
            joints = self.joints_true @ P2.T if self.joints_true is not None else None
        else:
            D = float(distance)
            if not (np.isfinite(D) and D > 0):
                raise ValueError(f"distance must be a positive finite number, got {distance!r}")
            centre = np.nanmean(self.xy.reshape(-1, 3), axis=0)
            # Points and joints in the camera's axes about the centre, each computed once.
            Y = (self.xy - centre) @ R.T  # (P, F, 3)
            Yj = (self.joints_true - centre) @ R.T if self.joints_true is not None else None
            # The nearest point decides whether the camera stands clear of the scene.
            nearest = float(np.nanmax(Y[..., 2]))
            if Yj is not None and np.isfinite(Yj).any():
                nearest = max(nearest, float(np.nanmax(Yj[..., 2])))
            if nearest >= D:
                raise ValueError(f"a camera at distance {D:g} from the scene centre is inside the scene: "
                                 f"points come {nearest:g} towards it; give a distance above {nearest:g}")

            def magnification(Yc: np.ndarray) -> np.ndarray:
                return D / (D - Yc[..., 2])  # distance over depth along the viewing direction

            mag = magnification(Y)
            xy = float(scale) * Y[..., :2] * mag[..., None]
            joints = float(scale) * Yj[..., :2] * magnification(Yj)[..., None] if Yj is not None else None
            # How much larger or smaller than at the centre's depth the points are drawn.
            meta["projection"]["magnification"] = [float(np.nanmin(mag)), float(np.nanmax(mag))]
            meta["projection"]["distance"] = D
        return Trajectories(
            xy=xy,
            names=self.names,
            frame_rate=self.frame_rate,
            labels_true=self.labels_true,
            edges_true=self.edges_true,
            part_names=self.part_names,
            joints_true=joints,
            video=None,
            meta=meta,
            allow_unobserved=self.allow_unobserved,
        )

    def subsample(self, step: int) -> "Trajectories":
        """Keep every ``step``-th frame (e.g. 120 Hz motion capture to 30 Hz)."""
        step = int(step)
        if step < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        out = self.slice(frames=slice(0, self.n_frames, step))
        if self.frame_rate:
            out.frame_rate = self.frame_rate / step
        return out

    def drop_unobserved(self) -> "Trajectories":
        """Remove points that are never observed."""
        keep = self.observed.any(axis=1)
        return self.slice(points=keep)

    def missing_at_random(self, fraction: float, random_state: Any = None) -> tuple["Trajectories", np.ndarray]:
        """Hide a random ``fraction`` of the observed entries.

        Returns
        -------
        traj : Trajectories
            The copy with the chosen entries set to NaN.
        hidden : ndarray of bool, shape (P, F)
            The entries that were hidden.
        """
        if not 0 <= fraction < 1:
            raise ValueError(f"fraction must be in [0, 1), got {fraction}")
        rng = check_random_state(random_state)
        obs = np.flatnonzero(self.observed.ravel())
        n = int(round(fraction * obs.size))
        hidden = np.zeros(self.n_points * self.n_frames, bool)
        hidden[rng.choice(obs, size=n, replace=False)] = True
        hidden = hidden.reshape(self.n_points, self.n_frames)
        xy = self.xy.copy()
        xy[hidden] = np.nan
        return self.with_xy(xy), hidden


def _index(sel: Any, n: int, name: str) -> np.ndarray:
    if sel is None:
        return np.arange(n)
    if isinstance(sel, slice):
        return np.arange(n)[sel]
    arr = np.asarray(sel)
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ValueError(f"{name} mask must have shape ({n},), got {arr.shape}")
        return np.flatnonzero(arr)
    arr = np.atleast_1d(arr).astype(np.int64)
    if arr.size and (arr.min() < -n or arr.max() >= n):
        raise ValueError(f"{name} index out of range for {n} {name}")
    return np.where(arr < 0, arr + n, arr)


def as_trajectories(data: Any, name: str = "traj") -> Trajectories:
    """Accept a :class:`Trajectories` or an array of shape (P, F, D)."""
    if isinstance(data, Trajectories):
        return data
    if isinstance(data, (np.ndarray, list, tuple)):
        return Trajectories(np.asarray(data, dtype=float))
    raise TypeError(f"{name} must be a Trajectories or an array of shape (P, F, D), got {type(data).__name__}")
