"""The structure-from-motion baselines "sfm" and "multibody-sfm", and the loaders.

Cases
-----
sfm-imputation
    One rigid body (``synthetic.rigid_bodies(1)``, 20-40 points, 60-120 frames,
    1% noise, random views) with 30% of its entries missing at random: RMSE of
    the hidden entries in units of the noise std (the foundation issue asks
    for <= 2), mean and worst over scenes.
multibody-sfm-rigid
    Independently moving rigid bodies (``synthetic.rigid_bodies``, 2-5 bodies,
    10-60 points each, 30-80 frames, 1% noise), under an affine camera and
    under mild (0.1) and strong (0.25) perspective, the number of bodies
    estimated: misclassification (mean, worst), share of scenes with the right
    count.
multibody-sfm-hopkins
    Every Hopkins 155 sequence in the data directory, the number of bodies
    estimated: misclassification and the count found (the checkerboard
    ``1R2RC`` and ``truck1`` are rigid scenes; the others are articulated or
    non-rigid and shown for reference).
geometry-speed
    The shared geometry's kernels at fixed sizes, where the tests used to time
    them: the affine factorisation of one rigid body (50 points x 200 frames,
    30% missing) and the local-subspace affinity of two bodies (50 x 200).
load-real-data
    Every file in the data directory through ``stickfigure.load``: time,
    peak memory and what was read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np

import stickfigure as sf
from stickfigure.metrics import imputation_rmse, misclassification_rate

from .run import Case, Context


def case_sfm_imputation(ctx: Context) -> Iterator[dict[str, Any]]:
    ratios, rows = [], []
    for k in range(20 if ctx.full else 6):
        rng = np.random.default_rng(30_000 + ctx.seed * 1000 + k)
        tr = sf.synthetic.rigid_bodies(1, frames=int(rng.integers(60, 121)), noise=0.01, seed=rng,
                                       points_per_body=(20, 40))
        occ, hidden = tr.missing_at_random(0.3, random_state=rng)

        def run() -> np.ndarray:
            skel = sf.fit(occ, method="sfm", random_state=k)
            return skel.impute(occ)

        filled, timing = ctx.measure(run)
        ratios.append(imputation_rmse(filled, tr.xy, hidden) / tr.meta["noise_std"])
        rows.append(timing)
    yield {"dataset": "rigid body, 30% missing", "method": "sfm", "rmse": float(np.mean(ratios)),
           **{k: float(np.mean([r[k] for r in rows])) for k in ("time_s", "time_ratio", "peak_mb")},
           "notes": f"rmse in noise stds: mean {np.mean(ratios):.2f}, worst {np.max(ratios):.2f} "
                    f"over {len(ratios)} scenes"}


def case_multibody_rigid(ctx: Context) -> Iterator[dict[str, Any]]:
    for perspective in (0.0, 0.1, 0.25):
        mis, right, rows = [], [], []
        for k in range(20 if ctx.full else 6):
            rng = np.random.default_rng(40_000 + ctx.seed * 1000 + k)
            tr = sf.synthetic.rigid_bodies(int(rng.integers(2, 6)), frames=int(rng.integers(30, 81)), noise=0.01,
                                           seed=rng, points_per_body=(10, 60), perspective=perspective)
            skel, timing = ctx.measure(lambda: sf.fit(tr, method="multibody-sfm", random_state=k))
            mis.append(misclassification_rate(tr.labels_true, skel.labels))
            right.append(skel.n_sticks == tr.n_parts_true)
            rows.append(timing)
        yield {"dataset": f"rigid_bodies 2-5, perspective {perspective:g}", "method": "multibody-sfm",
               "misclassification": float(np.mean(mis)), "exact": float(np.mean(right)),
               **{k: float(np.mean([r[k] for r in rows])) for k in ("time_s", "time_ratio", "peak_mb")},
               "notes": f"worst misclassification {np.max(mis):.3f} over {len(mis)} scenes; "
                        "exact = share with the true number of bodies"}


def case_multibody_hopkins(ctx: Context) -> Iterator[dict[str, Any]]:
    assert ctx.data_dir is not None
    root = ctx.data_dir / "hopkins155"
    for path in sorted(root.glob("*/*_truth.mat")):
        tr = sf.load(path)
        skel, timing = ctx.measure(lambda: sf.fit(tr, method="multibody-sfm", random_state=ctx.seed))
        yield {"dataset": f"hopkins {path.parent.name} {tr.n_points}x{tr.n_frames}", "method": "multibody-sfm",
               "misclassification": misclassification_rate(tr.labels_true, skel.labels),
               "exact": skel.n_sticks == tr.n_parts_true, **timing,
               "notes": f"{skel.n_sticks} bodies found, {tr.n_parts_true} true"}


def _data_files(root: Path) -> list[Path]:
    out = []
    for p in sorted(root.rglob("*")):
        if p.suffix.lower() in (".c3d", ".bvh", ".amc", ".slp", ".mat", ".csv", ".npz") and p.is_file():
            out.append(p)
    return out


def case_geometry_speed(ctx: Context) -> Iterator[dict[str, Any]]:
    from stickfigure import geometry as g

    tr = sf.synthetic.random_figure(n_sticks=1, frames=200, noise=0.01, seed=6, points_per_stick=50)
    occ, _ = tr.missing_at_random(0.3, random_state=0)
    _, timing = ctx.measure(lambda: g.affine_factorization(occ.xy, 3, random_state=0))
    yield {"dataset": "1 body 50 x 200, 30% missing", "method": "affine_factorization", **timing}
    bodies = sf.synthetic.rigid_bodies(2, frames=200, noise=0.005, seed=11, points_per_body=(25, 25))
    _, timing = ctx.measure(lambda: g.local_subspace_affinity(bodies.xy))
    yield {"dataset": "2 bodies 50 x 200", "method": "local_subspace_affinity", **timing}


def case_load(ctx: Context) -> Iterator[dict[str, Any]]:
    assert ctx.data_dir is not None
    for path in _data_files(ctx.data_dir):
        try:
            traj, timing = ctx.measure(lambda: sf.load(path))
        except ValueError as exc:  # e.g. a MoCap Toolbox file holding several takes needs a name
            yield {"dataset": str(path.relative_to(ctx.data_dir)), "method": "load", "notes": f"needs options: {exc}"}
            continue
        truth = "labels" if traj.labels_true is not None else "no labels"
        yield {"dataset": str(path.relative_to(ctx.data_dir)), "method": "load", **timing,
               "notes": f"{traj.n_points} points x {traj.n_frames} frames, {traj.n_dims}D, "
                        f"{100 * traj.missing_fraction:.1f}% missing, {truth}"}


CASES = [
    Case("sfm-imputation", case_sfm_imputation),
    Case("multibody-sfm-rigid", case_multibody_rigid),
    Case("multibody-sfm-hopkins", case_multibody_hopkins, needs_data=True),
    Case("geometry-speed", case_geometry_speed),
    Case("load-real-data", case_load, needs_data=True),
]
