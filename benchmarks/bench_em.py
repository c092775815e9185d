"""Method "em" (Ross, Tarlow & Zemel): structure, imputation, time and memory.

Cases
-----
em-structure-random3d
    Random 3D figures (``synthetic.random_figure``: 3-7 sticks, 90-180 frames,
    5-9 points per stick, 1% noise, random views), end to end: ARI,
    misclassification, edge F1, exact-structure rate (mean over figures).
em-structure-star
    Figures whose hub holds more joints than a stick has endpoints
    (``synthetic.star``: 4-5 limbs), end to end: the default (``hub_end``), three
    endpoints a stick (``hub_end=False``, the default before session 32) and
    ``spare_end`` with ``max_trees=1`` (ARI, edge F1, exact-structure rate).
em-structure-withheld
    The paper's structural robustness claim ("correctly recover the structure ...
    when up to 75% of the training observations were randomly withheld"): the
    random figures of em-structure-random3d with 75 % of their entries withheld at
    random (every point kept in at least two frames), end to end: ARI, edge F1,
    exact-structure rate.
em-structure-low-noise
    The same random figures without noise and with 0.1 % noise (mean ARI, edge F1,
    and how many sticks more than parts each one got).
em-structure-noisy
    The same random figures with 2 % and 3 % noise (of the mean stick length; 1 % of
    the figure's bounding-box diagonal is about 2 %): mean ARI, edge F1, exact-structure
    rate, and how many sticks more than parts each one got (negative: too few).
em-structure-virtual-markers
    CMU subject 131 (a walk, the BVH in the data directory) at 30 Hz with three
    noiseless virtual markers on every bone, isometric and side views: another
    subject, motion and marker placement than the CMU take.
em-imputation-synthetic
    The paper's imputation comparison (Figs. 4 and 6, bottom right) on random
    figures: learn on the first 70% of the frames, occlude the rest (a sweeping
    bar plus 5% at random, ``synthetic.occlude``), re-fit and predict the hidden
    points; RMSE of em, multibody-sfm and sfm. Three training conditions: clean,
    occluded like the test frames, and 75% of the training observations
    withheld at random (the paper's robustness claim).
em-imputation-mocap
    The same protocol on motion capture projected to 2D (isometric view): the CMU
    41-marker take and the HDM05 take from the data directory, at 30 Hz and at
    their own 120 Hz (the first 240 frames of each unless ``ctx.full``).
em-imputation-mocap-random-views
    em-imputation-mocap's protocol (30 Hz) on the takes seen from the random cameras of
    em-structure-mocap-random-views (2 a take, 6 with ``ctx.full``), one scene per camera
    with its own occlusion draw; each row counts the scenes where em is below each baseline.
    Also another subject: the CMU 41 markers placed on the CMU 131_01 walk (as in
    em-structure-cmu41-virtual). ``ctx.full`` adds the takes at their own 120 Hz.
em-imputation-mocap-perspective
    em-imputation-mocap's protocol (30 Hz) on the takes seen through a pinhole camera 4
    scene radii from the scene centre (as em-structure-mocap-perspective), em with its
    defaults and with ``impute_scale`` (each new frame's image scale measured against the
    learned shapes); with ``ctx.full`` also ``impute_scale`` on the orthographic view, where
    it has nothing to correct.
em-structure-mocap
    The CMU and HDM05 takes (isometric, at 30 Hz and at their own 120 Hz, the first
    240 frames of each unless ``ctx.full``): ARI of the sticks against the marker-set
    body segments, edges; and the same takes with the marker set's segments given as
    the sticks (joints searched), whose BIC against the found structure's shows which
    of the two the model prefers.
em-structure-mocap-views
    The issue's check on motion capture: the whole CMU and HDM05 takes at their own
    120 Hz, seen isometrically, from the side and from the front. Do the sticks follow
    body segments (coherent sticks: the marker-set segments of each stick's markers form
    one connected piece of the body) and does the tree join them as a body does
    (anatomical edges; how many trees the forest has)? The notes name the failures.
em-structure-mocap-random-views
    The same check from cameras nobody chose: 4 views of each whole take (12 with
    ``ctx.full``), azimuth uniform, elevation 0-35 degrees, drawn from the seed; a
    summary row per take counts the views whose result is a body tree (every stick
    coherent, every edge anatomical, one tree). ``--seed 1000``, ``2000`` and ``3000``
    chose em's structure rules (sessions 5-29); ``--seed 0``, ``4000`` and ``5000`` were
    held out from them (docs/em.md section 11, session 30). Judge a change on both.
em-structure-mocap-occluded
    The named views of em-structure-mocap-views with the paper's occlusion on every
    frame (``synthetic.occlude``: a sweeping bar plus 5% at random, about 12% of the
    entries hidden), two occlusion draws a view (the random views too with
    ``ctx.full``): real takes have gaps, and a structure that holds only on complete
    data is fragile. A summary row per take counts the body trees.
em-structure-cmu41-virtual
    The same check on another subject and motion: CMU 131_01 (a walk; the BVH in the data
    directory) with the CMU 41-marker set placed at its landmarks on the BVH's bones
    (``marker_set="cmu41"``: the recorded take's marker names, body segments and body tree),
    the whole take at 120 Hz, isometric, side, front and 4 random views (12 with
    ``ctx.full``). The markers are rigid on their bones, so a failure here is not skin
    motion. A summary row counts the body trees.
em-structure-cmu41-virtual-skin
    The same take and views with the markers moved as skin moves them
    (``synthetic.skin_motion``: a smooth random displacement of every coordinate over a
    12-frame kernel, each segment's amplitude matched to how much the recorded CMU 85_02
    take's markers of that segment move against each other, ``skin_sd_like``). Rigid
    markers make every spine link's small turn exact, which a recorded take's skin motion
    hides. One skin draw (two with ``ctx.full``); a summary row per draw counts the body
    trees.
em-structure-mocap-clips
    Clips, not whole takes: the CMU take and the placed 131_01 take each cut into three
    consecutive clips of a third of their frames (120 Hz; the HDM05 take, 202 frames, is
    too short for clips of 180 frames and is left out), every clip seen from the same
    2 random cameras (4 with ``ctx.full``), so that a row differs from its take's others
    by the clip alone. Each row gives the clip's articulation (the RMS distance of its 3D
    markers from their best rigid fit, in figure radii: how much the figure bends, not
    how far it goes); a summary row per take counts the body trees.
em-structure-mocap-gaps
    The random views of em-structure-mocap-random-views with 6 markers each losing one
    run of 20-60% of the frames (``synthetic.marker_gaps``, a seed a view): raw optical
    capture loses markers for seconds, longer than a gait cycle, where the bar of
    em-structure-mocap-occluded hides each marker briefly. A summary row per take
    counts the body trees.
em-structure-mocap-perspective
    The random views of em-structure-mocap-random-views through a pinhole camera 4 scene
    radii (the markers' RMS distance from their mean) from the scene centre, where the
    model's cameras are orthographic: a real camera a few metres from a walk magnifies
    the near side and the near end of the path by a fifth to a half. A summary row per
    take counts the body trees; the rows give the range of magnification.
em-structure-hopkins
    Real video feature tracks (Hopkins 155, every sequence in the data directory):
    sticks found, and how well they respect the independent motions the dataset
    labels (homogeneity: 1 when no stick mixes points of two motions; a motion
    may rightly be several sticks, so ARI against the motions is not the
    measure here, though it is reported).
em-speed
    Time and peak memory of the whole pipeline (initialisation, EM, every merge
    stage) for an excavator-sized problem (35 points x 176 frames, 5 sticks) and
    a human-sized one (53 points x 1018 frames), and the human-sized problem at
    half its frames, and the full human-sized one in one process (``n_jobs=1``:
    the second start after the first instead of beside it, and the greedy
    trials and block fits one after the other). The whole-pipeline rows are
    timed untraced; peak memory (tracemalloc, which slows them about 1.5x)
    comes from the rows with the true groups given, run in one process
    (``n_jobs=1``: tracemalloc sees this process only; memory should scale
    linearly with frames).
    ``ctx.full`` adds the human-sized run with the paper's fixed iteration counts.
em-time-spread
    The human-sized problem's time on 4 figures (8 with ``ctx.full``, figure seeds
    from the benchmark's seed on), default settings: one figure's time does not
    show the target's margin, because the search's cost grows with the small
    sticks it leaves (each a trial with its own EM run). A summary row gives the
    mean, the slowest and how many ran under 2 minutes.
em-memory
    Peak memory against frames: the human-sized figure's first 254, 509 and 1018
    frames, true groups given and every frame searched (``max_frames=None``, so
    the merge search itself runs on all frames; by default it runs on at most 400
    and only the final re-fit sees every frame, which hides the growth). Each
    row gives the peak per 1000 frames and its ratio to the shortest clip's
    (1.0 = linear in frames).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

import stickfigure as sf
from stickfigure.geometry import articulation as image_articulation
from stickfigure.metrics import score_skeleton
from stickfigure.models import get_method
from stickfigure.trajectories import Trajectories

from .run import Case, Context

BASELINES = ("em", "multibody-sfm", "sfm")


# ------------------------------------------------------------------ scoring
def _score(skel: sf.Skeleton, traj: Trajectories, *extra: str) -> dict[str, Any]:
    s = score_skeleton(skel, traj)
    return {k: s.get(k) for k in ("ari", "misclassification", "edge_f1", "exact", *extra)}


def _mean(rows: list[dict[str, Any]], keys: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k in keys:
        vals = [float(r[k]) for r in rows if r.get(k) is not None]
        if vals:
            out[k] = float(np.mean(vals))
    return out


def _random_figures(ctx: Context, n_quick: int = 8, n_full: int = 20, noise: float = 0.01
                    ) -> Iterator[tuple[int, Trajectories]]:
    for k in range(n_full if ctx.full else n_quick):
        seed = ctx.seed * 1000 + k
        rng = np.random.default_rng(20_000 + seed)
        yield seed, sf.synthetic.random_figure(n_sticks=int(rng.integers(3, 8)), frames=int(rng.integers(90, 181)),
                                               noise=noise, seed=seed, points_per_stick=(5, 9))


# ------------------------------------------------------------------ structure
def _random_structure(ctx: Context, noise: float) -> tuple[dict[str, Any], list[int]]:
    """em on the benchmark's random figures: the mean scores and, per figure, sticks more than parts."""
    rows, extra = [], []
    for seed, traj in _random_figures(ctx, noise=noise):
        skel, timing = ctx.measure(lambda: sf.fit(traj, method="em", random_state=seed))
        rows.append({**_score(skel, traj), **timing})
        extra.append(skel.n_sticks - int(traj.n_parts_true or 0))
    return _mean(rows, ("ari", "misclassification", "edge_f1", "exact", "time_s", "time_ratio", "peak_mb")), extra


