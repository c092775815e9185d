"""The sampler's state (tree, indicators, node parameters) and the log-joint density.

The state holds everything the Markov chain moves except the local positions
``y_i``, which are integrated out wherever possible and drawn afresh from
their conditional whenever a kernel needs them (:func:`sample_y`), and the
complete data (observed entries plus the current imputation of the missing
ones), held in :class:`Data`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .model import (
    Hyper,
    distal_end,
    gamma_logpdf,
    marginal_loglik,
    rotation_prior_logpdf,
    sample_rotation_prior,
    translation_prior_logpdf,
    y_posterior,
)
from .prior import ancestor_matrix, depths, log_tree_prior, sample_tree_prior

__all__ = ["State", "Data", "parent_context", "node_prior_logpdf", "point_loglik", "log_joint", "sample_y",
           "sample_node_parameters", "sample_prior_state", "simulate_data"]


@dataclass
class Data:
    """Trajectories in model coordinates.

    Attributes
    ----------
    x : complex ndarray, shape (I, F)
        Observed entries and the current imputation of the missing ones.
    observed : bool ndarray, shape (I, F)

    The missing entries of ``x`` as it was given (the starting imputation, a
    fixed function of the observed data) are kept: see :attr:`x_proposal`.
    """

    x: np.ndarray
    observed: np.ndarray
    w: np.ndarray = field(init=False, repr=False)
    _x_start: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.w = self.observed.astype(float)
        self._x_start = self.x.copy()

    @property
    def x_proposal(self) -> np.ndarray:
        """What the structure moves build their data-driven proposals from, complex (I, F).

        The observed entries, and at the missing ones the starting imputation
        (not the current one). The structure moves target the posterior with the
        missing entries integrated out; a proposal that depended on their current
        values (which follow the current structure) would not leave it invariant.
        """
        if not self.has_missing:
            return self.x
        return np.where(self.observed, self.x, self._x_start)

    @property
    def n_points(self) -> int:
        return self.x.shape[0]

    @property
    def n_frames(self) -> int:
        return self.x.shape[1]

    @property
    def has_missing(self) -> bool:
        return not bool(self.observed.all())


@dataclass
class State:
    """Indicators, tree and node parameters (see :mod:`.model` for their meaning).

    Attributes
    ----------
    c : ndarray of int, shape (I,)
    parent : ndarray of int, shape (K,)
        -1 for children of the root.
    theta : ndarray, shape (K, F)
    T : complex ndarray, shape (K, F)
    s_x, s_yh, s_yv, s_T : ndarray, shape (K,)
    lam : float
    """

    c: np.ndarray
    parent: np.ndarray
    theta: np.ndarray
    T: np.ndarray
    s_x: np.ndarray
    s_yh: np.ndarray
    s_yv: np.ndarray
    s_T: np.ndarray
    lam: float

    @property
    def K(self) -> int:
        return int(self.parent.shape[0])

    def copy(self) -> "State":
        return State(self.c.copy(), self.parent.copy(), self.theta.copy(), self.T.copy(), self.s_x.copy(),
                     self.s_yh.copy(), self.s_yv.copy(), self.s_T.copy(), float(self.lam))

    def counts(self) -> np.ndarray:
        return np.bincount(self.c, minlength=self.K)

    def children(self, k: int) -> np.ndarray:
        return np.flatnonzero(self.parent == k)

    def subtree(self, k: int) -> np.ndarray:
        """Nodes of the sub-tree rooted at ``k`` (``k`` included)."""
        return np.flatnonzero(ancestor_matrix(self.parent)[:, k])

    def add_node(self, parent: int, theta: np.ndarray, T: np.ndarray, s_x: float, s_yh: float, s_yv: float,
                 s_T: float) -> int:
        """Append a node; returns its index."""
        self.parent = np.append(self.parent, parent)
        self.theta = np.vstack([self.theta, theta[None]])
        self.T = np.vstack([self.T, T[None]])
        self.s_x = np.append(self.s_x, s_x)
        self.s_yh = np.append(self.s_yh, s_yh)
        self.s_yv = np.append(self.s_yv, s_yv)
        self.s_T = np.append(self.s_T, s_T)
        return self.K - 1

    def keep_nodes(self, keep: np.ndarray) -> None:
        """Drop the nodes where ``keep`` is False (they must hold no points and no children)."""
        keep = np.asarray(keep, bool)
        if keep.all():
            return
        new_index = np.cumsum(keep) - 1
        if np.any(~keep[self.c]):
            raise RuntimeError("cannot drop a node that holds points")
        if np.any(~keep[self.parent[keep & (self.parent >= 0)]]):
            raise RuntimeError("cannot drop a node that has children")
        self.c = new_index[self.c]
        par = self.parent[keep]
        self.parent = np.where(par >= 0, new_index[np.maximum(par, 0)], -1)
        self.theta = self.theta[keep]
        self.T = self.T[keep]
        self.s_x, self.s_yh, self.s_yv, self.s_T = (a[keep] for a in (self.s_x, self.s_yh, self.s_yv, self.s_T))

    def precisions(self) -> np.ndarray:
        """(K, 4) array of s_x, s_yh, s_yv, s_T."""
        return np.column_stack([self.s_x, self.s_yh, self.s_yv, self.s_T])


def parent_context(st: State, hyper: Hyper) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every node: its parent's distal end J (K, F), child precision (K,) and angles (K, F).

    The root contributes the origin, ``hyper.root_precision`` and angle 0.
    """
    has = st.parent >= 0
    p = np.where(has, st.parent, 0)
    J = np.where(has[:, None], distal_end(st.theta[p], st.T[p], st.s_yh[p]), 0.0 + 0.0j)
    s_par = np.where(has, st.s_T[p], hyper.root_precision)
    th_par = np.where(has[:, None], st.theta[p], 0.0)
    return J, s_par, th_par


