"""Method "mcmc" (Meeds, Ross, Zemel & Roweis): structure, imputation and speed on the paper's sizes.

Cases
-----
mcmc-arm
    The 4-joint arm (32 points x 33 frames), several seeds, clean and with the
    sweeping occluder (``synthetic.occlude``: a bar plus 5% at random, about 12%
    hidden): how often the most probable structure is the true one (``exact``),
    ARI, edge F1, imputation RMSE of the hidden entries (occluded runs; the
    model is fitted to the occluded data and ``Skeleton.impute`` fills them), the
    posterior mass on 3-4 sticks and the log-joint R-hat across the 4 chains.
mcmc-random-planar
    Random planar figures with 3-6 sticks (``synthetic.random_figure(planar=True)``,
    60 frames quick / 120 full), clean and occluded, with ``em`` on the same
    scenes: ARI, edge F1 (each learned stick mapped to the true part holding
    most of its points), exact-structure rate, imputation RMSE.
mcmc-giraffe-sized / mcmc-walker-sized
    Random planar figures of the paper's giraffe size (8 sticks, about 58
    points x 30 frames) and walking-man size (10 sticks of 4 points: 40 x 35),
    clean and occluded; the same scores, and ``em`` on the same scenes (ARI,
    edge F1, RMSE) when it is installed.
mcmc-walker-projected
    The 3D walking figure (``synthetic.walker``: 11 sticks, 44 x 35) seen from
    the side: the 2D model on projected 3D motion.
mcmc-speed
    One chain, one process, one BLAS thread, on the giraffe-sized figure: CPU
    seconds per 1000 sweeps (``ctx.full`` runs all 1000; quick runs 200 and
    scales), timed without tracemalloc (which slows this workload about
    threefold) and as CPU time so that other load on the machine counts little.

Time columns are the whole fit (4 chains on the available cores) unless the
row says otherwise.
"""

from __future__ import annotations

import time
from typing import Any, Iterator

import numpy as np

import stickfigure as sf
from stickfigure.metrics import imputation_rmse, score_skeleton
from stickfigure.trajectories import Trajectories

from .run import Case, Context


def _scores(skel: sf.Skeleton, traj: Trajectories) -> dict[str, Any]:
    s = score_skeleton(skel, traj)
    return {k: s.get(k) for k in ("ari", "misclassification", "edge_f1", "exact")}


def _fit(method: str, traj: Trajectories, seed: int, ctx: Context, **kw: Any) -> tuple[sf.Skeleton, dict]:
    return ctx.measure(lambda: sf.fit(traj, method=method, random_state=seed, **kw))


def _mean_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k in ("ari", "misclassification", "edge_f1", "rmse", "time_s", "time_ratio", "peak_mb", "mass_3_4", "rhat"):
        vals = [float(r[k]) for r in rows if r.get(k) is not None and np.isfinite(float(r[k]))]
        if vals:
            out[k] = float(np.mean(vals))
    ex = [bool(r["exact"]) for r in rows if r.get("exact") is not None]
    if ex:
        out["exact"] = float(np.mean(ex))
    return out


def _scene_rows(ctx: Context, dataset: str, scenes: list[tuple[int, Trajectories]], methods: tuple[str, ...]
                ) -> Iterator[dict[str, Any]]:
    available = set(sf.available_methods())
    for occluded in (False, True):
        for method in methods:
            if method not in available:
                continue
            rows = []
            for seed, traj in scenes:
                data, hidden = (sf.synthetic.occlude(traj, seed=seed) if occluded else (traj, None))
                skel, timing = _fit(method, data, seed, ctx)
                row: dict[str, Any] = {**_scores(skel, traj), **timing}
                if occluded:
                    row["rmse"] = imputation_rmse(skel.impute(data), traj.xy, hidden)
                if method == "mcmc":
                    post = {int(k): v for k, v in skel.info["n_sticks_posterior"].items()}
                    row["mass_3_4"] = post.get(3, 0.0) + post.get(4, 0.0)
                    row["rhat"] = skel.info["rhat"]["log_joint"]
                rows.append(row)
            mean = _mean_rows(rows)
            notes = f"{len(scenes)} scenes; exact = share with the true structure"
            if method == "mcmc" and dataset.startswith("arm"):
                notes += f"; posterior mass on 3-4 sticks {mean.pop('mass_3_4', float('nan')):.2f}"
            else:
                mean.pop("mass_3_4", None)
            if "rhat" in mean:
                notes += f"; log-joint R-hat {mean.pop('rhat'):.3f}"
            yield {"suite": "mcmc", "dataset": dataset + (" occluded" if occluded else ""), "method": method,
                   **mean, "notes": notes}