def case_structure_random3d(ctx: Context) -> Iterator[dict[str, Any]]:
    mean, extra = _random_structure(ctx, 0.01)
    yield {"dataset": "random_figure 3D", "method": "em", **mean,
           "notes": f"mean of {len(extra)} figures (3-7 sticks, 90-180 frames, 5-9 pts/stick, 1% noise)"}


STAR_SETTINGS = {"default (hub_end)": {}, "hub_end=False": {"hub_end": False},
                 "spare_end, hub_end=False, max_trees=1": {"spare_end": True, "hub_end": False, "max_trees": 1}}


def case_structure_star(ctx: Context) -> Iterator[dict[str, Any]]:
    # A hub on more joints than a stick has endpoints (synthetic.star: 4 or 5 limbs, the hub
    # with the most points), which random_figure never makes: end to end, the default (one more
    # endpoint for the hub) against three endpoints a stick and the spare endpoint.
    figures = []
    for k in range(12 if ctx.full else 4):
        seed = ctx.seed * 1000 + k
        rng = np.random.default_rng(40_000 + seed)
        figures.append((seed, sf.synthetic.star(n_limbs=int(rng.integers(4, 6)), frames=int(rng.integers(90, 181)),
                                                seed=seed, hub_points=int(rng.integers(8, 13)),
                                                limb_points=int(rng.integers(4, 8)))))
    for name, kw in STAR_SETTINGS.items():
        rows = []
        for seed, traj in figures:
            skel, timing = ctx.time(lambda: sf.fit(traj, method="em", random_state=seed, **kw))
            rows.append({**_score(skel, traj), **timing})
        yield {"dataset": f"star 3D, {name}", "method": "em",
               **_mean(rows, ("ari", "edge_f1", "exact", "time_s", "time_ratio")),
               "notes": f"mean of {len(rows)} figures (a hub of 8-12 points with 4-5 limbs of 4-7, "
                        "90-180 frames, 1% noise, random views)"}