def node_prior_logpdf(st: State, hyper: Hyper) -> np.ndarray:
    """log G(phi_k | phi_parent(k)) for every node, shape (K,)."""
    J, s_par, th_par = parent_context(st, hyper)
    ab = hyper.gamma_ab
    lp = (gamma_logpdf(st.s_x, *ab[0]) + gamma_logpdf(st.s_yh, *ab[1]) + gamma_logpdf(st.s_yv, *ab[2])
          + gamma_logpdf(st.s_T, *ab[3]))
    lp = lp + rotation_prior_logpdf(st.theta, th_par, hyper.kappa_rho, hyper.kappa_nd)
    return lp + translation_prior_logpdf(st.T, J, s_par)


def point_loglik(st: State, x: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """log F(x_i | phi_{c_i}) for every point, shape (I,)."""
    c = st.c
    return marginal_loglik(x, st.theta[c], st.T[c], st.s_x[c], st.s_yh[c], st.s_yv[c],
                           None if w is None else w)


def log_joint(st: State, data: Data, hyper: Hyper, observed: bool = False) -> float:
    """log p(x, c, tree, phi) with the y_i integrated out.

    Parameters
    ----------
    observed : bool
        Use only the observed entries (the quantity reported in traces) instead
        of the complete data with the current imputation (the sampler's target).
    """
    ll = point_loglik(st, data.x, data.w if observed and data.has_missing else None).sum()
    lp = log_tree_prior(st.counts(), st.parent, st.lam) + node_prior_logpdf(st, hyper).sum()
    if hyper.update_lambda:
        lp += float(gamma_logpdf(st.lam, hyper.lambda_a, hyper.lambda_b))
    if hyper.update_kappa_nd:
        lp += float(gamma_logpdf(hyper.kappa_nd, hyper.kappa_nd_a, hyper.kappa_nd_b))
    return float(ll + lp)


def sample_y(st: State, data: Data, rng: np.random.Generator, observed_only: bool = False) -> np.ndarray:
    """Draw every point's local position from its conditional, complex shape (I,).

    With ``observed_only`` the conditional given the observed entries alone (the
    missing ones integrated out), as needed to redraw the missing entries from
    ``p(x_mis | state, x_obs)`` (:func:`.kernels.impute_missing`).
    """
    c = st.c
    w = data.w if observed_only and data.has_missing else None
    mean, vh, vv = y_posterior(data.x, st.theta[c], st.T[c], st.s_x[c], st.s_yh[c], st.s_yv[c], w)
    I = mean.shape[0]
    return mean + np.sqrt(vh) * rng.standard_normal(I) + 1j * np.sqrt(vv) * rng.standard_normal(I)


def sample_node_parameters(st: State, hyper: Hyper, rng: np.random.Generator) -> None:
    """Draw every node's parameters from G(. | parent), parents first (in place)."""
    K, F = st.theta.shape
    ab = hyper.gamma_ab
    prec = rng.gamma(ab[:, 0], 1.0 / ab[:, 1], size=(K, 4))
    st.s_x, st.s_yh, st.s_yv, st.s_T = (prec[:, r].copy() for r in range(4))
    for k in np.argsort(depths(st.parent), kind="stable"):
        p = st.parent[k]
        if p >= 0:
            th_p, J, s_par = st.theta[p], distal_end(st.theta[p], st.T[p], st.s_yh[p]), st.s_T[p]
        else:
            th_p, J, s_par = np.zeros(F), np.zeros(F, complex), hyper.root_precision
        st.theta[k] = sample_rotation_prior(th_p, hyper.kappa_rho, hyper.kappa_nd, rng)
        st.T[k] = J + (rng.standard_normal(F) + 1j * rng.standard_normal(F)) / np.sqrt(s_par)


def sample_prior_state(n_points: int, n_frames: int, hyper: Hyper, rng: np.random.Generator,
                       lam: float | None = None) -> State:
    """An exact draw of (indicators, tree, node parameters) from the prior."""
    lam = hyper.lam if lam is None else lam
    c, parent = sample_tree_prior(n_points, lam, rng)
    K = parent.shape[0]
    st = State(c=c, parent=parent, theta=np.zeros((K, n_frames)), T=np.zeros((K, n_frames), complex),
               s_x=np.ones(K), s_yh=np.ones(K), s_yv=np.ones(K), s_T=np.ones(K), lam=float(lam))
    sample_node_parameters(st, hyper, rng)
    return st


def simulate_data(st: State, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Draw local positions y (I,) and trajectories x (I, F) from the data model (eqs. 1-2)."""
    c = st.c
    I, F = c.shape[0], st.theta.shape[1]
    half = 3.0 / np.sqrt(st.s_yh[c])
    y = (half + rng.standard_normal(I) / np.sqrt(st.s_yh[c])) + 1j * rng.standard_normal(I) / np.sqrt(st.s_yv[c])
    noise = (rng.standard_normal((I, F)) + 1j * rng.standard_normal((I, F))) / np.sqrt(st.s_x[c])[:, None]
    x = np.exp(1j * st.theta[c]) * y[:, None] + st.T[c] + noise
    return y, x