def case_arm(ctx: Context) -> Iterator[dict[str, Any]]:
    seeds = range(ctx.seed, ctx.seed + (5 if ctx.full else 2))
    scenes = [(s, sf.synthetic.arm(seed=s)) for s in seeds]
    yield from _scene_rows(ctx, "arm 32x33", scenes, ("mcmc",))


def case_random_planar(ctx: Context) -> Iterator[dict[str, Any]]:
    n = 8 if ctx.full else 4
    frames = 120 if ctx.full else 60
    scenes = [(ctx.seed + k, sf.synthetic.random_figure(n_sticks=3 + k % 4, frames=frames, planar=True,
                                                         seed=ctx.seed + k)) for k in range(n)]
    yield from _scene_rows(ctx, f"random planar 3-6 sticks x{frames}", scenes, ("mcmc", "em"))


def _giraffe(seed: int) -> Trajectories:
    return sf.synthetic.random_figure(n_sticks=8, frames=30, planar=True, seed=seed, points_per_stick=(7, 8))


def _walker_sized(seed: int) -> Trajectories:
    return sf.synthetic.random_figure(n_sticks=10, frames=35, planar=True, seed=seed, points_per_stick=4)


def case_giraffe(ctx: Context) -> Iterator[dict[str, Any]]:
    seeds = range(ctx.seed, ctx.seed + (5 if ctx.full else 1))
    yield from _scene_rows(ctx, "planar giraffe-sized 8 sticks ~58x30", [(s, _giraffe(s)) for s in seeds],
                           ("mcmc", "em"))


def case_walker_sized(ctx: Context) -> Iterator[dict[str, Any]]:
    seeds = range(ctx.seed, ctx.seed + (5 if ctx.full else 1))
    yield from _scene_rows(ctx, "planar walker-sized 10 sticks 40x35", [(s, _walker_sized(s)) for s in seeds],
                           ("mcmc", "em"))


def case_walker_projected(ctx: Context) -> Iterator[dict[str, Any]]:
    seeds = range(ctx.seed, ctx.seed + (3 if ctx.full else 1))
    yield from _scene_rows(ctx, "walker 3D side view 44x35", [(s, sf.synthetic.walker(seed=s)) for s in seeds],
                           ("mcmc",))


def case_speed(ctx: Context) -> Iterator[dict[str, Any]]:
    from stickfigure.models.mcmc.data import normalise, root_precision
    from stickfigure.models.mcmc.kernels import SweepConfig
    from stickfigure.models.mcmc.model import Hyper
    from stickfigure.models.mcmc.sampler import ChainSettings, run_chain

    traj = _giraffe(ctx.seed)
    z, _, _, noise = normalise(traj.xy)
    hyper = Hyper(root_precision=root_precision(z), b_sx=10.0 * max(noise, 0.003) ** 2)
    n = 1000 if ctx.full else 200
    settings = ChainSettings(n_sweeps=n, burn_in=n // 2, thin=2, init_clusters=1)
    # Timed without the runner's tracemalloc, which slows this many-small-arrays
    # workload about threefold; CPU time of this process (one BLAS thread), so other
    # load on the machine counts as little as possible.
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        c0, t0 = time.process_time(), time.perf_counter()
        out = run_chain(z, hyper, SweepConfig(), settings, ctx.seed)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    per_1000 = cpu * 1000.0 / n
    yield {"suite": "mcmc", "dataset": f"planar giraffe-sized {traj.n_points}x{traj.n_frames}", "method": "mcmc",
           "time_s": per_1000, "time_ratio": per_1000 / ctx.reference_s,
           "notes": f"CPU seconds per 1000 sweeps, one chain, one process, one thread ({n} sweeps run; final "
                    f"sticks {int(out['trace_n_sticks'][-1])}; {wall:.1f} s wall)"}


CASES = [
    Case("mcmc-arm", case_arm),
    Case("mcmc-random-planar", case_random_planar),
    Case("mcmc-giraffe-sized", case_giraffe),
    Case("mcmc-walker-sized", case_walker_sized),
    Case("mcmc-walker-projected", case_walker_projected),
    Case("mcmc-speed", case_speed),
]