def case_structure_withheld(ctx: Context) -> Iterator[dict[str, Any]]:
    rows = []
    for seed, traj in _random_figures(ctx):
        sparse = _withhold(traj, 0.75, seed)
        skel, timing = ctx.measure(lambda: sf.fit(sparse, method="em", random_state=seed))
        rows.append({**_score(skel, traj), **timing})
    yield {"dataset": "random_figure 3D, 75% withheld", "method": "em",
           **_mean(rows, ("ari", "misclassification", "edge_f1", "exact", "time_s", "time_ratio", "peak_mb")),
           "notes": f"mean of {len(rows)} figures (those of em-structure-random3d), 75% of entries withheld at random"}


def case_structure_low_noise(ctx: Context) -> Iterator[dict[str, Any]]:
    # The same figures without noise and at 0.1 %: the residuals are then what the EM's
    # truncated optimisation leaves, and the noise bound (max_precision) decides the count.
    for noise in (0.0, 0.001):
        mean, extra = _random_structure(ctx, noise)
        yield {"dataset": f"random_figure 3D, noise {noise:g}", "method": "em", **mean,
               "notes": f"mean of {len(extra)} figures; sticks more than parts: {', '.join(map(str, extra))}"}


def case_structure_noisy(ctx: Context) -> Iterator[dict[str, Any]]:
    # "1 % noise" of the figure's bounding-box diagonal is about 2 % of a stick's length; at 3 %
    # the clustering's groups can all be too coarse (docs/em.md section 11, session 35).
    for noise in (0.02, 0.03):
        mean, extra = _random_structure(ctx, noise)
        yield {"dataset": f"random_figure 3D, noise {noise:g}", "method": "em", **mean,
               "notes": f"mean of {len(extra)} figures; sticks more than parts: {', '.join(map(str, extra))}"}


def case_structure_virtual_markers(ctx: Context) -> Iterator[dict[str, Any]]:
    # Another CMU subject and motion (131_01, a walk, 30 Hz): three noiseless virtual markers
    # rigidly on every bone of the BVH skeleton, projected isometrically and from the side.
    assert ctx.data_dir is not None
    path = Path(ctx.data_dir) / "mocap" / "131_01.bvh"
    if not path.exists():
        return
    base = sf.load(path, markers_per_bone=3, random_state=ctx.seed).subsample(4)
    for view in ("isometric", "side"):
        traj = base.project(view)
        skel, timing = ctx.time(lambda: sf.fit(traj, method="em", random_state=ctx.seed))
        yield {"dataset": f"131_01.bvh, 3 markers per bone, {view}, {traj.n_points}x{traj.n_frames}",
               "method": "em", **_score(skel, traj), **timing,
               "notes": f"{skel.n_sticks} sticks for {traj.n_parts_true} BVH parts (spine parts barely move)"}


# ----------------------------------------------------------------- imputation
PINHOLE_RADII = 4.0  # the perspective cases' camera distance, in scene radii


def _pinhole_distance(take: Trajectories, radii: float) -> float:
    """``radii`` times the 3D markers' RMS distance from their mean (the scene radius)."""
    X = take.xy.reshape(-1, 3)
    return radii * float(np.sqrt(np.nanmean(np.sum((X - np.nanmean(X, axis=0)) ** 2, axis=1))))


def _withhold(traj: Trajectories, fraction: float, seed: int) -> Trajectories:
    """Hide ``fraction`` of the observations at random, keeping every point seen at least twice."""
    rng = np.random.default_rng(seed)
    xy = traj.xy.copy()
    obs = traj.observed
    hide = obs & (rng.random(obs.shape) < fraction)
    for p in np.flatnonzero((obs & ~hide).sum(axis=1) < 2):  # a point must stay observable
        keep = rng.choice(np.flatnonzero(obs[p]), size=min(2, obs[p].sum()), replace=False)
        hide[p, keep] = False
    xy[hide] = np.nan
    return traj.with_xy(xy, allow_unobserved=False)


def _protocol(traj: Trajectories, method: str, seed: int, condition: str, fit_kw: dict[str, Any]
              ) -> tuple[float, sf.Skeleton]:
    """Held-out imputation RMSE (in the data's units) of one method."""
    train, test = traj.split(0.7)
    if condition == "train occluded":
        train, _ = sf.synthetic.occlude(train, seed=seed + 1)
        train = train.drop_unobserved() if (~train.observed.any(axis=1)).any() else train
    elif condition == "train 75% withheld":
        train = _withhold(train, 0.75, seed + 2)
    occluded, hidden = sf.synthetic.occlude(test, seed=seed)
    if train.n_points != traj.n_points:  # a point never seen in training cannot be imputed by any method
        keep = np.isin(np.arange(traj.n_points), np.flatnonzero(traj.slice(frames=slice(0, train.n_frames))
                                                                 .observed.any(axis=1)))
        occluded, hidden, test = occluded.slice(points=keep), hidden[keep], test.slice(points=keep)
    skel = sf.fit(train, method=method, random_state=seed, **fit_kw)
    filled = np.asarray(get_method(method).impute_skeleton(skel, occluded), dtype=float)
    d = filled[hidden] - test.xy[hidden]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1)))), skel


