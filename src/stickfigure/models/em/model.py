"""State of the Ross-Tarlow-Zemel stick model and its objective (the negative free energy).

Notation (all positions in *normalised* units, see :func:`normalise`):

=============  =====================  ================================================
symbol         array                  meaning
=============  =====================  ================================================
w_pf           ``obs.w`` (P, F, D)    observed point p in frame f (0 where missing)
o_pf           ``obs.mask`` (P, F)    1 where observed
r_p            ``labels`` (P,)        stick of point p (the hard assignment R)
l_p            ``local`` (P, 3)       local coordinates of point p on its stick (L)
k_i            ``ends`` (ES, 3)       local coordinates of endpoint i (K); stick s owns
                                      endpoints Es .. Es+E-1 (E = 2 in the paper)
R_sf, t_sf     ``rot`` (S, F, D, 3),  motion M_sf = [R_sf t_sf], R with orthonormal rows
               ``trans`` (S, F, D)
g_i            ``vertex_of`` (ES,)    vertex of endpoint i (the assignment G)
mu(e), tau(e)  ``mu_e`` (ES, F, D),   Gaussian posterior of the endpoint positions
               ``tau_e`` (ES,)        (isotropic precision; it does not depend on f)
mu(v), tau(v)  ``mu_v`` (J, F, D),    Gaussian posterior of the vertex positions
               ``tau_v`` (J, F)
alpha, beta    (J,)                   Gamma posterior of the vertex precisions phi_j
tau_w          float                  observation precision
tau_m          float                  endpoint-to-stick precision
tau_t          float                  temporal smoothness precision of the vertices
=============  =====================  ================================================

A block of the model can be optimised on its own (merge scoring, see
``structure.py``): its vertices may then carry *ghost* endpoints, endpoints of
sticks outside the block whose posterior is held fixed. They enter the vertex
and precision updates through four sufficient statistics (``Ghosts``).

The objective (eq. 4 of the paper) is written out term by term in
:func:`objective_terms`; docs/em.md has the derivation.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Iterator

import numpy as np
from scipy import sparse
from scipy.special import digamma, gammaln

from . import _point_kernels as _pk

__all__ = ["Observations", "Priors", "Ghosts", "StickState", "Design", "normalise", "objective_terms",
           "objective", "structure_log_prior"]

LOG2PI = float(np.log(2.0 * np.pi))


@dataclass
class Observations:
    """Observed trajectories in normalised units.

    Attributes
    ----------
    w : ndarray, shape (P, F, D)
        Positions, 0 where missing.
    mask : ndarray, shape (P, F)
        1.0 where observed, 0.0 where missing.
    filled : ndarray, shape (P, F, D), or None
        A completion of the trajectories (normalised units, no gaps) that starts the
        per-stick SfM of sparse sticks (:func:`.initialise.stick_sfm`); None: their
        gaps are interpolated in time there. The EM itself never reads it.
    """

    w: np.ndarray
    mask: np.ndarray
    filled: np.ndarray | None = None

    def __post_init__(self) -> None:
        # C-ordered float64, as the compiled loops take them (._point_kernels): a strided view
        # (a subset of frames picked by an index array is one) would be copied on every call.
        self.w = np.ascontiguousarray(self.w, dtype=float)
        self.mask = np.ascontiguousarray(self.mask, dtype=float)

    @property
    def n_points(self) -> int:
        return int(self.w.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.w.shape[1])

    @property
    def n_dims(self) -> int:
        return int(self.w.shape[2])

    def take(self, points: np.ndarray) -> "Observations":
        return Observations(self.w[points], self.mask[points],
                            None if self.filled is None else self.filled[points])

    def take_frames(self, frames: np.ndarray) -> "Observations":
        return Observations(self.w[:, frames], self.mask[:, frames],
                            None if self.filled is None else self.filled[:, frames])


def normalise(xy: np.ndarray) -> tuple[Observations, np.ndarray, float]:
    """Centre and scale trajectories so that priors are unit-free.

    Parameters
    ----------
    xy : ndarray, shape (P, F, D), NaN where missing

    Returns
    -------
    obs : Observations
        ``(xy - centre) / scale`` with missing entries set to 0.
    centre : ndarray, shape (D,)
        Mean of the observed positions.
    scale : float
        Root-mean-square distance of the observed positions from ``centre``.
    """
    mask = ~np.isnan(xy[..., 0])
    vals = xy[mask]
    centre = vals.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((vals - centre) ** 2, axis=1))))
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    w = np.where(mask[..., None], (xy - centre) / scale, 0.0)
    return Observations(w=w, mask=mask.astype(float)), centre, scale


@dataclass(frozen=True)
class Priors:
    """Fixed hyper-parameters (normalised units).

    Attributes
    ----------
    tau_p : float
        Precision of the zero-mean Gaussian prior on local coordinates L and K.
    alpha0, beta0 : float
        Shape and rate of the Gamma prior on every vertex precision phi_j.
    max_precision : float
        Upper bound on tau_w and tau_t (the paper's "thresholds on Gaussian
        variances"), and ``1 / max_precision`` the least noise variance the stick
        checks assume (:func:`.refine.noise_variance`). The default 1e6 (a noise
        std of at least 1e-3 of the RMS spread) is a resolution: misfits below it
        are not evidence of structure. On noiseless data the residual is what the
        truncated EM left; with the former 1e10 it was read as articulation and
        3 of 4 noiseless random figures came out with 8-13 sticks for 5.
    max_tau_m_ratio : float
        Upper bound on ``tau_m / tau_w``. The two Gaussians on an endpoint (about
        its stick, precision tau_m, and about its vertex, phi_j) act in series, so
        the objective keeps creeping up as tau_m grows without bound (towards
        endpoints rigidly fixed on their sticks); the bound stops that drift so
        that EM runs converge (endpoint play
        with the default: at least 0.3 times the observation noise).
    """

    tau_p: float = 25.0
    alpha0: float = 1.0
    beta0: float = 1e-3
    max_precision: float = 1e6
    max_tau_m_ratio: float = 10.0


@dataclass
class Ghosts:
    """Fixed endpoints (of sticks outside a block) attached to the block's vertices.

    Attributes
    ----------
    n : ndarray, shape (J,)
        Number of ghost endpoints on each vertex.
    sum : ndarray, shape (J, F, D)
        Sum of their posterior means.
    sq : ndarray, shape (J, F)
        Sum of the squared norms of their means.
    var : ndarray, shape (J, F)
        Sum of ``D / tau(e)`` (the trace of their posterior covariance).
    """

    n: np.ndarray
    sum: np.ndarray
    sq: np.ndarray
    var: np.ndarray

    @staticmethod
    def empty(J: int, F: int, D: int) -> "Ghosts":
        return Ghosts(np.zeros(J), np.zeros((J, F, D)), np.zeros((J, F)), np.zeros((J, F)))

    def take(self, vertices: np.ndarray) -> "Ghosts":
        """The ghosts of ``vertices`` (indices or a mask over the vertices), in that order."""
        return Ghosts(self.n[vertices], self.sum[vertices], self.sq[vertices], self.var[vertices])

    def grown(self, k: int) -> "Ghosts":
        """These ghosts and ``k`` new vertices without any."""
        _, F, D = self.sum.shape
        z = Ghosts.empty(k, F, D)
        return Ghosts(np.concatenate([self.n, z.n]), np.concatenate([self.sum, z.sum]),
                      np.concatenate([self.sq, z.sq]), np.concatenate([self.var, z.var]))


@dataclass
class Design:
    """Per-stick sums over the observed entries of one assignment R.

    Built once per assignment (and data); every EM sweep then touches the points
    only through the compiled passes over the P x F entries of
    :mod:`._point_kernels`.

    Attributes
    ----------
    onehot : sparse (S, P)
        Point-to-stick incidence.
    n : ndarray (S, F)
        Visible points of each stick in each frame.
    s_w : ndarray (S, F, D)
        Sum of their positions.
    s_ww : ndarray (S,)
        Sum of their squared norms over all frames.
    """

    labels: np.ndarray
    n_sticks: int
    obs: Observations = field(repr=False)
    onehot: sparse.csr_matrix = field(repr=False)
    n: np.ndarray = field(repr=False)
    s_w: np.ndarray = field(repr=False)
    s_ww: np.ndarray = field(repr=False)

    @staticmethod
    def of(labels: np.ndarray, n_sticks: int, obs: Observations) -> "Design":
        P, F, D = obs.w.shape
        S = n_sticks
        labels = np.ascontiguousarray(labels, dtype=np.int64)
        onehot = sparse.csr_matrix((np.ones(P), (labels, np.arange(P))), shape=(S, P))
        vis = (obs.mask > 0).astype(float)
        n = np.asarray(onehot @ vis).reshape(S, F)
        s_w = np.asarray(onehot @ (obs.w * vis[..., None]).reshape(P, F * D)).reshape(S, F, D)
        ww = np.sum(obs.w * obs.w * vis[..., None], axis=(1, 2))
        s_ww = np.bincount(labels, weights=ww, minlength=S)
        return Design(labels=labels, n_sticks=S, obs=obs, onehot=onehot, n=n, s_w=s_w, s_ww=s_ww)

    @property
    def _args(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """labels, mask and w as the compiled loops take them (Observations keeps them C-ordered)."""
        return self.labels, self.obs.mask, self.obs.w

    def stick_sum(self, x: np.ndarray) -> np.ndarray:
        """Sum ``x`` (P, ...) over the points of each stick -> (S, ...)."""
        P = x.shape[0]
        out = self.onehot @ x.reshape(P, -1)
        return np.asarray(out).reshape((self.n_sticks,) + x.shape[1:])

    def point_stats(self, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per (stick, frame) sums over the visible points of ``l``, ``l l^T`` and ``w l^T``.

        Returns
        -------
        s_l : (S, F, 3), s_ll : (S, F, 3, 3), s_wl : (S, F, D, 3)
        """
        S, F, D = self.s_w.shape
        s_l, s_ll, s_wl = np.empty((S, F, 3)), np.empty((S, F, 3, 3)), np.empty((S, F, D, 3))
        _pk.point_moments(*self._args, np.ascontiguousarray(local, dtype=float), s_l, s_ll, s_wl)
        return s_l, s_ll, s_wl

    def residual_sq(self, rot: np.ndarray, trans: np.ndarray, local: np.ndarray) -> np.ndarray:
        """``sum_{p in s, f} o_pf |w_pf - R_sf l_p - t_sf|^2`` for every stick, shape (S,)."""
        out = np.empty(self.n_sticks)
        _pk.residual_sq(*self._args, np.ascontiguousarray(rot, dtype=float),
                        np.ascontiguousarray(trans, dtype=float), np.ascontiguousarray(local, dtype=float), out)
        return out

    def local_normal_equations(self, rot: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``sum_f o_pf R^T R`` (P, 3, 3) and ``sum_f o_pf R^T (w_pf - t)`` (P, 3), R and t of p's stick."""
        P = self.labels.size
        H, b = np.empty((P, 3, 3)), np.empty((P, 3))
        _pk.local_normal_equations(*self._args, np.ascontiguousarray(rot, dtype=float),
                                   np.ascontiguousarray(trans, dtype=float), H, b)
        return H, b


# The hub rule for the fit in progress (hub_endpoints).
_hub_endpoints = False


@contextmanager
def hub_endpoints(on: bool) -> Iterator[None]:
    """Inside the block (a whole fit), only the sticks with the most points may use their last endpoint.

    A fit-wide switch, like :func:`.updates.mirror_alignment`: joints are made by a
    dozen steps (merges, splits, bridges, sub-tree moves), all of which must see the
    same rule. Forked workers (:mod:`.forked`) inherit it. See
    :meth:`StickState.joint_capacity`.
    """
    global _hub_endpoints
    old = _hub_endpoints
    _hub_endpoints = bool(on)
    try:
        yield
    finally:
        _hub_endpoints = old


@dataclass
class StickState:
    """Every variable of the model (see the module docstring for the notation)."""

    labels: np.ndarray
    vertex_of: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    local: np.ndarray
    ends: np.ndarray
    mu_e: np.ndarray
    tau_e: np.ndarray
    mu_v: np.ndarray
    tau_v: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    tau_w: float
    tau_m: float
    tau_t: float
    ghosts: Ghosts | None = None
    _design: Design | None = field(default=None, repr=False)
    _quat: np.ndarray | None = field(default=None, repr=False)  # quaternions of ``rot`` (cache)
    _quat_of: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_sticks(self) -> int:
        return int(self.rot.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.mu_v.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.rot.shape[1])

    @property
    def n_dims(self) -> int:
        return int(self.rot.shape[2])

    @property
    def ends_per_stick(self) -> int:
        """E, the number of endpoints of every stick (2 in the paper)."""
        return int(self.ends.shape[0] // max(self.n_sticks, 1))

    @property
    def stick_of_end(self) -> np.ndarray:
        return np.repeat(np.arange(self.n_sticks), self.ends_per_stick)

    def design(self, obs: Observations) -> Design:
        """The sparse design of the current assignment (cached until labels or data change)."""
        d = self._design
        if d is None or d.n_sticks != self.n_sticks or d.labels is not self.labels or d.obs is not obs:
            self._design = Design.of(self.labels, self.n_sticks, obs)
        return self._design

    def stick_sizes(self) -> np.ndarray:
        """Number of points on each stick, shape (S,), int."""
        return np.bincount(self.labels, minlength=self.n_sticks)

    def vertex_counts(self) -> np.ndarray:
        """Number of (own) endpoints on each vertex, shape (J,)."""
        return np.bincount(self.vertex_of, minlength=self.n_vertices).astype(float)

    def joints_per_stick(self) -> np.ndarray:
        """Number of each stick's endpoints on a joint (a vertex shared with another stick), shape (S,).

        Merges join only different trees, so no two endpoints of a stick share a vertex
        and this is also the number of joints the stick is on.
        """
        return (self.vertex_counts() >= 2)[self.vertex_of].reshape(self.n_sticks, -1).sum(axis=1)

    def joint_capacity(self) -> np.ndarray:
        """How many joints each stick may be on, shape (S,): E, or under :func:`hub_endpoints`
        E for the sticks with the most points and E - 1 for the others."""
        cap = np.full(self.n_sticks, self.ends_per_stick)
        if _hub_endpoints and self.n_sticks > 1:
            size = self.stick_sizes()
            cap[size < size.max()] -= 1
        return cap

    def open_sticks(self) -> np.ndarray:
        """Which sticks may take another joint (fewer joints than :meth:`joint_capacity`), shape (S,)."""
        return self.joints_per_stick() < self.joint_capacity()

    def only_one_point_sticks(self, vertices: int | np.ndarray | list[int]) -> bool:
        """Whether every endpoint on ``vertices`` (one index or several, taken as one joint) is of a
        1-point stick.

        Such a joint is fixed in none of its sticks' frames: each turns freely about its
        point in every frame, so the joint can be anywhere within their reach and ties
        nothing, while a criterion still credits it as a joint (one vertex fewer).
        """
        on = np.flatnonzero(np.isin(self.vertex_of, np.atleast_1d(vertices))) // self.ends_per_stick
        return bool(on.size) and bool(np.all(self.stick_sizes()[on] == 1))

    def copy(self) -> "StickState":
        arrays = {k: getattr(self, k).copy() for k in ("labels", "vertex_of", "rot", "trans", "local", "ends",
                                                        "mu_e", "tau_e", "mu_v", "tau_v", "alpha", "beta")}
        g = self.ghosts
        ghosts = None if g is None else Ghosts(g.n.copy(), g.sum.copy(), g.sq.copy(), g.var.copy())
        return replace(self, **arrays, ghosts=ghosts, _design=None, _quat=None, _quat_of=None)

    def point_predictions(self) -> np.ndarray:
        """``R_{r_p f} l_p + t_{r_p f}``, shape (P, F, D)."""
        return np.einsum("pfdk,pk->pfd", self.rot[self.labels], self.local) + self.trans[self.labels]

    def end_predictions(self) -> np.ndarray:
        """``R_{s(i) f} k_i + t_{s(i) f}``, shape (ES, F, D)."""
        S, F, D = self.trans.shape
        E = self.ends_per_stick
        # One (F D, 3) x (3, E) product per stick (batched 3-vectors through matmul are slower).
        pred = np.matmul(self.rot.reshape(S, F * D, 3), np.swapaxes(self.ends.reshape(S, E, 3), 1, 2))
        return (np.swapaxes(pred, 1, 2).reshape(S, E, F, D) + self.trans[:, None]).reshape(S * E, F, D)


def chain_degree(F: int) -> np.ndarray:
    """Number of temporal neighbours of each frame (the paper's 2^h(f)), shape (F,)."""
    c = np.full(F, 2.0)
    c[0] = c[-1] = 1.0
    return c


def objective_terms(state: StickState, obs: Observations, priors: Priors) -> tuple[np.ndarray, np.ndarray]:
    """The objective split into per-stick and per-vertex parts.

    ``objective = per_stick.sum() + per_vertex.sum() + structure_log_prior``.
    Every term that involves a stick's points, motions, local coordinates or
    endpoint posteriors is in ``per_stick``; every term that involves a vertex's
    posterior, its precision phi_j or the coupling of endpoints (own or ghost)
    to it is in ``per_vertex``. A block's objective is therefore the sum of its
    sticks' and vertices' parts, which is what merge scoring compares.

    Terms (E = expectation under Q; D the dimension; a_j = alpha_j / beta_j)::

      points     sum_{p,f} o_pf [D/2 log(tau_w / 2pi) - tau_w/2 |w_pf - R l_p - t|^2]
      L, K prior sum 3/2 log(tau_p / 2pi) - tau_p/2 |l|^2     (each point and endpoint)
      e | stick  sum_{i,f} D/2 log(tau_m / 2pi) - tau_m/2 (|mu(e) - R k_i - t|^2 + D / tau(e))
      H[e]       sum_{i,f} D/2 (1 + log 2pi - log tau(e))
      e | v      sum_{i,f} D/2 (E log phi - log 2pi) - a/2 (|mu(e) - mu(v)|^2 + D/tau(e) + D/tau(v))
      v chain    sum_{j, f>1} D/2 log(tau_t / 2pi) - tau_t/2 (|mu(v_f) - mu(v_f-1)|^2 + D/tau(v_f) + D/tau(v_f-1))
      H[v]       sum_{j,f} D/2 (1 + log 2pi - log tau(v))
      phi        E log Gamma(phi | alpha0, beta0) + H[Gamma(alpha, beta)]

    with ``E log phi = digamma(alpha) - log beta``.

    Returns
    -------
    per_stick : ndarray, shape (S,)
    per_vertex : ndarray, shape (J,)
    """
    D = state.n_dims
    F = state.n_frames
    S, J = state.n_sticks, state.n_vertices
    des = state.design(obs)
    tw, tt, tp = state.tau_w, state.tau_t, priors.tau_p

    # --- per stick: points
    sq = des.residual_sq(state.rot, state.trans, state.local)  # (S,)
    nobs = des.n.sum(axis=1)  # (S,)
    per_stick = nobs * (0.5 * D * (np.log(tw) - LOG2PI)) - 0.5 * tw * sq
    lprior = 1.5 * (np.log(tp) - LOG2PI) - 0.5 * tp * np.sum(state.local ** 2, axis=1)
    per_stick = per_stick + des.stick_sum(lprior)

    # --- per stick: endpoints given the stick, their prior and entropy
    per_stick = per_stick + endpoint_terms(state, priors).reshape(S, -1).sum(axis=1)

    # --- per vertex: endpoint-vertex coupling
    inv_te = 1.0 / state.tau_e
    a = state.alpha / state.beta
    elog_phi = digamma(state.alpha) - np.log(state.beta)
    g = state.vertex_of
    inv_tv = 1.0 / state.tau_v  # (J, F)
    dv = state.mu_e - state.mu_v[g]
    dsq = np.sum(dv * dv, axis=(1, 2))  # (2S,)
    # per endpoint: sum_f [|.|^2 + D/tau(e) + D/tau(v)]
    coup = dsq + F * D * inv_te + D * inv_tv[g].sum(axis=1)
    n_own = np.bincount(g, minlength=J).astype(float)
    coup_v = np.bincount(g, weights=coup, minlength=J)
    n_all = n_own.copy()
    if state.ghosts is not None:
        gh = state.ghosts
        gsq = gh.sq - 2.0 * np.sum(gh.sum * state.mu_v, axis=2) + gh.n[:, None] * np.sum(state.mu_v ** 2, axis=2)
        coup_v = coup_v + np.sum(gsq + gh.var + gh.n[:, None] * D * inv_tv, axis=1)
        n_all = n_all + gh.n
    per_vertex = n_all * F * 0.5 * D * (elog_phi - LOG2PI) - 0.5 * a * coup_v

    # --- per vertex: temporal chain and entropy
    if F > 1:
        dmu = np.diff(state.mu_v, axis=1)
        chain = np.sum(dmu * dmu, axis=(1, 2)) + D * np.sum(inv_tv[:, 1:] + inv_tv[:, :-1], axis=1)
        per_vertex = per_vertex + (F - 1) * 0.5 * D * (np.log(tt) - LOG2PI) - 0.5 * tt * chain
    per_vertex = per_vertex + 0.5 * D * np.sum(1.0 + LOG2PI - np.log(state.tau_v), axis=1)

    # --- per vertex: phi prior and entropy
    a0, b0 = priors.alpha0, priors.beta0
    al, be = state.alpha, state.beta
    e_prior = a0 * np.log(b0) - gammaln(a0) + (a0 - 1.0) * elog_phi - b0 * a
    h_gamma = al - np.log(be) + gammaln(al) + (1.0 - al) * digamma(al)
    per_vertex = per_vertex + e_prior + h_gamma
    return per_stick, per_vertex


def endpoint_terms(state: StickState, priors: Priors) -> np.ndarray:
    """Each endpoint's own terms of the objective (E S,): ``e | stick``, ``H[e]`` and its K prior.

    ``F D/2 log(tau_m / 2pi) - tau_m/2 (|mu(e) - R k - t|^2 + F D / tau(e))
    + F D/2 (1 + log 2pi - log tau(e)) + 3/2 log(tau_p / 2pi) - tau_p/2 |k|^2``
    (:func:`objective_terms` adds them to their stick's part).
    """
    D, F = state.n_dims, state.n_frames
    tm = state.tau_m
    eres = state.mu_e - state.end_predictions()
    esq = np.sum(eres * eres, axis=(1, 2))  # (ES,)
    out = F * 0.5 * D * (np.log(tm) - LOG2PI) - 0.5 * tm * (esq + F * D / state.tau_e)
    out += F * 0.5 * D * (1.0 + LOG2PI - np.log(state.tau_e))
    out += 1.5 * (np.log(priors.tau_p) - LOG2PI) - 0.5 * priors.tau_p * np.sum(state.ends ** 2, axis=1)
    return out


def free_endpoint_terms(state: StickState, obs: Observations, priors: Priors) -> float:
    """What the endpoints on no joint add to the objective: their own terms and their vertices'.

    An endpoint alone on its vertex explains no observation, yet its terms are not
    zero. Its vertex's chain has a flat start and Gaussian steps of precision
    ``tau_t``, so it contributes the log density of the endpoint's path, about
    ``(F - 1) D/2 log(tau_t / 2pi)`` less the steps' squared sizes: a smoothness
    prior on the stick's motion, counted once more for every free endpoint of the
    stick. With a flat start the chain is not a normalised density, and
    in the data's normalised units (unit RMS spread) these terms are large and
    positive: 3.5 per frame and free endpoint on a 5-stick random figure, 5-7 on
    the CMU 41-marker walk (docs/em.md section 7). Within one merge search the
    free endpoints fall by the same number at every merge, but a model with more
    sticks, or more endpoints per stick, has more of them, and gains that much
    whatever the data say. :func:`structure.bic` subtracts this sum with
    ``free_ends=False`` (the estimator's ``bic_free_ends=False``).
    """
    _, per_vertex = objective_terms(state, obs, priors)
    alone = state.vertex_counts() == 1
    if state.ghosts is not None:
        alone &= state.ghosts.n == 0
    return float(endpoint_terms(state, priors)[alone[state.vertex_of]].sum() + per_vertex[alone].sum())


def structure_log_prior(labels: np.ndarray, n_sticks: int, vertex_of: np.ndarray, n_vertices: int) -> float:
    """log P(R) + log P(G) with the multinomial weights at their ML values.

    ``c_s = n_s / P`` (points per stick) and ``d_j = n_j / ES`` (endpoints per
    vertex), so ``log P(R) = sum_s n_s log(n_s / P)`` and likewise for G.
    """
    ns = np.bincount(labels, minlength=n_sticks).astype(float)
    nj = np.bincount(vertex_of, minlength=n_vertices).astype(float)
    out = 0.0
    for n in (ns, nj):
        tot = n.sum()
        nz = n[n > 0]
        out += float(np.sum(nz * np.log(nz / tot)))
    return out


def objective(state: StickState, obs: Observations, priors: Priors) -> float:
    """The negative free energy (eq. 4) of the whole model, structure prior included."""
    ps, pv = objective_terms(state, obs, priors)
    return float(ps.sum() + pv.sum()) + structure_log_prior(state.labels, state.n_sticks, state.vertex_of,
                                                            state.n_vertices)
