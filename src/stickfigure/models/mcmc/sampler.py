"""Running Markov chains: burn-in, thinning, parallel chains, collected samples.

Each chain gets its own :class:`numpy.random.Generator` from a spawned
:class:`numpy.random.SeedSequence`, so results do not depend on how the chains
are spread over processes. With ``n_jobs > 1`` the chains run in separate
processes (:class:`concurrent.futures.ProcessPoolExecutor`), each with its own
tqdm progress bar.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..._threads import available_cpus
from .data import initial_state, rigid_imputation
from .kernels import MoveStats, SweepConfig, polish_tree, sweep, update_kappa_nd
from .model import Hyper, y_posterior
from .state import Data, State, log_joint

__all__ = ["ChainSettings", "run_chain", "run_chains", "stack_draws"]


@dataclass(frozen=True)
class ChainSettings:
    """Length of a chain and how it is started.

    Attributes
    ----------
    n_sweeps : int
        Sweeps in total, burn-in included.
    burn_in : int
        Sweeps discarded at the start.
    thin : int
        Keep every ``thin``-th sweep after burn-in.
    init_clusters : int
        Number of k-means clusters of the starting state (0: one per ``init_size`` points).
    init_size : int
    anneal : float
        Fraction of the burn-in spent in annealed starts (0: no annealing).
        In each start the joint ties are loosened (:func:`_tempered_sweep`),
        their strength rising from ``beta0`` to 1 over 80% of the start; the
        rest of the start samples the model itself. Burn-in draws are
        discarded; afterwards every kernel samples the model itself.
    beta0 : float
    n_starts : int
        Annealed starts in the burn-in, each from a fresh starting state; the
        chain goes on from the one whose log-joint over its last sweeps is
        highest (see :func:`run_chain`).
    polish : bool
        At the end of each start's annealing, a greedy search over trees for
        the partition reached (:func:`.kernels.polish_tree`).
    """

    n_sweeps: int = 600
    burn_in: int = 300
    thin: int = 2
    init_clusters: int = 0
    init_size: int = 4
    anneal: float = 0.8
    beta0: float = 0.01
    n_starts: int = 5
    polish: bool = True


def _record(st: State, data: Data) -> dict[str, Any]:
    c = st.c
    ymean, _, _ = y_posterior(data.x, st.theta[c], st.T[c], st.s_x[c], st.s_yh[c], st.s_yv[c])
    pred = np.exp(1j * st.theta[c]) * ymean[:, None] + st.T[c]
    return {"c": c.copy(), "parent": st.parent.copy(), "theta": st.theta.copy(), "T": st.T.copy(),
            "prec": st.precisions(), "y": ymean, "pred": pred}


def _tempered_sweep(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                    beta: float) -> State:
    """A sweep of the model whose joint ties are loosened by ``beta`` (burn-in only).

    The tempered model has ``s_T -> beta s_T`` (a Gamma(a_sT, b_sT / beta) prior, so
    it is a proper model whose state maps one-to-one onto the real one),
    ``kappa -> beta kappa`` and a weaker root tie. With loose joints a stick's
    parameters follow its own points instead of contorting to meet its
    neighbours, so the structure moves can rearrange the tree; as ``beta`` rises
    to 1 the joints tighten and the tree in which they fit wins.
    """
    st.s_T = st.s_T * beta
    tempered = replace(hyper, kappa_rho=hyper.kappa_rho * beta, kappa_nd=hyper.kappa_nd * beta,
                       root_precision=hyper.root_precision * beta, b_sT=hyper.b_sT / beta)
    st = sweep(st, data, tempered, rng, cfg)
    st.s_T = st.s_T / beta
    return st


def _start_lengths(settings: ChainSettings) -> list[int]:
    """Sweeps of each annealed start (their sum is at most the burn-in)."""
    total = int(settings.anneal * settings.burn_in)
    n = max(1, int(settings.n_starts))
    if total < 2 * n:  # too short to split: one start (or none)
        return [total] if total > 0 else []
    return [total // n] * n


def run_chain(z: np.ndarray, hyper: Hyper, cfg: SweepConfig, settings: ChainSettings,
              seed: np.random.SeedSequence | int, chain_id: int = 0, progress: bool = False,
              init: State | None = None) -> dict[str, Any]:
    """Run one chain on model-coordinate data.

    Burn-in (discarded): ``settings.n_starts`` annealed starts, each from a fresh
    starting state (``init`` or k-means clusters, the imputation of missing
    entries reset), with the joint ties tightening from ``beta0`` to 1 over 80%
    of the start and the model itself for the rest. The chain goes on from the
    start whose observed-data log-joint, averaged over its last sweeps (a fifth
    of the start, at least 3), is highest, and samples the model itself for the
    rest of the burn-in and after it. This is a way of *starting* the chain:
    a start can end in a tree that no single move can leave (a stick hung at
    the wrong end of its neighbour and contorted to meet it, 100+ nats below
    the right tree, see docs/mcmc.md); several starts make that far less likely
    for the state the chain goes on from. Every kept draw comes from the exact
    kernels, and each chain chooses among its own starts only, so the chains
    stay independent and R-hat still compares independent runs.

    Parameters
    ----------
    z : complex ndarray, shape (I, F)
        Trajectories in model coordinates, NaN where missing.
    hyper, cfg, settings
        Model, sweep and chain settings.
    seed : SeedSequence or int
    chain_id : int
        Position of the progress bar.
    init : State, optional
        Starting state (else k-means clusters under the root).

    Returns
    -------
    dict
        ``trace_log_joint``, ``trace_n_sticks``, ``trace_lambda``, ``trace_kappa_nd`` (every sweep, observed-data
        log-joint; the burn-in's starts one after the other), and the kept draws: ``c`` (D, I),
        ``parent`` (D, Kmax; -2 pads), ``theta`` (D, Kmax, F), ``T`` (D, Kmax, F) complex,
        ``prec`` (D, Kmax, 4), ``y`` (D, I) complex (posterior mean local positions given the
        draw), ``log_joint``, ``n_sticks``, ``lam``, ``kappa_nd`` (D,); ``pred_mean`` (I, F) complex, the
        posterior mean prediction of every entry; ``acceptance`` (dict); ``start_scores`` (the
        score of every annealed start) and ``start_chosen``; ``final_state``.
    """
    rng = np.random.default_rng(seed)
    observed = ~np.isnan(z)
    I = z.shape[0]

    def fresh() -> tuple[State, Data]:
        data = Data(x=rigid_imputation(z), observed=observed)
        if init is None:
            k0 = settings.init_clusters or max(1, int(round(I / settings.init_size)))
            return initial_state(data, hyper, rng, k0), data
        return init.copy(), data

    stats = MoveStats()
    n = int(settings.n_sweeps)
    tr_lj = np.empty(n)
    tr_k = np.empty(n, np.int64)
    tr_lam = np.empty(n)
    draws: list[dict[str, Any]] = []
    pred_sum = np.zeros(z.shape, complex)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=f"chain {chain_id}", position=chain_id, leave=True, mininterval=0.5)

    tr_kappa = np.empty(n)

    def record(s: int, st: State, data: Data, hy: Hyper) -> None:
        tr_lj[s] = log_joint(st, data, hy, observed=True)
        tr_k[s] = st.K
        tr_lam[s] = st.lam
        tr_kappa[s] = hy.kappa_nd
        if bar is not None:
            bar.update(1)
            if s % 20 == 0:
                bar.set_postfix(K=st.K, logp=f"{tr_lj[s]:.1f}", refresh=False)

    s = 0
    scores: list[float] = []
    best: tuple[float, State, Data, Hyper] | None = None

    def model_sweep(st: State, data: Data, hy: Hyper, stats: MoveStats | None = None) -> tuple[State, Hyper]:
        st = sweep(st, data, hy, rng, cfg, stats)
        if hy.update_kappa_nd:
            hy = update_kappa_nd(st, hy, rng)
        return st, hy

    try:
        for length in _start_lengths(settings):
            st, data = fresh()
            hy = hyper
            n_anneal = max(1, int(0.8 * length))
            for t in range(length):
                beta = settings.beta0 + (1.0 - settings.beta0) * t / n_anneal if t < n_anneal else 1.0
                if t == n_anneal and settings.polish and cfg.structure:
                    st = polish_tree(st, data, hy, rng, cfg)
                if beta < 1.0:
                    st = _tempered_sweep(st, data, hy, rng, cfg, beta)
                else:
                    st, hy = model_sweep(st, data, hy)
                record(s, st, data, hy)
                s += 1
            m = max(3, length // 5)
            score = float(np.mean(tr_lj[s - min(m, length):s]))
            scores.append(score)
            if best is None or score > best[0]:
                best = (score, st, data, hy)
        if best is None:
            st, data = fresh()
            hy = hyper
        else:
            _, st, data, hy = best
        for s in range(s, n):
            st, hy = model_sweep(st, data, hy, stats)
            record(s, st, data, hy)
            if s >= settings.burn_in and (s - settings.burn_in) % settings.thin == 0:
                rec = _record(st, data)
                rec["log_joint"], rec["n_sticks"], rec["lam"] = tr_lj[s], st.K, st.lam
                rec["kappa_nd"] = hy.kappa_nd
                pred_sum += rec.pop("pred")
                draws.append(rec)
    finally:
        if bar is not None:
            bar.close()
    out = stack_draws(draws, z.shape[1])
    out.update(trace_log_joint=tr_lj, trace_n_sticks=tr_k, trace_lambda=tr_lam, trace_kappa_nd=tr_kappa,
               pred_mean=pred_sum / max(len(draws), 1), acceptance=stats.rates(), final_state=st,
               start_scores=np.array(scores), start_chosen=int(np.argmax(scores)) if scores else -1)
    return out


def stack_draws(draws: list[dict[str, Any]], F: int) -> dict[str, np.ndarray]:
    """Pad per-draw arrays (whose node count varies) to common shapes."""
    D = len(draws)
    Kmax = max((d["parent"].shape[0] for d in draws), default=0)
    I = draws[0]["c"].shape[0] if D else 0
    out = {
        "c": np.zeros((D, I), np.int64),
        "parent": np.full((D, Kmax), -2, np.int64),
        "theta": np.zeros((D, Kmax, F)),
        "T": np.zeros((D, Kmax, F), complex),
        "prec": np.ones((D, Kmax, 4)),
        "y": np.zeros((D, I), complex),
        "log_joint": np.array([d["log_joint"] for d in draws], float),
        "n_sticks": np.array([d["n_sticks"] for d in draws], np.int64),
        "lam": np.array([d["lam"] for d in draws], float),
        "kappa_nd": np.array([d.get("kappa_nd", np.nan) for d in draws], float),
    }
    for t, d in enumerate(draws):
        K = d["parent"].shape[0]
        out["c"][t] = d["c"]
        out["parent"][t, :K] = d["parent"]
        out["theta"][t, :K] = d["theta"]
        out["T"][t, :K] = d["T"]
        out["prec"][t, :K] = d["prec"]
        out["y"][t] = d["y"]
    return out


def _chain_job(args: tuple) -> dict[str, Any]:
    return run_chain(*args)


def run_chains(z: np.ndarray, hyper: Hyper, cfg: SweepConfig, settings: ChainSettings, n_chains: int,
               rng: np.random.Generator, n_jobs: int | None = None, progress: bool = False) -> list[dict[str, Any]]:
    """Run ``n_chains`` independent chains, in parallel processes when ``n_jobs`` > 1.

    Parameters
    ----------
    n_jobs : int, optional
        Worker processes; None means ``min(n_chains, CPUs this process may use)``, 1 runs in this process.
    """
    seeds = np.random.SeedSequence(int(rng.integers(2**63 - 1))).spawn(n_chains)
    jobs = [(z, hyper, cfg, settings, seeds[c], c, progress) for c in range(n_chains)]
    if n_jobs is None:
        n_jobs = min(n_chains, available_cpus())
    n_jobs = max(1, min(int(n_jobs), n_chains))
    if n_jobs == 1:
        return [_chain_job(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=n_jobs) as ex:
        return list(ex.map(_chain_job, jobs))