def _imputation_rows(ctx: Context, dataset: str, scenes: list[tuple[int, Trajectories]],
                     conditions: tuple[str, ...], em_kw: Callable[[Trajectories], dict[str, Any]] | None = None
                     ) -> Iterator[dict[str, Any]]:
    for condition in conditions:
        per: dict[str, list[float]] = {m: [] for m in BASELINES}
        timing_em: list[dict[str, float]] = []
        failures: dict[str, str] = {}
        for seed, traj in scenes:
            for m in BASELINES:
                kw = em_kw(traj) if (m == "em" and em_kw) else {}
                try:
                    (rmse, _), t = ctx.measure(lambda: _protocol(traj, m, seed, condition, kw))
                except Exception as exc:  # a failure is a result, not a crash of the table
                    failures[m] = f"{type(exc).__name__}: {exc}"
                    per[m].append(np.nan)
                    continue
                per[m].append(rmse)
                if m == "em":
                    timing_em.append(t)
        em, mb, s1 = (np.array(per[m]) for m in BASELINES)
        ok = np.isfinite(em) & np.isfinite(mb) & np.isfinite(s1)
        for m, vals in zip(BASELINES, (em, mb, s1)):
            row = {"dataset": f"{dataset} ({condition})", "method": m, "rmse": float(np.nanmean(vals))}
            if m == "em" and ok.any():
                row.update(_mean(timing_em, ("time_s", "time_ratio", "peak_mb")))
                row["notes"] = (f"{len(scenes)} scenes; em below multibody-sfm on {np.mean(em[ok] < mb[ok]):.0%}, "
                                f"below sfm on {np.mean(em[ok] < s1[ok]):.0%}; mean RMSE em/multibody "
                                f"{np.mean(em[ok]) / np.mean(mb[ok]):.2f}")
            if m in failures:
                row["notes"] = (row.get("notes", "") + f" failed: {failures[m]}").strip()
            yield row


def case_imputation_synthetic(ctx: Context) -> Iterator[dict[str, Any]]:
    scenes = list(_random_figures(ctx, n_quick=6, n_full=20))
    yield from _imputation_rows(ctx, "random_figure 3D", scenes, ("train clean", "train occluded",
                                                                  "train 75% withheld"))


def _mocap_takes(ctx: Context, native: bool = False) -> list[tuple[str, Trajectories]]:
    """The mocap takes in 3D, at 30 Hz (or at their own rate with ``native``)."""
    assert ctx.data_dir is not None
    out = []
    for name in ("85_02.c3d", "HDM_dg_06-03_03_120.c3d"):
        path = Path(ctx.data_dir) / "mocap" / name
        if not path.exists():
            continue
        out.append((name, _at_rate(sf.load(path).drop_unobserved(), native)))
    return out


def _at_rate(take: Trajectories, native: bool) -> Trajectories:
    """``take`` subsampled to about 30 Hz, or as it is with ``native``."""
    return take.subsample(1 if native else max(1, int(round((take.frame_rate or 120.0) / 30.0))))


def _seen(ctx: Context, take: Trajectories, view: str | tuple[float, float],
          radii: float | None = None) -> Trajectories:
    """A 3D take projected from ``view`` (through a pinhole camera ``radii`` scene radii from the
    scene centre when given), the first 240 frames unless ``ctx.full``."""
    traj = take.project(view, distance=None if radii is None else _pinhole_distance(take, radii))
    if not ctx.full and traj.n_frames > 240:
        traj = traj.slice(frames=slice(0, 240))
    return traj


def _mocap(ctx: Context, native: bool = False, radii: float | None = None,
           view: str | tuple[float, float] = "isometric") -> list[tuple[str, Trajectories]]:
    """The mocap takes projected from ``view`` (isometric unless given), at 30 Hz (or at their own
    rate with ``native``), the first 240 frames unless ``ctx.full``; through a pinhole camera
    ``radii`` scene radii from the scene centre when given (``_pinhole_distance``)."""
    return [(name, _seen(ctx, take, view, radii)) for name, take in _mocap_takes(ctx, native)]


def case_imputation_mocap(ctx: Context) -> Iterator[dict[str, Any]]:
    for k, (name, traj) in enumerate(_mocap(ctx)):
        yield from _imputation_rows(ctx, f"{name} isometric 30 Hz", [(ctx.seed + k, traj)],
                                    ("train clean", "train occluded", "train 75% withheld"))
    # The same takes at their own 120 Hz: four times the frames for the same motion, and
    # skin-marker residuals that are smooth from frame to frame (docs/em.md section 11).
    for k, (name, traj) in enumerate(_mocap(ctx, native=True)):
        yield from _imputation_rows(ctx, f"{name} isometric {traj.frame_rate or 120:g} Hz", [(ctx.seed + k, traj)],
                                    ("train clean", "train occluded", "train 75% withheld"))


def case_imputation_mocap_random_views(ctx: Context) -> Iterator[dict[str, Any]]:
    # The imputation check runs on camera views nobody chose: each take from the random
    # cameras of em-structure-mocap-random-views, one scene per camera (its own occlusion draw).
    # With ctx.full also at the takes' own 120 Hz (em-imputation-mocap's second half).
    views = _random_views(ctx, 6 if ctx.full else 2)
    for native in (False, True) if ctx.full else (False,):
        per_take: dict[str, list[tuple[int, Trajectories]]] = {}
        takes = _mocap_takes(ctx, native)  # read once, projected from every camera
        placed = Path(ctx.data_dir) / "mocap" / "131_01.bvh"
        if placed.exists():  # another subject and motion, the same marker set
            takes.append(("131_01.bvh, CMU 41 markers placed,", _at_rate(sf.load(placed, marker_set="cmu41"),
                                                                          native)))
        for v, view in enumerate(views):
            for k, (name, take) in enumerate(takes):
                per_take.setdefault(name, []).append((ctx.seed + 100 * k + v, _seen(ctx, take, view)))
        for name, scenes in per_take.items():
            rate = f"{scenes[0][1].frame_rate or 120:g} Hz" if native else "30 Hz"
            yield from _imputation_rows(ctx, f"{name} {len(scenes)} random views {rate}", scenes,
                                        ("train clean", "train occluded", "train 75% withheld"))


