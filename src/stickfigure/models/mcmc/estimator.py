"""The "mcmc" method: posterior samples of stick figures (Meeds, Ross, Zemel & Roweis, CVPR 2008)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, ClassVar

import numpy as np

from ...skeleton import Skeleton
from ...trajectories import Trajectories
from ..base import StickEstimator, register
from .data import initial_imputation, normalise, root_precision
from .diagnostics import convergence, n_sticks_posterior
from .kernels import SweepConfig, update_rotations, update_translations_given_y
from .model import Hyper
from .sampler import ChainSettings, run_chains
from .state import Data, State

__all__ = ["StickMCMC"]

_NOISE_FLOOR = 0.003  # model units: keeps s_x finite on noise-free data (0.5% of a stick)


@register("mcmc")
class StickMCMC(StickEstimator):
    """Stick figures by MCMC under the nonparametric tree prior of Meeds et al.

    The posterior over segmentations, trees and stick motions is sampled by
    several chains (:mod:`.sampler`); the result is the most probable structure
    (the most frequent segmentation and tree among the kept draws, represented by
    its draw of highest log-joint) as a :class:`~stickfigure.skeleton.Skeleton`, with the
    posterior samples, traces and diagnostics in its ``state`` and ``info``.

    Parameters
    ----------
    n_chains : int
        Independent chains (R-hat needs at least 2).
    n_sweeps : int
        Sweeps per chain, burn-in included.
    burn_in : int
        Sweeps discarded at the start of every chain.
    thin : int
        Keep every ``thin``-th sweep after burn-in.
    n_jobs : int, optional
        Worker processes (None: one per chain up to the number of CPUs; 1: in this process).
    scale : "auto" or float
        Data units per model unit; "auto" estimates it from the size of rigid parts (see docs/mcmc.md).
    a_sx, b_sx : float, "auto"
        Gamma prior of the noise precision. The paper's ``b_sx = 1`` makes the model
        blind to residuals below about 10% of a stick; "auto" sets ``b_sx = a_sx sigma^2``
        from the estimated noise ``sigma`` (docs/mcmc.md explains why).
    a_syh, b_syh, a_syv, b_syv, a_sT, b_sT, kappa_rho, kappa_nd : float
        The other hyper-parameters, the paper's values by default.
    lam : float
        Growth parameter lambda (its starting value when ``update_lambda``).
    update_lambda : bool
        Sample lambda under a Gamma(``lambda_a``, ``lambda_b``) prior.
    lambda_a, lambda_b : float
    update_kappa_nd : bool
        Sample kappa_nd (its starting value ``kappa_nd``) under a Gamma(``kappa_nd_a``,
        ``kappa_nd_b``) prior; False keeps the paper's fixed value (docs/mcmc.md).
    kappa_nd_a, kappa_nd_b : float
    root_precision : "auto" or float
        Precision of the root's children's translations about the centre.
    n_aux : int
        Prior draws per potential parent for new-node proposals (Neal's algorithm 8).
    n_split_merge : int
        Split-merge proposals per sweep.
    n_launch : int
        Restricted Gibbs scans building a split-merge launch state.
    n_tree_moves : int
        Rounds of sub-tree, path-reversal, swap, re-hang and re-attaching split-merge moves per sweep.
    init : "single" or int
        Start every chain from one stick, or from this many k-means clusters.
    n_starts : int
        Annealed starts in each chain's burn-in; the chain goes on from the best
        of its own starts (see :func:`.sampler.run_chain` and docs/mcmc.md).
    n_impute_samples : int
        Posterior samples averaged by :meth:`impute_skeleton`.
    impute_from : {"partition", "all"}
        Which stored samples :meth:`impute_skeleton` averages: those whose
        segmentation (points into sticks, whatever the tree) is that of the most
        probable structure (default), or every stored sample (the plain posterior
        predictive). They differ only when the chains disagree on the
        segmentation (R-hat above 1.1): a chain stuck in a mode with an extra one-
        or two-point stick, whose hidden points have no rigid partner, spoils the
        average (random planar figure 0 with the occluder: that chain alone imputes
        at 0.22, the other three at 0.014; all draws 0.055). Draws on other trees
        over the same segmentation are kept: averaging over trees helps (figure 1:
        0.044 with them, 0.064 from the most probable tree's draws alone).
    impute_sweeps : int
        Conditional sweeps per sample when imputing new frames.
    max_stored : int
        Most posterior samples whose per-frame parameters are kept in the result.
    progress : bool
        A progress bar per chain.
    random_state : None, int or Generator
    """

    min_points: ClassVar[int] = 2
    min_frames: ClassVar[int] = 2

    def __init__(self, n_chains: int = 4, n_sweeps: int = 600, burn_in: int = 300, thin: int = 2,
                 n_jobs: int | None = None, scale: float | str = "auto", a_sx: float = 10.0,
                 b_sx: float | str = "auto", a_syh: float = 100.0, b_syh: float = 1.0, a_syv: float = 400.0,
                 b_syv: float = 1.0, a_sT: float = 100.0, b_sT: float = 1.0, kappa_rho: float = 1.0,
                 kappa_nd: float = 1.0, lam: float = 1.0, update_lambda: bool = True, lambda_a: float = 1.0,
                 lambda_b: float = 1.0, update_kappa_nd: bool = True, kappa_nd_a: float = 1.0,
                 kappa_nd_b: float = 0.01, root_precision: float | str = "auto", n_aux: int = 5,
                 n_split_merge: int = 5, n_launch: int = 2, n_tree_moves: int = 2, init: str | int = "single",
                 n_starts: int = 5, n_impute_samples: int = 20, impute_sweeps: int = 25, max_stored: int = 100,
                 impute_from: str = "partition", progress: bool = False, random_state: Any = None) -> None:
        self.n_chains = n_chains
        self.n_sweeps = n_sweeps
        self.burn_in = burn_in
        self.thin = thin
        self.n_jobs = n_jobs
        self.scale = scale
        self.a_sx = a_sx
        self.b_sx = b_sx
        self.a_syh = a_syh
        self.b_syh = b_syh
        self.a_syv = a_syv
        self.b_syv = b_syv
        self.a_sT = a_sT
        self.b_sT = b_sT
        self.kappa_rho = kappa_rho
        self.kappa_nd = kappa_nd
        self.lam = lam
        self.update_lambda = update_lambda
        self.lambda_a = lambda_a
        self.lambda_b = lambda_b
        self.update_kappa_nd = update_kappa_nd
        self.kappa_nd_a = kappa_nd_a
        self.kappa_nd_b = kappa_nd_b
        self.root_precision = root_precision
        self.n_aux = n_aux
        self.n_split_merge = n_split_merge
        self.n_launch = n_launch
        self.n_tree_moves = n_tree_moves
        self.init = init
        self.n_starts = n_starts
        self.n_impute_samples = n_impute_samples
        self.impute_sweeps = impute_sweeps
        self.max_stored = max_stored
        self.impute_from = impute_from
        self.progress = progress
        self.random_state = random_state

    # ------------------------------------------------------------ checking
    def _check_params(self) -> None:
        def pos_int(name: str, allow_zero: bool = False) -> int:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if allow_zero else 1):
                bound = ">= 0" if allow_zero else ">= 1"
                raise ValueError(f"{name} must be an integer {bound}, got {v!r}")
            return int(v)

        for name in ("n_chains", "n_sweeps", "thin", "n_aux", "n_impute_samples", "max_stored", "n_starts"):
            pos_int(name)
        for name in ("burn_in", "n_split_merge", "n_launch", "n_tree_moves", "impute_sweeps"):
            pos_int(name, allow_zero=True)
        if self.burn_in >= self.n_sweeps:
            raise ValueError(f"burn_in ({self.burn_in}) must be smaller than n_sweeps ({self.n_sweeps})")
        if self.n_jobs is not None:
            pos_int("n_jobs")
        for name in ("a_sx", "a_syh", "b_syh", "a_syv", "b_syv", "a_sT", "b_sT", "kappa_rho", "kappa_nd", "lam",
                     "lambda_a", "lambda_b", "kappa_nd_a", "kappa_nd_b"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        for name in ("b_sx", "root_precision", "scale"):
            v = getattr(self, name)
            if isinstance(v, str):
                if v != "auto":
                    raise ValueError(f"{name} must be 'auto' or a positive number, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be 'auto' or a positive number, got {v!r}")
        if self.impute_from not in ("partition", "all"):
            raise ValueError(f"impute_from must be 'partition' or 'all', got {self.impute_from!r}")
        if not (self.init == "single" or (isinstance(self.init, (int, np.integer)) and not isinstance(self.init, bool)
                                           and self.init >= 1)):
            raise ValueError(f"init must be 'single' or a number of clusters >= 1, got {self.init!r}")

    # ---------------------------------------------------------------- fit
    def _fit(self, traj: Trajectories, rng: np.random.Generator) -> Skeleton:
        if traj.n_dims != 2:
            raise ValueError(f"mcmc models 2D trajectories (the paper's setting), got {traj.n_dims}D data; "
                             "project them first, e.g. traj.project()")
        self._check_params()
        z, centre, scale, noise = normalise(traj.xy, self.scale)
        sigma = noise if np.isfinite(noise) else _NOISE_FLOOR
        hyper = Hyper(
            a_sx=float(self.a_sx),
            b_sx=float(self.a_sx * max(sigma, _NOISE_FLOOR) ** 2) if self.b_sx == "auto" else float(self.b_sx),
            a_syh=float(self.a_syh), b_syh=float(self.b_syh), a_syv=float(self.a_syv), b_syv=float(self.b_syv),
            a_sT=float(self.a_sT), b_sT=float(self.b_sT), kappa_rho=float(self.kappa_rho),
            kappa_nd=float(self.kappa_nd),
            root_precision=root_precision(z) if self.root_precision == "auto" else float(self.root_precision),
            lam=float(self.lam), update_lambda=bool(self.update_lambda), lambda_a=float(self.lambda_a),
            lambda_b=float(self.lambda_b), update_kappa_nd=bool(self.update_kappa_nd),
            kappa_nd_a=float(self.kappa_nd_a), kappa_nd_b=float(self.kappa_nd_b),
        )
        cfg = SweepConfig(n_aux=int(self.n_aux), n_split_merge=int(self.n_split_merge), n_launch=int(self.n_launch),
                          n_subtree=int(self.n_tree_moves))
        settings = ChainSettings(n_sweeps=int(self.n_sweeps), burn_in=int(self.burn_in), thin=int(self.thin),
                                 init_clusters=1 if self.init == "single" else int(self.init),
                                 n_starts=int(self.n_starts))
        chains = run_chains(z, hyper, cfg, settings, int(self.n_chains), rng, n_jobs=self.n_jobs,
                            progress=bool(self.progress))
        return _build_skeleton(traj, chains, hyper, centre, scale, noise, int(self.max_stored), rng)

    def fit(self, X: Trajectories | np.ndarray, y: Any = None) -> "StickMCMC":
        super().fit(X, y)
        sk = self.skeleton_
        self.samples_ = {k[len("sample_"):]: v for k, v in sk.state.items() if k.startswith("sample_")}
        self.n_sticks_posterior_ = {int(k): v for k, v in sk.info["n_sticks_posterior"].items()}
        self.map_ = dict(sk.info["map"])
        self.diagnostics_ = {"rhat": sk.info["rhat"], "ess": sk.info["ess"], "acceptance": sk.info["acceptance"]}
        return self

    # ------------------------------------------------------------- impute
    @classmethod
    def impute_skeleton(cls, skeleton: Skeleton, traj: Trajectories) -> np.ndarray:
        """Posterior-predictive mean of every entry of ``traj`` (same points, any frames).

        For each of up to ``n_impute_samples`` stored posterior samples the
        structure -- indicators, tree, precisions and the points' local
        positions (their posterior mean from the training frames) -- is kept,
        and the per-frame rotations and translations are re-inferred from the
        visible entries by a short conditional Gibbs run (von Mises rotations
        and Gaussian translations given the local positions and the visible
        entries only), started from a rigid fit; the predicted positions
        are averaged over sweeps and samples. Sticks with no visible point in a
        frame follow the tree prior: their joint sits at the parent's distal
        end and their angle follows their parent's and neighbouring frames.
        """
        if traj.n_dims != 2:
            raise ValueError(f"mcmc models 2D trajectories, got {traj.n_dims}D data")
        st_ = skeleton.state
        cx, cy, scale = (float(v) for v in st_["normalisation"])
        q = (traj.xy - np.array([cx, cy])) / scale
        z = q[..., 0] + 1j * q[..., 1]
        observed = ~np.isnan(z)
        P, F = z.shape
        hyper = Hyper(**{k: v for k, v in skeleton.info["hyper"].items()})
        if skeleton.info.get("kappa_nd_mean") is not None:  # learned: its posterior mean
            hyper = replace(hyper, kappa_nd=float(skeleton.info["kappa_nd_mean"]))
        params = skeleton.params
        n_samples = int(params.get("n_impute_samples", 20))
        n_sweeps = int(params.get("impute_sweeps", 25))
        rs = params.get("random_state")
        rng = np.random.default_rng(rs if isinstance(rs, int) else 0)
        D = st_["sample_c"].shape[0]
        pool = np.arange(D)
        if params.get("impute_from", "partition") == "partition" and "sample" in skeleton.info.get("map", {}):
            pool = _same_partition(st_["sample_c"], int(skeleton.info["map"]["sample"]))
        pick = pool[np.unique(np.linspace(0, pool.size - 1, min(n_samples, pool.size)).round().astype(int))]
        if not observed.any():
            raise ValueError("traj has no observed entry to infer the motions from")
        x0 = initial_imputation(np.where(observed, z, np.nan)) if observed.any(1).all() else None
        total = np.zeros((P, F), complex)
        count = 0
        warm = max(1, n_sweeps // 5)
        for d in pick:
            st, y = _conditional_start(st_, int(d), z, observed, hyper)
            data = Data(x=_fill(z, observed, st, y, x0), observed=observed)
            for s in range(n_sweeps):
                # Given y the missing entries drop out: only the visible ones count, so a
                # hidden stick follows its joint and its neighbouring frames.
                update_translations_given_y(st, data, y, hyper, rng, observed_only=True)
                update_rotations(st, data, y, hyper, rng, observed_only=True)
                if s >= warm or n_sweeps == 1:
                    total += np.exp(1j * st.theta[st.c]) * y[:, None] + st.T[st.c]
                    count += 1
        pred = total / max(count, 1)
        out = np.stack([pred.real, pred.imag], axis=-1) * scale + np.array([cx, cy])
        return out


# ----------------------------------------------------------------- helpers
def _fill(z: np.ndarray, observed: np.ndarray, st: State, y: np.ndarray, x0: np.ndarray | None) -> np.ndarray:
    pred = np.exp(1j * st.theta[st.c]) * y[:, None] + st.T[st.c]
    return np.where(observed, z, pred)


def _same_partition(sample_c: np.ndarray, ref: int) -> np.ndarray:
    """Indices of the stored samples (rows of ``sample_c``, (D, P)) that group the points as sample ``ref`` does."""
    def key(c: np.ndarray) -> np.ndarray:  # labels renumbered by first appearance: label-free
        _, first, inv = np.unique(c, return_index=True, return_inverse=True)
        return np.argsort(np.argsort(first))[inv]

    want = key(sample_c[ref])
    return np.array([d for d in range(sample_c.shape[0]) if np.array_equal(key(sample_c[d]), want)], dtype=np.int64)


def _circ_interp(theta: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Fill angles where ``ok`` is False by interpolating the unwrapped known ones."""
    F = theta.shape[0]
    t = np.arange(F)
    if ok.all():
        return theta
    known = np.unwrap(theta[ok])
    return np.interp(t, t[ok], known)


def _conditional_start(state: dict[str, np.ndarray], d: int, z: np.ndarray, observed: np.ndarray,
                       hyper: Hyper) -> tuple[State, np.ndarray]:
    """A stored sample's structure with per-frame parameters fitted rigidly to the visible points."""
    c = state["sample_c"][d].astype(np.int64)
    parent = state["sample_parent"][d]
    K = int((parent > -2).sum())
    parent = parent[:K].astype(np.int64)
    prec = state["sample_prec"][d, :K]
    y = state["sample_y"][d, :, 0] + 1j * state["sample_y"][d, :, 1]
    P, F = z.shape
    theta = np.zeros((K, F))
    T = np.zeros((K, F), complex)
    has_theta = np.zeros((K, F), bool)
    w = observed.astype(float)
    zz = np.where(observed, z, 0)
    for k in range(K):
        m = c == k
        wk = w[m]  # (n, F)
        nk = wk.sum(0)
        yk = y[m]
        xk = zz[m]
        ybar = np.divide((wk * yk[:, None]).sum(0), nk, out=np.zeros(F, complex), where=nk > 0)
        xbar = np.divide((wk * xk).sum(0), nk, out=np.zeros(F, complex), where=nk > 0)
        cross = (wk * (xk - xbar) * np.conj(yk[:, None] - ybar)).sum(0)
        ok = (nk >= 2) & (np.abs(cross) > 1e-12)
        theta[k] = np.angle(cross)
        has_theta[k] = ok
    order = np.argsort(np.array([_depth(parent, k) for k in range(K)]), kind="stable")
    for k in order:
        p = parent[k]
        ok = has_theta[k]
        if ok.any():
            theta[k] = _circ_interp(theta[k], ok)
        elif p >= 0:
            theta[k] = theta[p]
        m = c == k
        wk = w[m]
        nk = wk.sum(0)
        resid = (wk * (zz[m] - np.exp(1j * theta[k]) * y[m][:, None])).sum(0)
        Tk = np.divide(resid, nk, out=np.zeros(F, complex), where=nk > 0)
        seen = nk > 0
        if p >= 0:
            J = T[p] + np.exp(1j * theta[p]) * 6.0 / np.sqrt(prec[p, 1])
            Tk = np.where(seen, Tk, J)
        elif seen.any() and not seen.all():
            t = np.arange(F)
            Tk = np.interp(t, t[seen], Tk[seen].real) + 1j * np.interp(t, t[seen], Tk[seen].imag)
        T[k] = Tk
    st = State(c=c, parent=parent, theta=theta, T=T, s_x=prec[:, 0].copy(), s_yh=prec[:, 1].copy(),
               s_yv=prec[:, 2].copy(), s_T=prec[:, 3].copy(), lam=1.0)
    return st, y


def _depth(parent: np.ndarray, k: int) -> int:
    d = 0
    while parent[k] >= 0:
        k = int(parent[k])
        d += 1
    return d


def _most_probable_structure(chains: list[dict[str, Any]], lj: np.ndarray) -> tuple[int, float]:
    """The draw representing the most frequent structure, and that structure's posterior frequency.

    A structure is the label-free configuration (node sets and parent links).
    The single draw of highest log-joint is a poor guide to where the posterior
    mass is (a mode with more parameters can reach higher densities yet hold
    less mass), so we count structures over all kept draws and return the
    highest-log-joint draw among those of the most frequent one.

    Returns
    -------
    flat : int
        Index into the chains' draws laid end to end.
    frequency : float
    """
    from .prior import canonical_key

    D = lj.shape[1]
    keys = []
    for ch in chains:
        for d in range(D):
            K = int((ch["parent"][d] > -2).sum())
            keys.append(canonical_key(ch["c"][d], ch["parent"][d, :K]))
    flat_lj = lj.ravel()
    counts: dict = {}
    for t, k in enumerate(keys):
        counts[k] = counts.get(k, 0) + 1
    top = max(counts.values())
    if top == 1:  # every draw differs: fall back on the highest log-joint
        return int(np.argmax(flat_lj)), 1.0 / len(keys)
    cands = [k for k, v in counts.items() if v == top]
    best = max((t for t, k in enumerate(keys) if k in cands), key=lambda t: flat_lj[t])
    return int(best), top / len(keys)


def _build_skeleton(traj: Trajectories, chains: list[dict[str, Any]], hyper: Hyper, centre: np.ndarray,
                    scale: float, noise: float, max_stored: int, rng: np.random.Generator) -> Skeleton:
    """The most probable structure as a Skeleton, with all samples, traces and diagnostics attached."""
    P, F = traj.n_points, traj.n_frames
    C = len(chains)
    lj = np.stack([ch["log_joint"] for ch in chains])  # (C, D)
    ns = np.stack([ch["n_sticks"] for ch in chains])
    D = lj.shape[1]
    flat, freq = _most_probable_structure(chains, lj)
    cm, dm = divmod(flat, D)
    best = chains[cm]
    # Every draw's structure, and the per-frame parameters of an even subset.
    Kmax = max(ch["parent"].shape[1] for ch in chains)

    def pad(a: np.ndarray, fill: float) -> np.ndarray:
        widths = [(0, 0)] * a.ndim
        widths[1] = (0, Kmax - a.shape[1])
        return np.pad(a, widths, constant_values=fill)

    all_c = np.concatenate([ch["c"] for ch in chains])
    all_parent = np.concatenate([pad(ch["parent"], -2) for ch in chains])
    all_prec = np.concatenate([pad(ch["prec"], 1.0) for ch in chains])
    all_y = np.concatenate([ch["y"] for ch in chains])
    all_theta = np.concatenate([pad(ch["theta"], 0.0) for ch in chains])
    all_T = np.concatenate([pad(ch["T"], 0.0) for ch in chains])
    chain_of = np.repeat(np.arange(C), D)
    keep = np.unique(np.concatenate([np.linspace(0, C * D - 1, min(max_stored, C * D)).round().astype(int), [flat]]))
    k_map = int((best["parent"][dm] > -2).sum())
    c_map = best["c"][dm]
    parent_map = best["parent"][dm, :k_map]
    # Sticks numbered by their first point.
    first = np.array([np.flatnonzero(c_map == k)[0] for k in range(k_map)])
    order = np.argsort(first)
    relabel = np.empty(k_map, np.int64)
    relabel[order] = np.arange(k_map)
    labels = relabel[c_map]
    theta = best["theta"][dm, :k_map][order]
    T = best["T"][dm, :k_map][order]
    par = parent_map[order]
    par = np.where(par >= 0, relabel[np.maximum(par, 0)], -1)
    edges = [(int(par[s]), s) for s in range(k_map) if par[s] >= 0]
    cvec = centre[0] + 1j * centre[1]
    joints_c = np.stack([T[s] * scale + cvec for _, s in edges]) if edges else np.zeros((0, F), complex)
    joints = np.stack([joints_c.real, joints_c.imag], axis=-1) if edges else np.zeros((0, F, 2))
    motions = np.zeros((k_map, F, 2, 4))
    cth, sth = np.cos(theta), np.sin(theta)
    motions[:, :, 0, 0], motions[:, :, 0, 1] = cth, -sth
    motions[:, :, 1, 0], motions[:, :, 1, 1] = sth, cth
    tt = T * scale + cvec
    motions[:, :, 0, 3], motions[:, :, 1, 3] = tt.real, tt.imag
    ymap = best["y"][dm] * scale
    local = np.column_stack([ymap.real, ymap.imag, np.zeros(P)])
    conv = convergence(lj, ns)
    pred = np.mean([ch["pred_mean"] for ch in chains], axis=0) * scale + cvec
    state = {
        "normalisation": np.array([centre[0], centre[1], scale]),
        "sample_c": all_c[keep],
        "sample_parent": all_parent[keep],
        "sample_prec": all_prec[keep],
        "sample_y": np.stack([all_y[keep].real, all_y[keep].imag], axis=-1),
        "sample_theta": all_theta[keep],
        "sample_T": np.stack([all_T[keep].real, all_T[keep].imag], axis=-1),
        "sample_log_joint": lj.ravel()[keep],
        "sample_chain": chain_of[keep],
        "draws_n_sticks": ns,
        "draws_log_joint": lj,
        "trace_log_joint": np.stack([ch["trace_log_joint"] for ch in chains]),
        "trace_n_sticks": np.stack([ch["trace_n_sticks"] for ch in chains]),
        "trace_lambda": np.stack([ch["trace_lambda"] for ch in chains]),
        "trace_kappa_nd": np.stack([ch["trace_kappa_nd"] for ch in chains]),
        "predictive_mean": np.stack([pred.real, pred.imag], axis=-1),
    }
    info = {
        "n_sticks_posterior": {str(k): v for k, v in n_sticks_posterior(ns).items()},
        "rhat": conv["rhat"],
        "ess": conv["ess"],
        "acceptance": [{k: round(v, 4) for k, v in ch["acceptance"].items()} for ch in chains],
        "map": {"chain": cm, "draw": dm, "log_joint": float(lj[cm, dm]), "n_sticks": k_map,
                "sample": int(np.searchsorted(keep, flat)), "structure_frequency": freq},
        "scale": float(scale),
        "centre": [float(centre[0]), float(centre[1])],
        "noise": float(noise) if np.isfinite(noise) else None,
        "hyper": hyper.as_dict(),
        "kappa_nd_mean": (float(np.mean([ch["kappa_nd"] for ch in chains])) if hyper.update_kappa_nd else None),
        "n_draws_per_chain": int(D),
        "log_joint_units": "model coordinates (data centred and divided by scale)",
    }
    return Skeleton(method="mcmc", labels=labels, n_sticks=k_map, edges=edges, joints=joints, motions=motions,
                    local=local, log_likelihood=float(lj[cm, dm]), n_dims=2, state=state, info=info)
