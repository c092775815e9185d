"""Synthetic articulated figures with ground truth, and the occlusion protocol.

Every generator returns a :class:`~stickfigure.trajectories.Trajectories` with
``labels_true`` (the stick of each point), ``edges_true`` (joined sticks, parent
first) and ``joints_true`` (the position of each joint in every frame, row ``j``
for ``edges_true[j]``), so segmentation, tree and joints can be scored.

Noise levels are *relative*: ``noise`` is the standard deviation of the
isotropic Gaussian added to every observed coordinate, as a fraction of the
figure's mean stick length ("1% noise" is ``noise=0.01``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ._validation import check_positive, check_random_state
from .trajectories import Trajectories, view_rotation

__all__ = ["arm", "random_figure", "star", "walker", "rigid_bodies", "occlude", "marker_gaps", "skin_motion",
           "FigureSpec"]


@dataclass
class FigureSpec:
    """A kinematic tree of rigid sticks in its rest pose.

    Attributes
    ----------
    parent : ndarray of int, shape (S,)
        Parent stick, -1 for the root.
    attach : ndarray, shape (S, 3)
        Where each stick's proximal end attaches, in its parent's local frame.
    lengths : ndarray, shape (S,)
        Stick lengths; stick s runs from its local origin to ``(lengths[s], 0, 0)``.
    local : ndarray, shape (P, 3)
        Each point's position in its stick's local frame.
    labels : ndarray of int, shape (P,)
        Stick of each point.
    """

    parent: np.ndarray
    attach: np.ndarray
    lengths: np.ndarray
    local: np.ndarray
    labels: np.ndarray

    @property
    def n_sticks(self) -> int:
        return int(self.parent.shape[0])

    @property
    def edges(self) -> list[tuple[int, int]]:
        return [(int(p), s) for s, p in enumerate(self.parent) if p >= 0]


def _forward_kinematics(spec: FigureSpec, rel_rot: np.ndarray, root_t: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """World positions of points and joints.

    Parameters
    ----------
    rel_rot : ndarray, shape (S, F, 3, 3)
        Rotation of each stick relative to its parent (world rotation for the root).
    root_t : ndarray, shape (F, 3)
        World position of the root stick's origin.

    Returns
    -------
    points : ndarray, shape (P, F, 3)
    joints : ndarray, shape (E, F, 3), one per entry of ``spec.edges``
    """
    S, F = rel_rot.shape[:2]
    R = np.empty((S, F, 3, 3))
    t = np.empty((S, F, 3))
    for s in range(S):  # parents precede children
        p = spec.parent[s]
        if p < 0:
            R[s], t[s] = rel_rot[s], root_t
        else:
            R[s] = R[p] @ rel_rot[s]
            t[s] = t[p] + np.einsum("fij,j->fi", R[p], spec.attach[s])
    pts = np.einsum("pfij,pj->pfi", R[spec.labels], spec.local) + t[spec.labels]
    joints = np.stack([t[c] for _, c in spec.edges]) if spec.edges else np.zeros((0, F, 3))
    return pts, joints


def _smooth_rotvecs(rng: np.random.Generator, n: int, F: int, amplitude: float, planar: bool,
                    cycles: tuple[float, float] = (0.5, 2.0)) -> np.ndarray:
    """Smooth random rotation vectors, shape (n, F, 3): a sum of two sinusoids per axis."""
    t = np.linspace(0.0, 1.0, F)
    axes = 1 if planar else 3
    out = np.zeros((n, F, 3))
    for k in range(2):
        freq = rng.uniform(*cycles, size=(n, 1, axes))
        phase = rng.uniform(0, 2 * np.pi, size=(n, 1, axes))
        amp = amplitude * rng.uniform(0.5, 1.0, size=(n, 1, axes)) / (k + 1)
        wave = amp * np.sin(2 * np.pi * freq * t[None, :, None] + phase)
        if planar:
            out[..., 2:] += wave
        else:
            out += wave
    return out


def _scatter_points(rng: np.random.Generator, length: float, n: int, planar: bool,
                    spread: float) -> np.ndarray:
    """Points rigidly attached around a stick (not collinear), local frame, shape (n, 3)."""
    along = rng.uniform(0.1, 0.9, size=n) * length
    radius = spread * length * rng.uniform(0.3, 1.0, size=n)
    if planar:
        side = rng.choice([-1.0, 1.0], size=n)
        return np.column_stack([along, side * radius, np.zeros(n)])
    ang = rng.uniform(0, 2 * np.pi, size=n)
    return np.column_stack([along, radius * np.cos(ang), radius * np.sin(ang)])


def _random_motion(rng: np.random.Generator, n_sticks: int, frames: int, amplitude: float, planar: bool
                   ) -> tuple[np.ndarray, np.ndarray]:
    """A random rest pose and smooth motion of a tree whose stick 0 is the root.

    Returns ``rel_rot`` (S, F, 3, 3), each stick's rotation relative to its parent
    (the root's in the world), and ``root_t`` (F, 3), the root's path: a drift plus
    a wobble. In the image plane when ``planar``.
    """
    rest = rng.uniform(-np.pi, np.pi, size=(n_sticks, 1, 3))
    if planar:
        rest[..., :2] = 0.0
    motion = _smooth_rotvecs(rng, n_sticks, frames, amplitude, planar)
    motion[0] *= 0.5  # the root turns less than the limbs
    rel = Rotation.from_rotvec((rest + motion).reshape(-1, 3)).as_matrix().reshape(n_sticks, frames, 3, 3)
    t = np.linspace(0, 1, frames)[:, None]
    drift = rng.normal(size=(1, 3)) * 0.5
    wobble = 0.3 * np.sin(2 * np.pi * rng.uniform(0.3, 1.0, size=(1, 3)) * t + rng.uniform(0, 6.3, size=(1, 3)))
    root_t = drift * t + wobble
    if planar:
        root_t[:, 2] = 0.0
    return rel, root_t


def _finish(points: np.ndarray, joints: np.ndarray, spec: FigureSpec, rng: np.random.Generator,
            noise: float, view: Any, planar: bool, meta: dict[str, Any], frame_rate: float | None,
            part_names: list[str] | None = None) -> Trajectories:
    """Project, add noise and wrap as Trajectories."""
    if planar:
        P2 = np.eye(3)[:2]
        az = el = None
    else:
        if view is None:
            az, el = float(rng.uniform(0, 360)), float(rng.uniform(-20, 60))
        else:
            az, el = (float(v) for v in view)
        P2 = view_rotation(az, el, up_axis=2)[:2]
    xy = points @ P2.T
    jxy = joints @ P2.T
    sigma = noise * float(np.mean(spec.lengths))
    xy = xy + sigma * rng.standard_normal(xy.shape)
    meta = {**meta, "noise_std": sigma, "view": None if planar else [az, el]}
    return Trajectories(
        xy=xy,
        labels_true=spec.labels,
        edges_true=spec.edges,
        part_names=part_names or [f"stick{s}" for s in range(spec.n_sticks)],
        joints_true=jxy,
        frame_rate=frame_rate,
        meta=meta,
    )


def _check_frames(value: Any, name: str = "frames") -> int:
    """A generator's frame count: an integer of at least 2 (one frame shows no motion)."""
    n = check_positive(value, name, integer=True)
    if n < 2:
        raise ValueError(f"{name} must be >= 2, got {n}")
    return n


def random_figure(
    n_sticks: int = 5,
    frames: int = 120,
    planar: bool = False,
    noise: float = 0.01,
    seed: Any = None,
    *,
    points_per_stick: int | tuple[int, int] = (5, 9),
    view: tuple[float, float] | None = None,
    amplitude: float = 0.9,
    spread: float = 0.25,
) -> Trajectories:
    """A random kinematic tree of rigid sticks moving in 3D (or in the image plane).

    The root stick moves freely (smooth rotation and translation); every other
    stick hangs from a point of its parent (its distal end, its proximal end for
    the root, or a point along it), each attachment point used once so the true
    tree is unambiguous, and turns about it with a smooth random 3-DOF (planar:
    1-DOF) rotation. Points are scattered rigidly around each stick, off its
    axis, so each stick's shape is truly 3D (planar: 2D). The figure is seen by a
    scaled-orthographic camera from a random view.

    Parameters
    ----------
    n_sticks : int
        Number of sticks (>= 1).
    frames : int
        Number of frames (>= 2).
    planar : bool
        Motion, points and camera in the image plane (the Meeds et al. setting).
    noise : float
        Gaussian noise std as a fraction of the mean stick length.
    seed : None, int or Generator
    points_per_stick : int or (low, high)
        Points on each stick, fixed or drawn uniformly in ``[low, high]``.
    view : (azimuth, elevation) in degrees, optional
        Camera direction; random (elevation in [-20, 60]) when omitted.
    amplitude : float
        Typical joint rotation amplitude in radians.
    spread : float
        Point distance from the stick axis as a fraction of its length.

    Returns
    -------
    Trajectories
        2D trajectories with ``labels_true``, ``edges_true`` and ``joints_true``.
    """
    n_sticks = check_positive(n_sticks, "n_sticks", integer=True)
    frames = _check_frames(frames)
    check_positive(noise, "noise", allow_zero=True)
    rng = check_random_state(seed)
    lo, hi = (points_per_stick, points_per_stick) if np.isscalar(points_per_stick) else points_per_stick
    lo, hi = int(lo), int(hi)
    if lo < 1 or hi < lo:
        raise ValueError(f"points_per_stick must be >= 1 (or a (low, high) range), got {points_per_stick!r}")

    lengths = rng.uniform(0.7, 1.3, size=n_sticks)
    parent = -np.ones(n_sticks, np.int64)
    attach = np.zeros((n_sticks, 3))
    # Free attachment sites: ("distal"|"proximal"|"interior", stick).
    sites: list[tuple[str, int]] = [("distal", 0), ("proximal", 0), ("interior", 0)]
    for s in range(1, n_sticks):
        kind, p = sites.pop(int(rng.integers(len(sites))))
        parent[s] = p
        if kind == "distal":
            attach[s] = [lengths[p], 0, 0]
        elif kind == "proximal":
            attach[s] = [0, 0, 0]
        else:
            attach[s] = [rng.uniform(0.35, 0.65) * lengths[p], 0, 0]
        sites += [("distal", s), ("interior", s)]

    counts = rng.integers(lo, hi + 1, size=n_sticks)
    labels = np.repeat(np.arange(n_sticks), counts)
    local = np.concatenate([_scatter_points(rng, lengths[s], counts[s], planar, spread) for s in range(n_sticks)])
    spec = FigureSpec(parent=parent, attach=attach, lengths=lengths, local=local, labels=labels)

    # Rest orientation of each stick relative to its parent, then smooth motion about it.
    pts, joints = _forward_kinematics(spec, *_random_motion(rng, n_sticks, frames, amplitude, planar))
    meta = {"generator": "random_figure", "n_sticks": n_sticks, "planar": planar}
    return _finish(pts, joints, spec, rng, noise, view, planar, meta, frame_rate=30.0)


def star(
    n_limbs: int = 4,
    frames: int = 120,
    noise: float = 0.01,
    seed: Any = None,
    *,
    hub_points: int = 10,
    limb_points: int = 5,
    view: tuple[float, float] | None = None,
    amplitude: float = 0.9,
) -> Trajectories:
    """A hub stick with ``n_limbs`` one-stick limbs: a torso with head and limbs, or a quadruped's body.

    :func:`random_figure` uses each attachment point once, so none of its sticks
    is on more than three joints; a body's torso is on four (neck, shoulders,
    lumbar) and a quadruped's on five or six. Here every limb hangs from its own
    point of the hub: its two ends first, then points along it, alternately to
    either side of its axis (0.2 of its length off it, so no two joints coincide).
    The hub moves freely; each limb turns about its joint with a smooth random
    3-DOF rotation. Points are scattered rigidly around each stick as in
    :func:`random_figure`, and the figure is seen by a scaled-orthographic camera.

    Parameters
    ----------
    n_limbs : int
        Number of limbs (>= 1); stick 0 is the hub, sticks 1 to ``n_limbs`` the limbs.
    frames : int
        Number of frames (>= 2).
    noise : float
        Gaussian noise std as a fraction of the mean stick length.
    seed : None, int or Generator
    hub_points, limb_points : int
        Points on the hub and on each limb (>= 1).
    view : (azimuth, elevation) in degrees, optional
        Camera direction; random (elevation in [-20, 60]) when omitted.
    amplitude : float
        Typical joint rotation amplitude in radians.

    Returns
    -------
    Trajectories
        2D trajectories with ``labels_true``, ``edges_true`` and ``joints_true``.
    """
    n_limbs = check_positive(n_limbs, "n_limbs", integer=True)
    frames = _check_frames(frames)
    hub_points = check_positive(hub_points, "hub_points", integer=True)
    limb_points = check_positive(limb_points, "limb_points", integer=True)
    check_positive(noise, "noise", allow_zero=True)
    rng = check_random_state(seed)
    S = n_limbs + 1
    lengths = rng.uniform(0.7, 1.3, size=S)
    lengths[0] = 1.5  # the hub: room for its joints
    parent = np.concatenate([[-1], np.zeros(n_limbs, np.int64)])
    attach = np.zeros((S, 3))
    inner = np.linspace(0.0, 1.0, max(n_limbs - 2, 0) + 2)[1:-1]
    fractions = np.concatenate([[0.0, 1.0], inner])[:n_limbs]
    for k, f in enumerate(fractions):
        side = 0.0 if k < 2 else (0.2 if k % 2 == 0 else -0.2) * lengths[0]
        attach[k + 1] = [f * lengths[0], side, 0.0]
    counts = np.concatenate([[hub_points], np.full(n_limbs, limb_points)])
    labels = np.repeat(np.arange(S), counts)
    local = np.concatenate([_scatter_points(rng, lengths[s], int(counts[s]), False, 0.25) for s in range(S)])
    spec = FigureSpec(parent=parent, attach=attach, lengths=lengths, local=local, labels=labels)
    pts, joints = _forward_kinematics(spec, *_random_motion(rng, S, frames, amplitude, False))
    meta = {"generator": "star", "n_sticks": S, "planar": False}
    return _finish(pts, joints, spec, rng, noise, view, False, meta, frame_rate=30.0,
                   part_names=["hub"] + [f"limb{k + 1}" for k in range(n_limbs)])


def arm(
    n_joints: int = 4,
    n_points: int = 32,
    n_frames: int = 33,
    noise: float = 0.01,
    seed: Any = None,
    *,
    fold: float = np.radians(150.0),
) -> Trajectories:
    """The articulated arm of Meeds et al. (their Fig. 2): a planar chain of sticks.

    The chain hangs from a fixed pivot at the origin and rotates
    counter-clockwise; its joints bend until the arm folds onto itself, then
    it opens up again. With the defaults: 4 sticks, 8 points each, 33 frames.

    Parameters
    ----------
    n_joints : int
        Number of sticks in the chain (the pivot is the first joint).
    n_points : int
        Total number of points, spread evenly over the sticks.
    n_frames : int
    noise : float
        Gaussian noise std as a fraction of the stick length.
    seed : None, int or Generator
    fold : float
        Largest bend of each joint, in radians.

    Returns
    -------
    Trajectories
        2D (y up), with ground truth. ``joints_true`` holds the joints between
        sticks; the fixed pivot is in ``meta["pivot"]``.
    """
    n_joints = check_positive(n_joints, "n_joints", integer=True)
    n_points = check_positive(n_points, "n_points", integer=True)
    if n_points < n_joints:
        raise ValueError(f"n_points ({n_points}) must be at least n_joints ({n_joints})")
    n_frames = _check_frames(n_frames, "n_frames")
    check_positive(noise, "noise", allow_zero=True)
    rng = check_random_state(seed)
    S = n_joints
    lengths = np.ones(S)
    counts = np.full(S, n_points // S)
    counts[: n_points % S] += 1
    labels = np.repeat(np.arange(S), counts)
    local = np.zeros((n_points, 3))
    for s in range(S):
        m = labels == s
        k = int(m.sum())
        local[m, 0] = (np.arange(k) + 0.5) / k * lengths[s]
        local[m, 1] = 0.06 * rng.uniform(-1, 1, size=k) * lengths[s]
    parent = np.arange(S) - 1
    attach = np.zeros((S, 3))
    attach[1:, 0] = lengths[:-1]
    spec = FigureSpec(parent=parent, attach=attach, lengths=lengths, local=local, labels=labels)
    u = np.linspace(0.0, 1.0, n_frames)
    bend = fold * np.sin(np.pi * u)  # folds, then opens again
    base = -np.pi / 2 + 2 * np.pi * u  # one counter-clockwise turn about the pivot
    angles = np.empty((S, n_frames))
    angles[0] = base
    angles[1:] = bend[None, :] * np.linspace(1.0, 0.8, S - 1)[:, None] if S > 1 else 0
    rotvec = np.zeros((S, n_frames, 3))
    rotvec[..., 2] = angles
    rel = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(S, n_frames, 3, 3)
    pts, joints = _forward_kinematics(spec, rel, np.zeros((n_frames, 3)))
    meta = {"generator": "arm", "pivot": [0.0, 0.0]}
    return _finish(pts, joints, spec, rng, noise, None, True, meta, frame_rate=None)


_WALKER_BONES = [
    # name, parent, attach (fraction along parent: 0 proximal, 1 distal), length, rest direction (x fwd, y left, z up)
    ("pelvis", -1, 0.0, 0.28, (0.0, 1.0, 0.0)),
    ("torso", 0, 0.5, 0.55, (0.0, 0.0, 1.0)),
    ("head", 1, 1.0, 0.25, (0.0, 0.0, 1.0)),
    ("l_upper_arm", 1, 0.9, 0.30, (0.0, 0.25, -1.0)),
    ("l_forearm", 3, 1.0, 0.27, (0.0, 0.0, -1.0)),
    ("r_upper_arm", 1, 0.8, 0.30, (0.0, -0.25, -1.0)),
    ("r_forearm", 5, 1.0, 0.27, (0.0, 0.0, -1.0)),
    ("l_thigh", 0, 1.0, 0.45, (0.0, 0.0, -1.0)),
    ("l_shin", 7, 1.0, 0.43, (0.0, 0.0, -1.0)),
    ("r_thigh", 0, 0.0, 0.45, (0.0, 0.0, -1.0)),
    ("r_shin", 9, 1.0, 0.43, (0.0, 0.0, -1.0)),
]


def walker(
    n_frames: int = 35,
    points_per_stick: int = 4,
    noise: float = 0.01,
    seed: Any = None,
    *,
    cycles: float = 1.0,
    view: str | tuple[float, float] = "side",
    project: bool = True,
) -> Trajectories:
    """A 3D human-like figure walking, seen by a scaled-orthographic camera.

    Eleven sticks (pelvis, torso, head, upper arms, forearms, thighs, shins)
    driven by a textbook gait: hips and shoulders swing in anti-phase, knees and
    elbows flex, the torso twists and the head nods, while the figure walks
    forward. Points sit rigidly around each bone, off its axis.

    Parameters
    ----------
    n_frames : int
    points_per_stick : int
    noise : float
        Gaussian noise std as a fraction of the mean bone length.
    seed : None, int or Generator
    cycles : float
        Number of gait cycles in the sequence.
    view : "side", "front", "isometric" or (azimuth, elevation)
    project : bool
        Return 2D (True) or the 3D trajectories (z up).
    """
    n_frames = check_positive(n_frames, "n_frames", integer=True)
    points_per_stick = check_positive(points_per_stick, "points_per_stick", integer=True)
    check_positive(noise, "noise", allow_zero=True)
    rng = check_random_state(seed)
    S = len(_WALKER_BONES)
    names = [b[0] for b in _WALKER_BONES]
    parent = np.array([b[1] for b in _WALKER_BONES])
    lengths = np.array([b[3] for b in _WALKER_BONES])
    # Each bone's local x axis points along its rest direction.
    rest = []
    for _, _, _, _, d in _WALKER_BONES:
        d = np.asarray(d, float) / np.linalg.norm(d)
        rest.append(Rotation.align_vectors([d], [[1.0, 0.0, 0.0]])[0].as_matrix())
    rest_world = np.stack(rest)
    attach = np.zeros((S, 3))
    for s in range(1, S):
        p = parent[s]
        attach[s] = [_WALKER_BONES[s][2] * lengths[p], 0, 0]
    labels = np.repeat(np.arange(S), points_per_stick)
    local = np.concatenate([_scatter_points(rng, lengths[s], points_per_stick, False, 0.3) for s in range(S)])
    spec = FigureSpec(parent=parent, attach=attach, lengths=lengths, local=local, labels=labels)

    ph = 2 * np.pi * cycles * np.linspace(0, 1, n_frames, endpoint=False) + rng.uniform(0, 2 * np.pi)
    swing = {  # pitch about the lateral (y) axis, radians
        "l_thigh": 0.45 * np.sin(ph), "r_thigh": 0.45 * np.sin(ph + np.pi),
        "l_shin": -0.55 * np.clip(np.sin(ph - 1.2), 0, None) - 0.1,
        "r_shin": -0.55 * np.clip(np.sin(ph + np.pi - 1.2), 0, None) - 0.1,
        "l_upper_arm": 0.4 * np.sin(ph + np.pi), "r_upper_arm": 0.4 * np.sin(ph),
        "l_forearm": 0.35 + 0.25 * np.sin(ph + np.pi), "r_forearm": 0.35 + 0.25 * np.sin(ph),
        "head": 0.15 * np.sin(2 * ph), "torso": 0.08 * np.sin(2 * ph),
    }
    world_R = np.empty((S, n_frames, 3, 3))
    yaw_torso = 0.15 * np.sin(ph)
    for s, name in enumerate(names):
        pitch = swing.get(name, np.zeros(n_frames))
        rv = np.zeros((n_frames, 3))
        rv[:, 1] = -pitch  # forward swing (+x) for positive pitch on a downward bone
        if name in ("torso", "pelvis"):
            rv[:, 2] = yaw_torso if name == "torso" else -0.5 * yaw_torso
        if name == "head":
            rv[:, 2] += 0.3 * np.sin(ph * 0.5)
        world_R[s] = Rotation.from_rotvec(rv).as_matrix() @ rest_world[s]
    # Relative rotations for forward kinematics (world orientation composed down the tree).
    rel = np.empty_like(world_R)
    for s in range(S):
        p = parent[s]
        rel[s] = world_R[s] if p < 0 else np.swapaxes(world_R[p], -1, -2) @ world_R[s]
    step = 0.6  # metres per gait cycle, roughly
    root_t = np.zeros((n_frames, 3))
    root_t[:, 0] = np.linspace(0, step * cycles, n_frames)
    root_t[:, 1] = -lengths[0] / 2
    root_t[:, 2] = 0.9 + 0.02 * np.cos(2 * ph)
    pts, joints = _forward_kinematics(spec, rel, root_t)
    meta = {"generator": "walker"}
    if not project:
        sigma = noise * float(np.mean(lengths))
        return Trajectories(
            xy=pts + sigma * rng.standard_normal(pts.shape), labels_true=labels, edges_true=spec.edges,
            part_names=names, joints_true=joints, frame_rate=30.0, up_axis=2, meta={**meta, "noise_std": sigma},
        )
    named = {"side": (-90.0, 0.0), "front": (0.0, 0.0), "isometric": (45.0, 35.264)}
    v = named[view] if isinstance(view, str) else view
    return _finish(pts, joints, spec, rng, noise, v, False, meta, frame_rate=30.0, part_names=names)


def rigid_bodies(
    n_bodies: int = 3,
    frames: int = 60,
    noise: float = 0.01,
    seed: Any = None,
    *,
    points_per_body: int | tuple[int, int] = (8, 14),
    perspective: float = 0.0,
    view: tuple[float, float] | None = None,
) -> Trajectories:
    """Independently moving rigid 3D bodies seen by one camera (a Hopkins-155-like scene).

    Each body is a random 3D point cloud (anisotropic, about unit size) that
    turns smoothly (a sum of sinusoids in its rotation vector, up to about 45
    degrees) and drifts on its own path; the bodies' paths cross, so their
    image regions overlap. The camera is scaled-orthographic, or a pinhole at
    distance ``1 / perspective`` scene radii (RMS) when ``perspective > 0``
    (0.1: mild, 0.3: strong foreshortening; the affine model then no longer
    fits exactly, as on real footage), but never closer than twice the
    deepest point's depth.

    Parameters
    ----------
    n_bodies : int
        Number of bodies (>= 1).
    frames : int
        Number of frames (>= 2).
    noise : float
        Gaussian noise std as a fraction of the mean body size (the RMS radius).
    seed : None, int or Generator
    points_per_body : int or (low, high)
        Points on each body, fixed or drawn uniformly in ``[low, high]``.
    perspective : float
        0 for an affine camera; otherwise the inverse camera distance in
        scene radii, in (0, 0.5].
    view : (azimuth, elevation) in degrees, optional
        Camera direction; random when omitted.

    Returns
    -------
    Trajectories
        2D (y up) with ``labels_true`` (the body of each point), ``edges_true``
        empty (no joints) and ``meta["noise_std"]``.
    """
    n_bodies = check_positive(n_bodies, "n_bodies", integer=True)
    frames = _check_frames(frames)
    check_positive(noise, "noise", allow_zero=True)
    if not 0 <= perspective <= 0.5:
        raise ValueError(f"perspective must be in [0, 0.5], got {perspective!r}")
    rng = check_random_state(seed)
    lo, hi = (points_per_body, points_per_body) if np.isscalar(points_per_body) else points_per_body
    lo, hi = int(lo), int(hi)
    if lo < 1 or hi < lo:
        raise ValueError(f"points_per_body must be >= 1 (or a (low, high) range), got {points_per_body!r}")
    counts = rng.integers(lo, hi + 1, size=n_bodies)
    labels = np.repeat(np.arange(n_bodies), counts)
    shapes = [rng.normal(size=(n, 3)) * rng.uniform(0.3, 1.0, size=3) for n in counts]
    size = float(np.mean([np.sqrt(np.mean(np.sum(sh * sh, axis=1))) for sh in shapes]))
    rest = Rotation.random(n_bodies, random_state=rng).as_rotvec()
    rv = _smooth_rotvecs(rng, n_bodies, frames, 0.8, planar=False) + rest[:, None, :]
    R = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(n_bodies, frames, 3, 3)
    t = np.linspace(0.0, 1.0, frames)[:, None]
    start = rng.normal(size=(n_bodies, 1, 3)) * 1.5
    # each body heads roughly through the scene centre, so image regions cross
    velocity = -start * rng.uniform(1.0, 2.0, size=(n_bodies, 1, 1)) + rng.normal(size=(n_bodies, 1, 3)) * 0.5
    centres = start + velocity * t[None]  # (B, F, 3)
    pts = np.concatenate([np.einsum("fij,pj->pfi", R[b], shapes[b]) + centres[b][None] for b in range(n_bodies)])
    if view is None:
        az, el = float(rng.uniform(0, 360)), float(rng.uniform(-20, 60))
    else:
        az, el = (float(v) for v in view)
    cam = pts @ view_rotation(az, el, up_axis=2).T  # (P, F, 3): image x, y and depth
    if perspective > 0:
        cam = cam - cam.mean(axis=(0, 1))
        radius = float(np.sqrt(np.mean(np.sum(cam * cam, axis=-1))))
        # never closer than twice the deepest point: no point reaches the camera plane
        dist = max(radius / perspective, 2.0 * float(np.abs(cam[..., 2]).max()))
        xy = cam[..., :2] * (dist / (dist + cam[..., 2:]))
    else:
        xy = cam[..., :2]
    sigma = noise * size
    xy = xy + sigma * rng.standard_normal(xy.shape)
    return Trajectories(
        xy=xy,
        labels_true=labels,
        edges_true=[],
        part_names=[f"body{b}" for b in range(n_bodies)],
        meta={"generator": "rigid_bodies", "noise_std": sigma, "view": [az, el], "perspective": perspective},
    )


def occlude(
    traj: Trajectories,
    seed: Any = None,
    *,
    bar_fraction: float = 0.075,
    random_fraction: float = 0.05,
    frames: slice | None = None,
) -> tuple[Trajectories, np.ndarray]:
    """Hide observations as in Ross et al.: a sweeping vertical bar plus random drop-outs.

    A vertical bar crosses the scene from left to right over the frames,
    hiding every point behind it; its width is chosen so that it hides
    ``bar_fraction`` of the observed entries. Then ``random_fraction`` of the
    remaining observed entries go missing at random. With the defaults about
    12% of the observations are hidden (the paper's 10-15%).

    Parameters
    ----------
    traj : Trajectories
        2D trajectories (3D ones are occluded in their first two coordinates).
    seed : None, int or Generator
    bar_fraction : float
        Share of observed entries the bar hides.
    random_fraction : float
        Share of the remaining observed entries hidden at random.
    frames : slice, optional
        Restrict the occlusion to these frames (e.g. the test part).

    Returns
    -------
    occluded : Trajectories
        A copy with the hidden entries set to NaN (never-observed points allowed).
    hidden : ndarray of bool, shape (P, F)
        The entries that were observed in ``traj`` and are hidden now.
    """
    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories, got {type(traj).__name__}")
    if not 0 <= bar_fraction < 1 or not 0 <= random_fraction < 1:
        raise ValueError("bar_fraction and random_fraction must be in [0, 1)")
    rng = check_random_state(seed)
    P, F = traj.n_points, traj.n_frames
    fsel = np.zeros(F, bool)
    fsel[frames if frames is not None else slice(None)] = True
    obs = traj.observed & fsel[None, :]
    x = traj.xy[..., 0]
    fidx = np.flatnonzero(fsel)
    lo, hi = np.nanmin(x[:, fidx]), np.nanmax(x[:, fidx])
    span = max(hi - lo, 1e-12)
    # Bar centre moves linearly across the frames it covers.
    pos = np.full(F, np.nan)
    if fidx.size > 1:
        pos[fidx] = np.linspace(0.0, 1.0, fidx.size)
    else:
        pos[fidx] = 0.5

    def bar_mask(width: float) -> np.ndarray:
        centre = lo - width / 2 + pos * (span + width)
        with np.errstate(invalid="ignore"):
            return obs & (np.abs(x - centre[None, :]) <= width / 2)

    n_obs = int(obs.sum())
    target = bar_fraction * n_obs
    a, b = 0.0, 2.0 * span
    for _ in range(50):  # bisection: the hidden count grows with the width
        mid = 0.5 * (a + b)
        if bar_mask(mid).sum() < target:
            a = mid
        else:
            b = mid
    hidden = bar_mask(b) if bar_fraction > 0 else np.zeros((P, F), bool)
    rest = np.flatnonzero((obs & ~hidden).ravel())
    n_rand = int(round(random_fraction * rest.size))
    if n_rand:
        flat = hidden.ravel().copy()
        flat[rng.choice(rest, size=n_rand, replace=False)] = True
        hidden = flat.reshape(P, F)
    xy = traj.xy.copy()
    xy[hidden] = np.nan
    out = traj.with_xy(xy)
    out.meta["occlusion"] = {"bar_fraction": bar_fraction, "random_fraction": random_fraction,
                             "hidden_fraction": float(hidden.sum() / max(n_obs, 1))}
    return out, hidden


def marker_gaps(
    traj: Trajectories,
    n_points: int,
    seed: Any = None,
    *,
    min_fraction: float = 0.2,
    max_fraction: float = 0.6,
) -> tuple[Trajectories, np.ndarray]:
    """Lose some points for long stretches, as markers drop out of raw optical capture.

    ``n_points`` points, drawn without replacement, each lose one contiguous run of
    frames whose length is drawn uniformly between ``min_fraction`` and
    ``max_fraction`` of the frames and whose start is drawn uniformly where the run
    fits. Unlike :func:`occlude` (a bar that sweeps across the scene, so each point
    is hidden briefly), a gap here can outlast several cycles of the motion, which
    linear interpolation cannot bridge.

    Parameters
    ----------
    traj : Trajectories
    n_points : int
        Points that lose a run, at most ``traj.n_points``.
    seed : None, int or Generator
    min_fraction, max_fraction : float
        Bounds of a run's length as a share of the frames, 0 < min <= max < 1.

    Returns
    -------
    gapped : Trajectories
        A copy with the hidden entries set to NaN.
    hidden : ndarray of bool, shape (P, F)
        The entries that were observed in ``traj`` and are hidden now.
    """
    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories, got {type(traj).__name__}")
    n_points = check_positive(n_points, "n_points", integer=True)
    if n_points > traj.n_points:
        raise ValueError(f"n_points must be at most the {traj.n_points} points of traj, got {n_points}")
    if not 0 < min_fraction <= max_fraction < 1:
        raise ValueError(f"need 0 < min_fraction <= max_fraction < 1, got {min_fraction} and {max_fraction}")
    rng = check_random_state(seed)
    P, F = traj.n_points, traj.n_frames
    hidden = np.zeros((P, F), bool)
    for p in rng.choice(P, size=n_points, replace=False):  # a few points: no loop over frames
        length = max(1, int(round(rng.uniform(min_fraction, max_fraction) * F)))
        start = int(rng.integers(0, F - length + 1))
        hidden[p, start:start + length] = True
    hidden &= traj.observed
    xy = traj.xy.copy()
    xy[hidden] = np.nan
    out = traj.with_xy(xy)
    out.meta["gaps"] = {"n_points": n_points, "min_fraction": min_fraction, "max_fraction": max_fraction,
                        "hidden_fraction": float(hidden.sum() / max(int(traj.observed.sum()), 1))}
    return out, hidden


def skin_motion(traj: Trajectories, sd: Any, seed: Any = None, *, timescale: float = 12.0) -> Trajectories:
    """Move every point by a smooth random displacement, as skin and soft tissue move markers.

    A marker on the skin is not rigid on its bone: it slides with the skin and the
    tissue under it, slowly compared with the frame rate. Here every coordinate of
    every point gets its own displacement: white Gaussian noise over the frames,
    smoothed by a Gaussian kernel of ``timescale`` frames (standard deviation) and
    scaled to standard deviation ``sd``. Its autocorrelation falls to one half at
    about ``1.67 * timescale`` frames. Missing observations stay missing; the ground
    truth (parts, tree, joints) is kept, since the bones do not move.

    On the recorded CMU 85_02 take (120 Hz) the distances between markers of one
    segment vary by 5.0-6.2 mm (s.d.) on the pelvis and 8.9-13.3 mm on the thorax,
    and their autocorrelation falls to one half in 22-35 frames. Independent
    displacements of ``sd`` per coordinate make a distance vary by about
    ``sd * sqrt(2)``, so ``sd`` = 4.5 mm with ``timescale`` = 12 frames matches the
    pelvis (docs/em.md section 11, session 29).

    Parameters
    ----------
    traj : Trajectories
        Points of shape (P, F, D); at least 2 frames.
    sd : float or array_like, shape (P,)
        Standard deviation of each coordinate's displacement, in the data's units (>= 0):
        one for every point, or each point's own (skin moves more over some segments
        than over others).
    seed : None, int or Generator
    timescale : float
        Standard deviation of the smoothing kernel, in frames (> 0).

    Returns
    -------
    Trajectories
        A copy with the displaced points.
    """
    from scipy.ndimage import gaussian_filter1d

    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories, got {type(traj).__name__}")
    try:
        sd_arr = np.asarray(sd, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"sd must be a number or an array of numbers, got {sd!r}") from None
    if sd_arr.ndim == 0:
        sd_arr = np.full(traj.n_points, float(sd_arr))
    if sd_arr.shape != (traj.n_points,):
        raise ValueError(f"sd must be a number or have shape ({traj.n_points},), got shape {sd_arr.shape}")
    if not np.all(np.isfinite(sd_arr) & (sd_arr >= 0)):
        raise ValueError("sd must be finite and >= 0 for every point")
    timescale = check_positive(timescale, "timescale")
    if traj.n_frames < 2:
        raise ValueError(f"skin motion needs at least 2 frames, got {traj.n_frames}")
    rng = check_random_state(seed)
    w = gaussian_filter1d(rng.standard_normal(traj.xy.shape), timescale, axis=1, mode="reflect")
    w /= np.maximum(w.std(axis=1, keepdims=True), 1e-300)  # each coordinate's displacement: s.d. 1 over the frames
    out = traj.with_xy(traj.xy + sd_arr[:, None, None] * w)
    out.meta["skin_motion"] = {"sd": float(sd_arr[0]) if np.ptp(sd_arr) == 0 else sd_arr.tolist(),
                               "timescale": float(timescale)}
    return out