def case_imputation_mocap_perspective(ctx: Context) -> Iterator[dict[str, Any]]:
    # em's cameras are orthographic; through a pinhole camera the figure's image grows and shrinks
    # as it walks, and impute_scale measures that scale in every new frame (docs/em.md section 8).
    configs: list[tuple[float | None, bool]] = [(PINHOLE_RADII, False), (PINHOLE_RADII, True)]
    if ctx.full:
        configs.append((None, True))  # what the option costs where the camera is orthographic
    for radii, scaled in configs:
        camera = "orthographic" if radii is None else f"pinhole camera at {radii:g} scene radii"
        for k, (name, traj) in enumerate(_mocap(ctx, radii=radii)):
            yield from _imputation_rows(ctx, f"{name} isometric 30 Hz, {camera}" + (", em impute_scale" if scaled
                                                                                      else ""),
                                        [(ctx.seed + k, traj)], ("train clean", "train occluded", "train 75% withheld"),
                                        em_kw=(lambda _: {"impute_scale": True}) if scaled else None)


def _selected_bic(skel: sf.Skeleton) -> float:
    return float(skel.info["stages"][skel.info["selected_stage"]]["bic"])


def case_structure_mocap(ctx: Context) -> Iterator[dict[str, Any]]:
    takes = [(name, traj, 30.0) for name, traj in _mocap(ctx)]
    takes += [(name, traj, traj.frame_rate or 120.0) for name, traj in _mocap(ctx, native=True)]
    for name, traj, rate in takes:
        if traj.labels_true is None:
            continue
        skel, timing = ctx.measure(lambda: sf.fit(traj, method="em", random_state=ctx.seed))
        # Majority-mapped edge F1 misses a coarse but right tree (a whole leg as one stick);
        # these two do not map (metrics.tree_consistency).
        s = _score(skel, traj, "coherent_sticks", "anatomical_edges")
        parts = traj.part_names or []
        named = []
        for a, b in skel.edges:
            ma = np.bincount(traj.labels_true[skel.labels == a][traj.labels_true[skel.labels == a] >= 0]).argmax()
            mb = np.bincount(traj.labels_true[skel.labels == b][traj.labels_true[skel.labels == b] >= 0]).argmax()
            named.append(f"{parts[ma] if ma < len(parts) else ma}-{parts[mb] if mb < len(parts) else mb}")
        yield {"dataset": f"{name} isometric {rate:g} Hz", "method": "em", **s, **timing,
               "notes": f"{skel.n_sticks} sticks, BIC {_selected_bic(skel):.0f}; edges (majority part): "
                        f"{', '.join(named)}"}
        # The marker set's segments as the sticks (kept: every move of the groups off), joints
        # searched as usual: how the model scores the body's own structure against the one it
        # found (docs/em.md section 11). Markers of no segment are left out of both fits.
        known = traj.labels_true >= 0
        sub, found = (traj, skel) if known.all() else (traj.slice(points=known), None)
        if found is None:
            found = sf.fit(sub, method="em", random_state=ctx.seed)
        given, timing = ctx.time(lambda: sf.fit(sub, method="em", random_state=ctx.seed, labels=sub.labels_true,
                                                refine_sticks=False, resplit=False, dissolve_points=0,
                                                resample_every=0, unpair=False, bridge_points=0,
                                                split_hubs=False))
        yield {"dataset": f"{name} isometric {rate:g} Hz, marker-set segments given", "method": "em",
               **_score(given, sub), **timing,
               "notes": f"BIC {_selected_bic(given):.0f} against {_selected_bic(found):.0f} for the structure "
                        f"found ({found.n_sticks} sticks) on the same {sub.n_points} markers: the model's score "
                        "of the body's segments"}


def _view_row(ctx: Context, name: str, take: Trajectories, view: str | tuple[float, float],
              occlusion: int | None = None, gaps: int | None = None,
              radii: float | None = None) -> dict[str, Any]:
    """em on one view of a take: scores, coherent sticks, anatomical edges, trees, failures by name.

    With ``occlusion`` (a seed) the view is occluded by ``synthetic.occlude`` before the fit;
    with ``gaps`` (a seed) ``GAP_POINTS`` of its markers lose a long run each
    (``synthetic.marker_gaps``); with ``radii`` the view is a pinhole camera that many scene
    radii (the RMS distance of the markers from their mean) from the scene centre.
    """
    from stickfigure.metrics import tree_consistency

    camera = ""
    if radii is None:
        traj = take.project(view)
    else:
        distance = _pinhole_distance(take, radii)
        traj = take.project(view, distance=distance)
        lo, hi = traj.meta["projection"]["magnification"]  # nearer and farther markers against the centre's
        camera = f", pinhole camera at {radii:g} scene radii ({distance:.0f} units; image scale {lo:.2f}-{hi:.2f})"
    data = traj if occlusion is None else sf.synthetic.occlude(traj, seed=occlusion)[0]
    if gaps is not None:
        data = sf.synthetic.marker_gaps(data, GAP_POINTS, seed=gaps)[0]
    skel, timing = ctx.time(lambda: sf.fit(data, method="em", random_state=ctx.seed))
    tc = tree_consistency(skel.labels, skel.edges, traj.labels_true, traj.edges_true, skel.n_sticks, detail=True)
    names = np.asarray(traj.names)
    wrong = ["+".join(names[skel.labels == s]) for s in tc["incoherent"]]
    wrong += ["+".join(names[skel.labels == a]) + " / " + "+".join(names[skel.labels == b])
              for a, b in tc["non_anatomical"]]
    n_trees = skel.n_sticks - len(skel.edges)
    shown = view if isinstance(view, str) else f"azimuth {view[0]:.0f}, elevation {view[1]:.0f}"
    shown += camera
    if occlusion is not None:
        shown += f", occluded (seed {occlusion}, {1 - data.observed.mean():.1%} hidden)"
    if gaps is not None:
        shown += f", {GAP_POINTS} markers with a long gap (seed {gaps}, {1 - data.observed.mean():.1%} hidden)"
    return {"dataset": f"{name} {shown} {traj.frame_rate or 120:g} Hz, {traj.n_points}x{traj.n_frames}",
            "method": "em", **_score(skel, traj), "coherent_sticks": tc["coherent_sticks"],
            "anatomical_edges": tc["anatomical_edges"], "n_trees": n_trees, **timing,
            "notes": f"{skel.n_sticks} sticks in {n_trees} tree(s); "
                     # geometry.articulation of what was fitted: how much the view shows the figure bend
                     + f"2D articulation {image_articulation(data.xy):.3f}; "
                     + ("failures: " + "; ".join(wrong) if wrong else "no incoherent stick or edge")}


