"""Topology methods: "mi-tree" and "yan-pollefeys" (with "em" beside them when it is registered).

Cases
-----
topology-synthetic-given
    Random 3D figures (``synthetic.random_figure``, 3-7 sticks, 90-180 frames,
    1% noise) with the true segmentation given: the tree alone (edge F1, exact).
topology-synthetic-e2e
    The same figures end to end: segmentation (ARI, misclassification) and tree.
topology-in-phase
    Ross et al.'s Fig. 7 failure of Yan & Pollefeys: a figure whose two legs are
    driven by the same joint-angle signal (:func:`in_phase_legs`). Reports edge
    F1 and whether the two legs were joined to each other.
topology-hopkins
    Hopkins 155 sequences (articulated ones first): misclassification of the
    segmentation (no joint tree in the ground truth).
topology-mocap
    Motion capture projected to 2D (needs ``stickfigure.load`` for C3D and a
    marker-to-segment ground truth; the case says so when either is missing).

Each row's ``notes`` says what was run; a method that is not registered yet is
reported as skipped rather than silently left out.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np
from scipy.spatial.transform import Rotation

import stickfigure as sf
from stickfigure.trajectories import Trajectories, view_rotation

from .run import Case, Context

METHODS = ("mi-tree", "yan-pollefeys", "em")
HOPKINS_ARTICULATED = ("arm", "articulated", "dancing", "head")
HOPKINS_OTHERS = ("people1", "truck1", "two_cranes", "1R2RC")


# ------------------------------------------------------------------ figures
def in_phase_legs(frames: int = 120, noise: float = 0.01, seed: Any = None, *,
                  view: tuple[float, float] = (60.0, 15.0), points_per_stick: int = 6,
                  roll: float = 0.3) -> Trajectories:
    """A lower body whose two legs move in phase (Ross et al., Fig. 7).

    Six sticks: pelvis (0, left-right), torso (1, up from the pelvis centre),
    left/right thighs (2, 3, from the pelvis ends) and shins (4, 5, from the
    knees). Hips and knees of both legs follow the *same* flexion signals (a
    two-footed hop), the torso leans with its own signal and the pelvis turns,
    drifts and tilts side to side (``roll`` radians, pelvic obliquity) while
    the legs keep swinging in the sagittal plane. Points are scattered rigidly
    around each stick; a scaled-orthographic camera looks from ``view``
    (azimuth, elevation).

    Why the tilt: without it the two legs are *one rigid body* -- the same
    rotation about the hip axis, and hips that stay on that axis -- so joining
    them (or making them one stick) is right, not Fig. 7's mistake. With it the
    two thighs still share their rotation, so their motion subspaces meet in
    three dimensions (what misleads Yan & Pollefeys), but the hips move up and
    down relative to each other (by ``2 * 0.16 * sin(roll)``, about a fifth of
    a thigh), so no rigid part and no joint holds both legs.

    Returns
    -------
    Trajectories
        2D, y up, with ``labels_true``, ``edges_true`` (parent, child) and
        ``joints_true``.
    """
    rng = np.random.default_rng(seed)
    names = ["pelvis", "torso", "l_thigh", "r_thigh", "l_shin", "r_shin"]
    parent = np.array([-1, 0, 0, 0, 2, 3])
    lengths = np.array([0.32, 0.6, 0.45, 0.45, 0.43, 0.43])
    # Attachment in the parent's frame; every stick's own axis is its local x.
    attach = np.array([[0, 0, 0], [0.16, 0, 0], [0, 0, 0], [0.32, 0, 0], [0.45, 0, 0], [0.45, 0, 0]], float)
    # Rest orientations (world, z up): pelvis along y, torso up, legs down.
    rest = [Rotation.align_vectors([d], [[1.0, 0, 0]])[0] for d in
            ([0, 1, 0], [0, 0, 1], [0, 0, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1])]
    t = np.linspace(0, 1, frames)
    cyc = rng.uniform(1.5, 2.5)
    phase = rng.uniform(0, 2 * np.pi)
    hip = 0.6 * np.sin(2 * np.pi * cyc * t + phase)  # the same for both legs
    knee = 0.5 * (1 - np.cos(2 * np.pi * cyc * t + phase))
    lean = 0.25 * np.sin(2 * np.pi * rng.uniform(0.3, 0.8) * t + rng.uniform(0, 6.3))
    yaw = 0.3 * np.sin(2 * np.pi * rng.uniform(0.2, 0.5) * t + rng.uniform(0, 6.3))
    tilt = roll * np.sin(2 * np.pi * rng.uniform(0.6, 1.2) * t + rng.uniform(0, 6.3))
    # World rotations: flexion about the world y axis (sagittal plane), after the pelvis yaw;
    # the pelvis alone also tilts about the forward (x) axis.
    Ryaw = Rotation.from_rotvec(np.outer(yaw, [0, 0, 1.0]))
    Rtilt = Rotation.from_rotvec(np.outer(tilt, [1.0, 0, 0]))
    R = [Ryaw * Rtilt * rest[0], Ryaw * Rotation.from_rotvec(np.outer(lean, [0, 1.0, 0])) * rest[1]]
    thigh = Ryaw * Rotation.from_rotvec(np.outer(hip, [0, 1.0, 0]))
    shin = Ryaw * Rotation.from_rotvec(np.outer(hip - knee, [0, 1.0, 0]))
    R += [thigh * rest[2], thigh * rest[3], shin * rest[4], shin * rest[5]]
    Rm = np.stack([r.as_matrix() for r in R])  # (S, F, 3, 3)
    origin = np.zeros((6, frames, 3))
    origin[0] = np.outer(t, [0.4, 0.1, 0]) + 0.05 * np.sin(2 * np.pi * cyc * t)[:, None] * [0, 0, 1.0]
    for s in range(1, 6):
        origin[s] = origin[parent[s]] + np.einsum("fij,j->fi", Rm[parent[s]], attach[s])
    counts = np.full(6, points_per_stick)
    labels = np.repeat(np.arange(6), counts)
    along = rng.uniform(0.1, 0.9, labels.size) * lengths[labels]
    ang = rng.uniform(0, 2 * np.pi, labels.size)
    rad = 0.2 * lengths[labels] * rng.uniform(0.3, 1.0, labels.size)
    local = np.column_stack([along, rad * np.cos(ang), rad * np.sin(ang)])
    pts = np.einsum("pfij,pj->pfi", Rm[labels], local) + origin[labels]
    edges = [(int(p), s) for s, p in enumerate(parent) if p >= 0]
    joints = np.stack([origin[c] for _, c in edges])
    P2 = view_rotation(*view, up_axis=2)[:2]
    sigma = noise * float(lengths.mean())
    xy = pts @ P2.T + sigma * rng.standard_normal((labels.size, frames, 2))
    return Trajectories(xy=xy, labels_true=labels, edges_true=edges, part_names=names,
                        joints_true=joints @ P2.T, frame_rate=30.0,
                        meta={"generator": "in_phase_legs", "noise_std": sigma, "view": list(view),
                              "roll": float(roll)})


def _random_figures(ctx: Context) -> Iterator[tuple[int, Trajectories]]:
    n = 30 if ctx.full else 8
    for k in range(n):
        seed = ctx.seed * 1000 + k
        rng = np.random.default_rng(10_000 + seed)
        traj = sf.synthetic.random_figure(n_sticks=int(rng.integers(3, 8)), frames=int(rng.integers(90, 181)),
                                          noise=0.01, seed=seed)
        yield seed, traj


# ------------------------------------------------------------------ scoring
def _registered(name: str) -> bool:
    return name in sf.available_methods()


def _score(skel: sf.Skeleton, traj: Trajectories) -> dict[str, Any]:
    from stickfigure.metrics import score_skeleton

    s = score_skeleton(skel, traj)
    return {k: s.get(k) for k in ("ari", "misclassification", "edge_f1", "exact")}


def _mean_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k in ("ari", "misclassification", "edge_f1", "exact", "time_s", "time_ratio", "peak_mb"):
        vals = [float(r[k]) for r in rows if r.get(k) is not None]
        if vals:
            out[k] = float(np.mean(vals))
    return out


def _fit_kwargs(method: str, traj: Trajectories, given: bool) -> dict[str, Any]:
    if not given:
        return {}
    if method in ("mi-tree", "yan-pollefeys"):
        return {"labels": traj.labels_true}
    return {"labels": traj.labels_true}  # em is expected to accept a given segmentation too


def _synthetic(ctx: Context, given: bool) -> Iterator[dict[str, Any]]:
    suite = "topology-synthetic-" + ("given" if given else "e2e")
    figures = list(_random_figures(ctx))
    for method in METHODS:
        if not _registered(method):
            yield {"suite": suite, "dataset": "random_figure", "method": method, "notes": "not registered yet"}
            continue
        rows, failures = [], 0
        for seed, traj in figures:
            try:
                skel, timing = ctx.measure(lambda: sf.fit(traj, method=method, random_state=seed,
                                                          **_fit_kwargs(method, traj, given)))
            except TypeError as exc:  # a method that does not take a given segmentation
                yield {"suite": suite, "dataset": "random_figure", "method": method, "notes": f"skipped: {exc}"}
                break
            except Exception as exc:  # one failure is a result, not a crash of the table
                failures += 1
                last = f"{type(exc).__name__}: {exc}"
                continue
            rows.append({**_score(skel, traj), **timing})
        else:
            note = f"mean of {len(rows)} figures (3-7 sticks, 90-180 frames, 1% noise)"
            if failures:
                note += f"; {failures} failed ({last})"
            yield {"suite": suite, "dataset": "random_figure", "method": method, **_mean_rows(rows), "notes": note}


def case_synthetic_given(ctx: Context) -> Iterator[dict[str, Any]]:
    yield from _synthetic(ctx, given=True)


def case_synthetic_e2e(ctx: Context) -> Iterator[dict[str, Any]]:
    yield from _synthetic(ctx, given=False)


def _legs_joined(skel: sf.Skeleton, traj: Trajectories) -> bool | None:
    """Whether the learned tree joins a left-leg part directly to a right-leg part."""
    if skel.n_sticks < 2:
        return None
    # Map every learned stick to the true part most of its points belong to.
    major = np.array([np.bincount(traj.labels_true[skel.labels == s], minlength=6).argmax()
                      if (skel.labels == s).any() else -1 for s in range(skel.n_sticks)])
    left, right = {2, 4}, {3, 5}
    return any((major[a] in left and major[b] in right) or (major[a] in right and major[b] in left)
               for a, b in skel.edges)


def case_in_phase(ctx: Context) -> Iterator[dict[str, Any]]:
    n = 10 if ctx.full else 4
    figures = [in_phase_legs(frames=120, noise=0.01, seed=ctx.seed * 100 + k) for k in range(n)]
    for given in (True, False):
        for method in METHODS:
            tag = "given segmentation" if given else "end to end"
            if not _registered(method):
                yield {"suite": "topology-in-phase", "dataset": f"in_phase_legs ({tag})", "method": method,
                       "notes": "not registered yet"}
                continue
            rows, joined = [], []
            for k, traj in enumerate(figures):
                try:
                    skel, timing = ctx.measure(lambda: sf.fit(traj, method=method, random_state=k,
                                                              **_fit_kwargs(method, traj, given)))
                except Exception as exc:
                    rows.append({"notes": f"{type(exc).__name__}: {exc}"})
                    continue
                rows.append({**_score(skel, traj), **timing})
                joined.append(bool(_legs_joined(skel, traj)))
            yield {"suite": "topology-in-phase", "dataset": f"in_phase_legs ({tag})", "method": method,
                   **_mean_rows(rows), "legs_joined": f"{sum(joined)}/{len(joined)}",
                   "notes": f"{len(figures)} figures, 6 sticks, both legs driven by one hip/knee signal, the pelvis tilting"}


def _load_hopkins(folder: Path) -> Trajectories:
    """A Hopkins 155 sequence through stickfigure.load (the io module's .mat reader)."""
    mats = sorted(folder.glob("*_truth.mat"))
    if not mats:
        raise FileNotFoundError(f"no *_truth.mat in {folder}")
    return sf.load(mats[0])


def case_hopkins(ctx: Context) -> Iterator[dict[str, Any]]:
    root = ctx.data_dir / "hopkins155"
    for name in HOPKINS_ARTICULATED + HOPKINS_OTHERS:
        folder = root / name
        if not folder.is_dir():
            continue
        try:
            traj = _load_hopkins(folder)
        except Exception as exc:
            yield {"suite": "topology-hopkins", "dataset": name, "notes": f"not loaded: {type(exc).__name__}: {exc}"}
            continue
        for method in METHODS:
            if not _registered(method):
                yield {"suite": "topology-hopkins", "dataset": name, "method": method, "notes": "not registered yet"}
                continue
            try:
                skel, timing = ctx.measure(lambda: sf.fit(traj, method=method, random_state=ctx.seed))
            except Exception as exc:
                yield {"suite": "topology-hopkins", "dataset": name, "method": method,
                       "notes": f"failed: {type(exc).__name__}: {exc}"}
                continue
            score = _score(skel, traj)
            yield {"suite": "topology-hopkins", "dataset": name, "method": method,
                   "ari": score["ari"], "misclassification": score["misclassification"], **timing,
                   "notes": f"{traj.n_points} pts x {traj.n_frames} frames, {traj.n_parts_true} true parts, "
                            f"{skel.n_sticks} found" + (" (articulated)" if name in HOPKINS_ARTICULATED else "")}


def case_mocap(ctx: Context) -> Iterator[dict[str, Any]]:
    mocap = ctx.data_dir / "mocap"
    for fname in ("85_02.c3d", "HDM_dg_06-03_03_120.c3d"):
        path = mocap / fname
        if not path.exists():
            continue
        try:
            traj3 = sf.load(path)
        except Exception as exc:
            yield {"suite": "topology-mocap", "dataset": fname, "notes": f"not loaded: {type(exc).__name__}: {exc}"}
            continue
        if traj3.labels_true is None:
            yield {"suite": "topology-mocap", "dataset": fname,
                   "notes": "loaded, but no marker-to-segment ground truth to score against"}
            continue
        step = max(1, int(round((traj3.frame_rate or 30.0) / 30.0)))
        traj = traj3.drop_unobserved().subsample(step).project("isometric")
        frames = traj.n_frames if ctx.full else min(traj.n_frames, 150)
        traj = traj.slice(frames=slice(0, frames)).drop_unobserved()
        for method in METHODS:
            if not _registered(method):
                yield {"suite": "topology-mocap", "dataset": fname, "method": method, "notes": "not registered yet"}
                continue
            for given in (True, False):
                kwargs = _fit_kwargs(method, traj, given)
                extra = ""
                if given and method == "mi-tree":
                    # A similarity pose needs two points: single-marker segments are left out (-1).
                    lab = np.asarray(kwargs["labels"]).copy()
                    ids, counts = np.unique(lab[lab >= 0], return_counts=True)
                    single = ids[counts < 2]
                    if single.size:
                        lab[np.isin(lab, single)] = -1
                        kwargs["labels"] = lab
                        extra = f"; {single.size} single-marker segments left out (a similarity needs 2 points)"
                try:
                    skel, timing = ctx.measure(lambda: sf.fit(traj, method=method, random_state=ctx.seed, **kwargs))
                except Exception as exc:
                    yield {"suite": "topology-mocap", "dataset": fname, "method": method,
                           "notes": f"failed: {type(exc).__name__}: {exc}"}
                    continue
                yield {"suite": "topology-mocap", "dataset": fname, "method": method, **_score(skel, traj),
                       **timing, "notes": ("given segmentation" if given else "end to end")
                       + f", isometric 2D, {traj.n_points} markers x {traj.n_frames} frames at 30 Hz" + extra}


CASES = [
    Case("topology-synthetic-given", case_synthetic_given),
    Case("topology-synthetic-e2e", case_synthetic_e2e),
    Case("topology-in-phase", case_in_phase),
    Case("topology-hopkins", case_hopkins, needs_data=True),
    Case("topology-mocap", case_mocap, needs_data=True),
]