def _whole_takes(ctx: Context) -> Iterator[tuple[str, Trajectories]]:
    assert ctx.data_dir is not None
    for name in ("85_02.c3d", "HDM_dg_06-03_03_120.c3d"):
        path = Path(ctx.data_dir) / "mocap" / name
        if path.exists():
            yield name, sf.load(path).drop_unobserved()


def case_structure_mocap_views(ctx: Context) -> Iterator[dict[str, Any]]:
    for name, take in _whole_takes(ctx):
        for view in ("isometric", "side", "front"):
            yield _view_row(ctx, name, take, view)


def _random_views(ctx: Context, n_views: int) -> list[tuple[float, float]]:
    # Cameras the data do not choose: azimuth uniform on the circle, elevation 0-35 degrees
    # (a camera at about body height to one looking down), drawn from the benchmark's seed.
    rng = np.random.default_rng(30_000 + ctx.seed)
    return [(float(rng.uniform(0.0, 360.0)), float(rng.uniform(0.0, 35.0))) for _ in range(n_views)]


def _body_tree_summary(name: str, what: str, rows: list[dict[str, Any]]) -> dict[str, Any]:
    body = sum(r["coherent_sticks"] == 1.0 and r["anatomical_edges"] == 1.0 and r["n_trees"] == 1
               for r in rows)
    return {"dataset": f"{name}, {what}", "method": "em",
            **_mean(rows, ("ari", "edge_f1", "coherent_sticks", "anatomical_edges", "n_trees", "time_s",
                           "time_ratio")),
            "notes": f"mean over the rows; a body tree (every stick coherent, every edge anatomical, "
                     f"one tree) in {body} of {len(rows)}"}


def case_structure_mocap_random_views(ctx: Context) -> Iterator[dict[str, Any]]:
    n_views = 12 if ctx.full else 4
    for name, take in _whole_takes(ctx):
        rows = []
        for view in _random_views(ctx, n_views):
            rows.append(_view_row(ctx, name, take, view))
            yield rows[-1]
        yield _body_tree_summary(name, f"{n_views} random views", rows)


def case_structure_mocap_occluded(ctx: Context) -> Iterator[dict[str, Any]]:
    views: list[str | tuple[float, float]] = ["isometric", "side", "front"]
    if ctx.full:
        views += _random_views(ctx, 12)
    for name, take in _whole_takes(ctx):
        rows = []
        for view in views:
            for k in range(2):  # occlusion seeds 5 and 6 past the benchmark's: draws of their own
                rows.append(_view_row(ctx, name, take, view, occlusion=ctx.seed + 5 + k))
                yield rows[-1]
        yield _body_tree_summary(name, f"{len(views)} views x 2 occlusions", rows)


GAP_POINTS = 6  # markers that lose a long run in em-structure-mocap-gaps (of 41 or 44)


def case_structure_mocap_gaps(ctx: Context) -> Iterator[dict[str, Any]]:
    n_views = 12 if ctx.full else 4
    for name, take in _whole_takes(ctx):
        rows = []
        for k, view in enumerate(_random_views(ctx, n_views)):
            rows.append(_view_row(ctx, name, take, view, gaps=50_000 + ctx.seed + k))
            yield rows[-1]
        yield _body_tree_summary(name, f"{n_views} random views, {GAP_POINTS} markers with a long gap", rows)


def case_structure_mocap_perspective(ctx: Context) -> Iterator[dict[str, Any]]:
    n_views = 12 if ctx.full else 4
    for name, take in _whole_takes(ctx):
        rows = []
        for view in _random_views(ctx, n_views):
            rows.append(_view_row(ctx, name, take, view, radii=PINHOLE_RADII))
            yield rows[-1]
        yield _body_tree_summary(name, f"{n_views} random views, pinhole camera at {PINHOLE_RADII:g} scene radii",
                                 rows)


def case_structure_cmu41_virtual(ctx: Context) -> Iterator[dict[str, Any]]:
    assert ctx.data_dir is not None
    path = Path(ctx.data_dir) / "mocap" / "131_01.bvh"
    if not path.exists():
        return
    take = sf.load(path, marker_set="cmu41")
    views: list[str | tuple[float, float]] = ["isometric", "side", "front"]
    views += _random_views(ctx, 12 if ctx.full else 4)
    rows = []
    for view in views:
        rows.append(_view_row(ctx, "131_01.bvh, CMU 41 markers placed,", take, view))
        yield rows[-1]
    yield _body_tree_summary("131_01.bvh, CMU 41 markers placed", f"{len(views)} views", rows)


#: Smoothing of the skin motion added to the placed markers, in frames at 120 Hz: the recorded
#: CMU 85_02 take's within-segment marker distances lose half their autocorrelation in 22-35
#: frames, and a Gaussian kernel of s.d. T does so at 1.67 T.
SKIN_TIMESCALE = 12.0


def _front_waist_width(take: Trajectories) -> float:
    names = list(take.names)
    return float(np.nanmean(np.linalg.norm(take.xy[names.index("LFWT")] - take.xy[names.index("RFWT")], axis=-1)))


def skin_sd_like(take: Trajectories, recorded: Trajectories) -> np.ndarray:
    """Each marker's skin-motion s.d. per coordinate for ``take``, matched segment by segment to a
    recorded take of the same marker set, shape (P,).

    On ``recorded`` the distances between two markers of one body segment vary only by skin
    motion; their median standard deviation over the segment's pairs, divided by sqrt(2) (two
    markers moving independently by ``sd`` per coordinate make a distance vary by about
    ``sd * sqrt(2)``), is the segment's ``sd``. It is scaled by the ratio of the two takes'
    front waist widths (LFWT-RFWT). A segment with one marker (a hand) gets the median over
    the segments.
    """
    from itertools import combinations

    scale = _front_waist_width(take) / _front_waist_width(recorded)
    per: dict[str, float] = {}
    for k, part in enumerate(recorded.part_names):
        idx = np.flatnonzero(recorded.labels_true == k)
        sds = [float(np.nanstd(np.linalg.norm(recorded.xy[a] - recorded.xy[b], axis=-1)))
               for a, b in combinations(idx, 2)]
        if sds:
            per[part] = float(np.median(sds)) / np.sqrt(2.0) * scale
    fallback = float(np.median(list(per.values())))
    return np.array([per.get(take.part_names[k], fallback) if k >= 0 else fallback for k in take.labels_true])


def case_structure_cmu41_virtual_skin(ctx: Context) -> Iterator[dict[str, Any]]:
    assert ctx.data_dir is not None
    path = Path(ctx.data_dir) / "mocap" / "131_01.bvh"
    recorded_path = Path(ctx.data_dir) / "mocap" / "85_02.c3d"
    if not path.exists() or not recorded_path.exists():
        return
    take = sf.load(path, marker_set="cmu41")
    sd = skin_sd_like(take, sf.load(recorded_path))
    views: list[str | tuple[float, float]] = ["isometric", "side", "front"]
    views += _random_views(ctx, 12 if ctx.full else 4)
    for draw in range(2 if ctx.full else 1):
        seed = 5 + draw + 10 * ctx.seed
        skin = sf.synthetic.skin_motion(take, sd, seed=seed, timescale=SKIN_TIMESCALE)
        name = (f"131_01.bvh, CMU 41 markers placed, skin motion as 85_02's ({sd.min():.3f}-{sd.max():.3f} units,"
                f" draw {seed})")
        rows = []
        for view in views:
            rows.append(_view_row(ctx, name + ",", skin, view))
            yield rows[-1]
        yield _body_tree_summary(name, f"{len(views)} views", rows)


def articulation(X: np.ndarray) -> float:
    """How much a 3D clip moves other than as one rigid body, in figure radii.

    Parameters
    ----------
    X : ndarray, shape (P, F, 3)
        The clip's 3D points; a point missing in any frame is left out.

    Returns
    -------
    float
        The RMS distance of the points from their mean shape rigidly aligned to each
        frame (generalised Procrustes: Kabsch rotations, three passes), divided by the
        figure's radius (the RMS distance of the mean shape's points from its centroid).
        0 for a rigid figure, whatever its path.
    """
    X = np.asarray(X, float)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"X must have shape (P, F, 3); got {X.shape}")
    X = X[np.isfinite(X).all(axis=(1, 2))]
    if X.shape[0] < 3:
        raise ValueError("articulation needs at least 3 points seen in every frame")
    Y = np.transpose(X, (1, 0, 2))  # (F, P, 3)
    Y = Y - Y.mean(axis=1, keepdims=True)

    def rotations(ref: np.ndarray) -> np.ndarray:
        # Kabsch: R[f] = U diag(1, 1, det) V^T from the SVD of ref^T Y[f]; ref @ R[f] fits frame f.
        U, _, Vt = np.linalg.svd(np.einsum("pi,fpj->fij", ref, Y))
        U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
        return U @ Vt  # (F, 3, 3)

    ref = Y[0]
    for _ in range(3):
        ref = np.einsum("fpj,fij->pi", Y, rotations(ref)) / Y.shape[0]  # frames rotated back, averaged
    fit = np.einsum("pi,fij->fpj", ref, rotations(ref))
    radius = np.sqrt(np.mean(np.sum(ref * ref, axis=1)))
    return float(np.sqrt(np.mean(np.sum((Y - fit) ** 2, axis=2))) / radius)


def case_structure_mocap_clips(ctx: Context) -> Iterator[dict[str, Any]]:
    assert ctx.data_dir is not None
    # Clips of at least 180 frames (1.5 s at 120 Hz, about a gait cycle): HDM05's 202 frames are too few.
    takes = [(name, take) for name, take in _whole_takes(ctx) if take.n_frames >= 540]
    path = Path(ctx.data_dir) / "mocap" / "131_01.bvh"
    if path.exists():
        takes.append(("131_01.bvh, CMU 41 markers placed", sf.load(path, marker_set="cmu41")))
    views = _random_views(ctx, 4 if ctx.full else 2)
    for name, take in takes:
        rows = []
        cuts = np.linspace(0, take.n_frames, 4).round().astype(int)
        for a, b in zip(cuts[:-1], cuts[1:]):
            clip = take.slice(frames=slice(int(a), int(b)))
            bend = articulation(clip.xy)
            for view in views:
                row = _view_row(ctx, f"{name}, frames {a}-{b},", clip, view)
                row["notes"] = f"articulation {bend:.3f} radii; " + row["notes"]
                rows.append(row)
                yield row
        yield _body_tree_summary(name, f"3 clips x {len(views)} random views", rows)


def case_structure_hopkins(ctx: Context) -> Iterator[dict[str, Any]]:
    from sklearn.metrics import homogeneity_score

    assert ctx.data_dir is not None
    for path in sorted((Path(ctx.data_dir) / "hopkins155").glob("*/*_truth.mat")):
        traj = sf.load(path)
        skel, timing = ctx.time(lambda: sf.fit(traj, method="em", random_state=ctx.seed))
        yield {"dataset": f"hopkins {path.parent.name} {traj.n_points}x{traj.n_frames}", "method": "em",
               "ari": _score(skel, traj)["ari"], **timing,
               "notes": f"{skel.n_sticks} sticks for {traj.n_parts_true} motions; homogeneity "
                        f"{homogeneity_score(traj.labels_true, skel.labels):.3f}"}


# ---------------------------------------------------------------------- speed
def _sized(n_points: int, frames: int, n_sticks: int, seed: int) -> Trajectories:
    """A random 3D figure with exactly ``n_points`` points (the last stick may get fewer)."""
    per = -(-n_points // n_sticks)
    traj = sf.synthetic.random_figure(n_sticks=n_sticks, frames=frames, noise=0.01, seed=seed,
                                      points_per_stick=per)
    return traj.slice(points=slice(0, n_points))


def case_speed(ctx: Context) -> Iterator[dict[str, Any]]:
    cases = [("excavator-sized 35x176, 5 sticks", _sized(35, 176, 5, ctx.seed), {}),
             ("human-sized 53x509, 11 sticks", _sized(53, 509, 11, ctx.seed), {}),
             ("human-sized 53x1018, 11 sticks", _sized(53, 1018, 11, ctx.seed), {})]
    if ctx.full:
        cases.append(("human-sized 53x1018, paper iteration counts", cases[-1][1], {"tol": 0.0}))
    for name, traj, kw in cases:
        # Timed untraced (tracemalloc slows this many-small-arrays code about 1.5x); peak memory
        # from the run with the true groups given, traced (the same arrays per frame, without
        # the time of the search).
        skel, timing = ctx.time(lambda: sf.fit(traj, method="em", random_state=ctx.seed, **kw))
        s = _score(skel, traj)
        yield {"dataset": name, "method": "em", **s, **timing,
               "notes": f"{traj.n_points} points x {traj.n_frames} frames; {len(skel.info['stages']) - 1} merges; "
                        f"{len(skel.info.get('starts', [None]))} start(s) searched; includes the initial clustering; "
                        f"untraced"}
        if traj.n_frames > 1000:
            # The same in one process: the second start (where it runs) after the first instead
            # of beside it, the trials and block fits one after the other (same skeleton; the
            # gain is time_s here over time_s above).
            skel1, timing1 = ctx.time(lambda: sf.fit(traj, method="em", random_state=ctx.seed, n_jobs=1, **kw))
            yield {"dataset": name + ", one process", "method": "em", **_score(skel1, traj), **timing1,
                   "notes": f"n_jobs=1; {timing1['time_s'] / max(timing['time_s'], 1e-9):.2f}x the default's time; "
                            f"untraced"}
        # The same without the initial clustering (given groups), to separate em's own cost.
        # One process (n_jobs=1): tracemalloc sees this process only, and with more jobs part of
        # the work (trials, half the block fits) would allocate in forked children.
        skel, timing = ctx.measure(lambda: sf.fit(traj, method="em", random_state=ctx.seed,
                                                  labels=traj.labels_true, n_jobs=1, **kw))
        yield {"dataset": name + ", groups given", "method": "em", **_score(skel, traj), **timing,
               "notes": "em alone (true groups as the start); traced (peak memory; time slowed by tracemalloc)"}


def case_time_spread(ctx: Context) -> Iterator[dict[str, Any]]:
    # One figure says little about the 2-minute target: the search's cost follows the number
    # of small sticks it leaves (each is a dissolution trial with its own EM run), and that
    # varies from figure to figure (figure seeds 0-3: 57.7-134 s, docs/em.md section 11).
    n_figures = 8 if ctx.full else 4
    rows = []
    for k in range(n_figures):
        traj = _sized(53, 1018, 11, ctx.seed + k)
        skel, timing = ctx.time(lambda: sf.fit(traj, method="em", random_state=ctx.seed))
        rows.append({"dataset": f"human-sized 53x1018, 11 sticks, figure seed {ctx.seed + k}", "method": "em",
                     **_score(skel, traj), **timing,
                     "notes": f"{skel.n_sticks} sticks; {len(skel.info['stages']) - 1} stages after the first; "
                              f"{len(skel.info.get('starts', [None]))} start(s) searched to the end; untraced"})
        yield rows[-1]
    times = np.array([r["time_s"] for r in rows])
    yield {"dataset": f"human-sized 53x1018, {n_figures} figures", "method": "em",
           **_mean(rows, ("ari", "edge_f1", "time_s", "time_ratio")),
           "notes": f"mean over the figures; slowest {times.max():.0f} s; under 120 s on "
                    f"{int(np.sum(times < 120.0))} of {n_figures}"}


def case_memory(ctx: Context) -> Iterator[dict[str, Any]]:
    full = _sized(53, 1018, 11, ctx.seed)
    first = None
    for frames in (254, 509, 1018):
        traj = full.slice(frames=slice(0, frames))
        skel, timing = ctx.measure(lambda: sf.fit(traj, method="em", random_state=ctx.seed,  # one process, traced
                                                  labels=traj.labels_true, max_frames=None, n_jobs=1))
        per = timing["peak_mb"] / frames * 1000.0
        first = per if first is None else first
        yield {"dataset": f"human-sized 53x{frames}, groups given, every frame searched", "method": "em",
               **_score(skel, traj), **timing,
               "notes": f"{per:.0f} MB per 1000 frames, {per / first:.2f}x the 254-frame clip's; traced"}


CASES = [
    Case("em-structure-random3d", case_structure_random3d),
    Case("em-structure-star", case_structure_star),
    Case("em-structure-withheld", case_structure_withheld),
    Case("em-structure-low-noise", case_structure_low_noise),
    Case("em-structure-noisy", case_structure_noisy),
    Case("em-structure-virtual-markers", case_structure_virtual_markers, needs_data=True),
    Case("em-imputation-synthetic", case_imputation_synthetic),
    Case("em-imputation-mocap", case_imputation_mocap, needs_data=True),
    Case("em-structure-mocap", case_structure_mocap, needs_data=True),
    Case("em-structure-mocap-views", case_structure_mocap_views, needs_data=True),
    Case("em-structure-mocap-random-views", case_structure_mocap_random_views, needs_data=True),
    Case("em-structure-mocap-occluded", case_structure_mocap_occluded, needs_data=True),
    Case("em-structure-cmu41-virtual", case_structure_cmu41_virtual, needs_data=True),
    Case("em-structure-cmu41-virtual-skin", case_structure_cmu41_virtual_skin, needs_data=True),
    Case("em-structure-mocap-clips", case_structure_mocap_clips, needs_data=True),
    Case("em-structure-mocap-gaps", case_structure_mocap_gaps, needs_data=True),
    Case("em-structure-mocap-perspective", case_structure_mocap_perspective, needs_data=True),
    Case("em-imputation-mocap-perspective", case_imputation_mocap_perspective, needs_data=True),
    Case("em-imputation-mocap-random-views", case_imputation_mocap_random_views, needs_data=True),
    Case("em-structure-hopkins", case_structure_hopkins, needs_data=True),
    Case("em-speed", case_speed),
    Case("em-time-spread", case_time_spread),
    Case("em-memory", case_memory),
]
