"""Markov chain kernels for the stick-figure posterior (section 3 of Meeds et al.).

Each public function is one kernel: it updates ``state`` (and for imputation the
complete data) in place, leaving the posterior invariant on its own. A sweep
(:func:`sweep`) applies them in the paper's order: indicators, split-merge,
sub-tree moves, then node parameters.

Derivations and deviations from the printed equations
-----------------------------------------------------
* Indicators (eqs. 11-12). The exact conditional of the tree prior carries the
  sub-tree factors derived in :mod:`.prior`; eqs. 11-12 omit them. New nodes use
  Neal's (2000) algorithm 8: every potential parent (each occupied node and the
  root) holds ``n_aux`` auxiliary parameter draws from the base distribution
  ``G(. | phi_parent)``, each with prior weight ``lambda / ((K + 1) n_aux)``, so a
  new node's likelihood is in effect averaged over several prior draws as the
  paper suggests. The auxiliary draws persist through a sweep (an auxiliary
  that becomes a node is replaced by a fresh draw) and are refreshed at the
  start of each sweep, after the parents' parameters have moved.
* Translations (eqs. 14-17). Conditioned on y_i the printed eq. 17 should use
  ``Delta x_i = x_i - R_k y_i`` (it prints the prior mean ``R_k L_k / 2``). We do better
  and integrate y out: the conditional of all F translations of a node is
  Gaussian with a precision that is a multiple of the identity plus a rank-2
  term (:func:`.model.translation_conditional`), sampled in O(F). This removes the
  strong coupling between a stick's translation and its points' local positions
  that makes the y-conditioned update crawl.
* Rotations (eqs. 18-21). Given y_i the statistics ``a + i b`` of eqs. 20-21 are
  right; in complex notation they are
  ``kappa_rho (e^{i theta_pf} + sum_c e^{i theta_cf}) + kappa_nd (e^{i theta_k,f-1} + e^{i theta_k,f+1})
  + s_x sum_i conj(y_i) (x_if - T_kf) + s_T L_k sum_c (T_cf - T_kf)``.
  They omit the per-frame normalisers ``I0(A)`` of the von Mises chain prior
  (see :mod:`.model`), which depend on ``theta_kf`` through the next frame and the
  children; the von Mises of eq. 19 is therefore used as an independence
  proposal and accepted with probability ``min(1, exp(g(theta') - g(theta)))``,
  ``g = -log I0(A_k,f+1) - sum_c log I0(A_c,f)``. Angles that do not interact
  (through the chain, the tree, or the normalisers) are updated together: colour
  ``(f + 2 depth) mod 3`` separates all of them.
* A rotation-shift kernel turns a whole stick about its joint (all frames) with
  y integrated out and the translations redrawn from their exact conditional;
  this moves along the direction (rotating the stick and counter-rotating its
  points' local positions) that the y-conditioned rotation update cannot.
* Precisions: ``s_x`` and ``s_yv`` given y and ``s_T`` given the children are Gamma;
  ``s_yh`` (which also sets the length) is slice sampled in log space with y
  integrated out.
* Split-merge: see :func:`split_merge`; with re-attachment (the split's outer half or
  the merged node hung from a new parent): :func:`reattach_move`.
* Tree moves: the paper's sub-tree move (:func:`subtree_move`) and three we
  added because chains otherwise stay in trees described from the wrong end:
  :func:`rehang_move` (a sub-tree move that refits the moved root),
  :func:`reverse_path` (describe a chain from its other end; the likelihood is
  unchanged) and :func:`swap_move` (parent and child exchange places).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .model import (
    LOG2PI,
    Hyper,
    distal_end,
    gamma_logpdf,
    log_i0,
    marginal_loglik,
    rotation_prior_logpdf,
    sample_rotation_prior,
    translation_conditional,
    translation_conditional_logpdf,
    translation_prior_logpdf,
    translation_sample,
)
from .prior import ancestor_matrix, log_tree_prior
from .state import Data, State, log_joint, node_prior_logpdf, sample_y

__all__ = [
    "SweepConfig",
    "MoveStats",
    "node_loglik_matrix",
    "gibbs_indicators",
    "split_merge",
    "reattach_move",
    "subtree_move",
    "reverse_path",
    "swap_move",
    "rehang_move",
    "polish_tree",
    "update_translations",
    "update_translations_given_y",
    "rotation_shift",
    "update_rotations",
    "update_precisions",
    "update_child_precisions",
    "slice_horizontal_precisions",
    "update_lambda",
    "update_kappa_nd",
    "impute_missing",
    "fit_node",
    "sweep",
]


@dataclass
class SweepConfig:
    """What one sweep does.

    Attributes
    ----------
    n_aux : int
        Prior draws per potential parent for new-node proposals.
    n_split_merge : int
        Split-merge proposals per sweep.
    n_launch : int
        Intermediate restricted Gibbs scans building a split's launch state.
    n_subtree : int
        Rounds of tree moves per sweep (sub-tree, path reversal, swap, re-hang, re-attaching split-merge).
    structure : bool
        Update indicators and the tree (False keeps them fixed: imputation on new frames).
    likelihood : bool
        Include the data (False samples the prior; used by the tests).
    """

    n_aux: int = 5
    n_split_merge: int = 5
    n_launch: int = 2
    n_subtree: int = 2
    structure: bool = True
    likelihood: bool = True


@dataclass
class MoveStats:
    """Proposal and acceptance counts per move."""

    proposed: dict[str, int] = field(default_factory=dict)
    accepted: dict[str, int] = field(default_factory=dict)

    def add(self, name: str, accepted: bool) -> None:
        self.proposed[name] = self.proposed.get(name, 0) + 1
        self.accepted[name] = self.accepted.get(name, 0) + int(bool(accepted))

    def rates(self) -> dict[str, float]:
        return {k: self.accepted.get(k, 0) / v for k, v in self.proposed.items() if v}


def _loglik(x: np.ndarray, theta, T, s_x, s_yh, s_yv, likelihood: bool, w: np.ndarray | None = None) -> np.ndarray:
    if likelihood:
        return marginal_loglik(x, theta, T, s_x, s_yh, s_yv, w)
    shape = np.broadcast_shapes(x.shape[:-1], np.shape(theta)[:-1], np.shape(s_x))
    return np.zeros(shape)


def node_loglik_matrix(st: State, x: np.ndarray, likelihood: bool = True, w: np.ndarray | None = None) -> np.ndarray:
    """log F(x_i | phi_k) for every point and node, shape (I, K) (only frames where ``w`` (I, F) is 1, if given)."""
    return _loglik(x[:, None, :], st.theta[None], st.T[None], st.s_x, st.s_yh, st.s_yv, likelihood,
                   None if w is None else w[:, None, :])


def _log_sigmoid(d: float) -> float:
    return -math.log1p(math.exp(-d)) if d >= 0 else d - math.log1p(math.exp(d))


# ----------------------------------------------------------------- indicators
def _draw_aux(theta_par: np.ndarray, J: np.ndarray, s_par: np.ndarray, M: int, hyper: Hyper,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M draws from G(. | parent) for each of S parents: theta (S, M, F), T (S, M, F), prec (S, M, 4)."""
    S, F = theta_par.shape
    ab = hyper.gamma_ab
    prec = rng.gamma(ab[:, 0], 1.0 / ab[:, 1], size=(S, M, 4))
    theta = sample_rotation_prior(np.broadcast_to(theta_par[:, None, :], (S, M, F)), hyper.kappa_rho,
                                  hyper.kappa_nd, rng)
    noise = rng.standard_normal((S, M, F)) + 1j * rng.standard_normal((S, M, F))
    T = J[:, None, :] + noise / np.sqrt(s_par)[:, None, None]
    return theta, T, prec


def _slot_context(st: State, hyper: Hyper, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta, distal end, child precision) of parents given as node indices (-1 = root)."""
    nodes = np.asarray(nodes)
    has = nodes >= 0
    p = np.where(has, nodes, 0)
    th = np.where(has[:, None], st.theta[p], 0.0)
    J = np.where(has[:, None], distal_end(st.theta[p], st.T[p], st.s_yh[p]), 0j)
    s = np.where(has, st.s_T[p], hyper.root_precision)
    return th, J, s


def gibbs_indicators(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                     stats: MoveStats | None = None) -> None:
    """Gibbs update of every point's node indicator (eqs. 11-12 with the exact tree-prior factors).

    Internal singletons keep their point (section 2.2.3). Nodes left empty are removed.
    Like every structure move it targets the posterior with the missing entries
    integrated out (only observed frames enter the likelihood).
    """
    x = data.x
    I, F = x.shape
    wobs = data.w if data.has_missing else None
    M = int(cfg.n_aux)
    K = st.K
    LL = node_loglik_matrix(st, x, cfg.likelihood, wobs)  # (I, K)
    n = st.counts().astype(float)
    A = ancestor_matrix(st.parent).astype(float)
    N = A.T @ n
    nchild = np.bincount(st.parent[st.parent >= 0], minlength=K).astype(int)
    # Auxiliary draws: slot 0 is the root, slot k + 1 node k.
    slots = np.arange(-1, K)
    th_s, J_s, s_s = _slot_context(st, hyper, slots)
    a_th, a_T, a_pr = _draw_aux(th_s, J_s, s_s, M, hyper, rng)
    AUX = _loglik(x[:, None, None, :], a_th[None], a_T[None], a_pr[None, ..., 0], a_pr[None, ..., 1],
                  a_pr[None, ..., 2], cfg.likelihood, None if wobs is None else wobs[:, None, None, :])  # (I, K + 1, M)
    log_lam = math.log(st.lam)
    log_M = math.log(M)

    def refresh_aux(s: int, m: int) -> None:
        node = s - 1
        th, J, sp = _slot_context(st, hyper, np.array([node]))
        t1, T1, p1 = _draw_aux(th, J, sp, 1, hyper, rng)
        a_th[s, m], a_T[s, m], a_pr[s, m] = t1[0, 0], T1[0, 0], p1[0, 0]
        AUX[:, s, m] = _loglik(x, t1[0, 0], T1[0, 0], p1[0, 0, 0], p1[0, 0, 1], p1[0, 0, 2], cfg.likelihood, wobs)

    order = rng.permutation(I)
    uniforms = rng.random(I)
    for i, u in zip(order.tolist(), uniforms.tolist()):
        k = int(st.c[i])
        if n[k] == 1 and nchild[k] > 0:
            continue  # internal singleton: its point cannot leave
        path_k = A[k] > 0
        n[k] -= 1
        N[path_k] -= 1
        singleton = n[k] == 0
        if singleton:
            p = int(st.parent[k])
            s0, m0 = p + 1, int(rng.integers(M))
            # Algorithm 8: the singleton's parameters become one of its parent's auxiliaries.
            a_th[s0, m0], a_T[s0, m0] = st.theta[k], st.T[k]
            a_pr[s0, m0] = [st.s_x[k], st.s_yh[k], st.s_yv[k], st.s_T[k]]
            AUX[:, s0, m0] = LL[:, k]
            if p >= 0:
                nchild[p] -= 1
        occ = n > 0
        Kp = int(occ.sum())
        # log N/(N+1) for occupied sub-trees (0 where empty, which only a removed leaf is)
        logr = np.where(N > 0, -np.log1p(1.0 / np.maximum(N, 1.0)), 0.0)
        logpath = A @ logr
        lw = np.empty(K + (K + 1) * M)
        lw[:K] = np.where(occ, np.log1p(n) + logpath + LL[i], -np.inf)
        base = log_lam - math.log(Kp + 1.0) - log_M
        lw_new = lw[K:].reshape(K + 1, M)
        lw_new[0] = base + AUX[i, 0]
        lw_new[1:] = np.where(occ[:, None], (base + logpath)[:, None] + AUX[i, 1:], -np.inf)
        # Inverse-CDF draw from the normalised weights.
        w = np.exp(lw - lw.max())
        cw = np.cumsum(w)
        choice = min(int(np.searchsorted(cw, u * cw[-1], side="right")), lw.size - 1)
        if choice < K:
            j = choice
            st.c[i] = j
            n[j] += 1
            N[A[j] > 0] += 1
            continue
        s, m = divmod(choice - K, M)
        if singleton and s == s0 and m == m0:
            # Back to its own (re-created) node.
            n[k] += 1
            N[path_k] += 1
            if st.parent[k] >= 0:
                nchild[st.parent[k]] += 1
            refresh_aux(s, m)
            continue
        p = s - 1
        new = st.add_node(p, a_th[s, m].copy(), a_T[s, m].copy(), *a_pr[s, m])
        LL = np.concatenate([LL, AUX[:, s, m][:, None]], axis=1)
        row = np.zeros(K + 1)
        if p >= 0:
            row[:K] = A[p]
            nchild[p] += 1
        row[K] = 1.0
        A = np.pad(A, ((0, 1), (0, 1)))
        A[K] = row
        n = np.append(n, 1.0)
        N = np.append(N, 0.0)
        N[row > 0] += 1.0
        nchild = np.append(nchild, 0)
        st.c[i] = new
        K += 1
        refresh_aux(s, m)
        # The new node is a potential parent for the points still to come.
        th, J, sp = _slot_context(st, hyper, np.array([new]))
        t1, T1, p1 = _draw_aux(th, J, sp, M, hyper, rng)
        a_th = np.concatenate([a_th, t1], axis=0)
        a_T = np.concatenate([a_T, T1], axis=0)
        a_pr = np.concatenate([a_pr, p1], axis=0)
        AUX = np.concatenate([AUX, _loglik(x[:, None, :], t1[0][None], T1[0][None], p1[0, :, 0], p1[0, :, 1],
                                           p1[0, :, 2], cfg.likelihood,
                                           None if wobs is None else wobs[:, None, :])[:, None, :]], axis=1)
        if stats is not None:
            stats.add("new_node", True)
    st.keep_nodes(n > 0)


# ------------------------------------------------------------- split-merge
@dataclass
class _Fit:
    theta: np.ndarray
    p_flip: float
    sigma_e: np.ndarray
    sigma_a: float
    sx_shape: float
    sx_rate: float


def fit_node(xB: np.ndarray, J: np.ndarray | None, s_par: float, hyper: Hyper,
             toward: np.ndarray | None = None) -> _Fit:
    """Deterministic rigid fit of a candidate node to its points, the centre of the split proposals.

    Per-frame rotations come from an iterated 2D Procrustes alignment to a mean
    shape; the stick's axis is then turned so that it points from the parent's
    distal end ``J`` towards the points' centroid (where the model puts them:
    the joint at ``T``, the points around ``L/2`` along the axis). Without a parent
    (the root) the axis is the shape's principal axis, pointing towards
    ``toward`` (where the node's children are) when given, else either way round.

    Parameters
    ----------
    xB : complex ndarray, shape (n, F)
    J : complex ndarray, shape (F,), or None for the root
    s_par : float
        Precision of the joint about ``J``.
    toward : complex ndarray, shape (F,), optional
        Where the distal end should point (used for children of the root).
    """
    n, F = xB.shape
    a_sx, b_sx = hyper.a_sx, hyper.b_sx
    if n >= 2:
        cen = xB.mean(0)
        Xc = xB - cen
        f0 = int(np.argmax((np.abs(Xc) ** 2).sum(0)))
        ref = Xc[:, f0]
        for _ in range(2):
            psi = np.angle((np.conj(ref)[:, None] * Xc).sum(0))
            ref = (Xc * np.exp(-1j * psi)).mean(1)
        rss = float((np.abs(Xc - ref[:, None] * np.exp(1j * psi)) ** 2).sum())
        r2 = float((np.abs(ref) ** 2).sum())
        shape = a_sx + (n - 1.5) * F
        rate = b_sx + 0.5 * rss
        sx_hat = shape / rate
        if J is not None:
            beta = np.angle(((cen - J) * np.exp(-1j * psi)).sum())
            p_flip = 0.1
        else:
            beta = 0.5 * np.angle((ref ** 2).sum())
            p_flip = 0.5
            if toward is not None:
                along = (((toward - cen) * np.exp(-1j * (psi + beta))).real).sum()
                beta += np.pi * (along < 0)
                p_flip = 0.1
        theta = psi + beta
        var = np.full(F, 1.0 / max(sx_hat * r2, 1e-12))
    else:
        shape, rate = a_sx, b_sx
        sx_hat = shape / rate
        if J is not None:
            d = xB[0] - J
            theta = np.angle(d)
            var = (1.0 / sx_hat + 1.0 / s_par) / np.maximum(np.abs(d) ** 2, 1e-12)
            p_flip = 0.1
        elif toward is not None:
            theta = np.angle(toward - xB[0])
            var = np.full(F, 0.25)
            p_flip = 0.1
        else:
            theta = np.zeros(F)
            var = np.full(F, 1.0)
            p_flip = 0.5
    sigma_e = np.clip(1.2 * np.sqrt(var), 1e-3, 0.7)
    return _Fit(theta=theta, p_flip=p_flip, sigma_e=sigma_e, sigma_a=0.1, sx_shape=shape, sx_rate=rate)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _theta_proposal_logpdf(theta: np.ndarray, fit: _Fit) -> float:
    """Density of theta = fit.theta + flip pi + alpha + e (alpha shared, e per frame), flip ~ Bernoulli."""
    d_inv = 1.0 / fit.sigma_e ** 2
    sa2 = fit.sigma_a ** 2
    denom = 1.0 + sa2 * d_inv.sum()
    logdet = float(np.log(fit.sigma_e ** 2).sum() + np.log(denom))
    F = theta.shape[0]
    out = []
    for flip, pf in ((0, 1.0 - fit.p_flip), (1, fit.p_flip)):
        if pf <= 0:
            continue
        d = _wrap(theta - fit.theta - flip * np.pi)
        quad = float((d * d * d_inv).sum() - sa2 * (d * d_inv).sum() ** 2 / denom)
        out.append(math.log(pf) - 0.5 * (F * LOG2PI + logdet + quad))
    return float(np.logaddexp.reduce(out))


def _theta_proposal_sample(fit: _Fit, rng: np.random.Generator) -> np.ndarray:
    flip = rng.random() < fit.p_flip
    F = fit.theta.shape[0]
    return _wrap(fit.theta + np.pi * flip + fit.sigma_a * rng.standard_normal() + fit.sigma_e * rng.standard_normal(F))


def _node_mean(xB: np.ndarray, J: np.ndarray | None, s_par: float, hyper: Hyper,
               toward: np.ndarray | None = None) -> tuple:
    """Deterministic parameters of a candidate node (the centre of its proposal)."""
    F = xB.shape[1]
    fit = fit_node(xB, J, s_par, hyper, toward)
    s_x = fit.sx_shape / fit.sx_rate
    s_yh, s_yv, s_T = hyper.a_syh / hyper.b_syh, hyper.a_syv / hyper.b_syv, hyper.a_sT / hyper.b_sT
    Jz = np.zeros(F, complex) if J is None else J
    T, _, _ = translation_conditional(fit.theta, s_x, s_yh, s_yv, xB.shape[0], xB.sum(0), Jz, s_par, 0, 0j, s_T)
    return (fit.theta, T, s_x, s_yh, s_yv, s_T)


def _node_proposal(xB: np.ndarray, J: np.ndarray | None, s_par: float, kids_T: np.ndarray, hyper: Hyper,
                   rng: np.random.Generator, target: tuple | None = None,
                   toward: np.ndarray | None = None) -> tuple[tuple, float]:
    """Draw (or evaluate the density of) a node's parameters given its points, parent and children.

    ``s_x`` from a Gamma centred on the rigid fit's residual, the other precisions
    from their priors (which dominate their posteriors), the angles around the
    rigid fit (:func:`fit_node`), the translations from their exact conditional
    given the angles (y integrated out, children included).
    """
    F = xB.shape[1]
    if toward is None and kids_T.shape[0]:
        toward = kids_T.mean(0)
    fit = fit_node(xB, J, s_par, hyper, toward)
    ab = hyper.gamma_ab
    if target is None:
        s_x = rng.gamma(fit.sx_shape, 1.0 / fit.sx_rate)
        s_yh, s_yv, s_T = (rng.gamma(ab[r, 0], 1.0 / ab[r, 1]) for r in (1, 2, 3))
        theta = _theta_proposal_sample(fit, rng)
    else:
        theta, _, s_x, s_yh, s_yv, s_T = target
    lq = float(gamma_logpdf(s_x, fit.sx_shape, fit.sx_rate) + gamma_logpdf(s_yh, *ab[1])
               + gamma_logpdf(s_yv, *ab[2]) + gamma_logpdf(s_T, *ab[3]))
    lq += _theta_proposal_logpdf(theta, fit)
    Jz = np.zeros(F, complex) if J is None else J
    mean, c, e = translation_conditional(theta, s_x, s_yh, s_yv, xB.shape[0], xB.sum(0), Jz, s_par,
                                         kids_T.shape[0], kids_T.sum(0), s_T)
    T = translation_sample(mean, theta, c, e, rng) if target is None else target[1]
    lq += translation_conditional_logpdf(T, mean, theta, c, e)
    return (theta, T, s_x, s_yh, s_yv, s_T), lq


@dataclass
class _Pair:
    """What a split of a node, and the merge that undoes it, hold fixed.

    ``J``/``s_par``: the distal end and child precision of the merged node's parent
    (None/root precision for the root); ``kids_*``: the merged node's children.
    """

    kind: str  # "sib", "down" or "up"
    J: np.ndarray | None
    s_par: float
    kids_theta: np.ndarray
    kids_T: np.ndarray


def _parent_of(st: State, hyper: Hyper, p: int) -> tuple[np.ndarray | None, float]:
    if p < 0:
        return None, float(hyper.root_precision)
    return distal_end(st.theta[p], st.T[p], st.s_yh[p]), float(st.s_T[p])


def _pair_means(xA: np.ndarray, xB: np.ndarray, pair: _Pair, hyper: Hyper) -> tuple[tuple, tuple]:
    """Deterministic parameters of A and B, the inner one attached to the outer one's distal end."""
    if pair.kind == "up":
        mB = _node_mean(xB, pair.J, pair.s_par, hyper, toward=xA.mean(0))
        mA = _node_mean(xA, distal_end(mB[0], mB[1], mB[3]), mB[5], hyper)
    elif pair.kind == "down":
        mA = _node_mean(xA, pair.J, pair.s_par, hyper, toward=xB.mean(0))
        mB = _node_mean(xB, distal_end(mA[0], mA[1], mA[3]), mA[5], hyper)
    else:
        mA = _node_mean(xA, pair.J, pair.s_par, hyper)
        mB = _node_mean(xB, pair.J, pair.s_par, hyper)
    return mA, mB


def _restricted_scans(x: np.ndarray, i: int, j: int, S: np.ndarray, pair: _Pair, hyper: Hyper, cfg: SweepConfig,
                      rng: np.random.Generator, target: np.ndarray | None = None
                      ) -> tuple[np.ndarray, float, tuple, tuple]:
    """Jain & Neal's launch state and final restricted Gibbs scan for the points S between A and B.

    The launch allocates each point of S to i or j, whichever keeps the steadier
    distance to it (Jain & Neal allocate at random; any allocation that depends
    only on the data and the pair is valid), then ``n_launch`` times refits both nodes
    (:func:`_pair_means`) and reallocates S by a restricted Gibbs scan. The final
    scan samples an allocation (``target`` None) or evaluates the probability of
    ``target`` (bool, True = B).

    Returns
    -------
    in_b : bool ndarray, shape (|S|,)
    log_q : float
    mean_a, mean_b : tuple
        Both nodes refitted to the final allocation.
    """
    m = S.shape[0]
    xS = x[S]
    # Launch: each point goes with whichever of i and j keeps the steadier distance
    # to it (points of one rigid part keep constant distances); ties at random.
    vi = np.abs(xS - x[i]).var(1)
    vj = np.abs(xS - x[j]).var(1)
    zb = np.where(vi == vj, rng.random(m) < 0.5, vj < vi)
    log_q = 0.0
    for t in range(cfg.n_launch + 1):
        mA, mB = _pair_means(x[np.concatenate([[i], S[~zb]])], x[np.concatenate([[j], S[zb]])], pair, hyper)
        d_all = (_loglik(xS, *mB[:5], cfg.likelihood) - _loglik(xS, *mA[:5], cfg.likelihood)).tolist()
        final = t == cfg.n_launch
        evaluate = final and target is not None
        u = None if evaluate else rng.random(m).tolist()
        nb = 1 + int(zb.sum())
        na = 1 + m - int(zb.sum())
        for q in range(m):
            if zb[q]:
                nb -= 1
            else:
                na -= 1
            d = math.log(nb) - math.log(na) + d_all[q]
            lp_b = _log_sigmoid(d)
            zq = bool(target[q]) if evaluate else u[q] < math.exp(lp_b)
            if final:
                log_q += lp_b if zq else _log_sigmoid(-d)
            zb[q] = zq
            if zq:
                nb += 1
            else:
                na += 1
    mA, mB = _pair_means(x[np.concatenate([[i], S[~zb]])], x[np.concatenate([[j], S[zb]])], pair, hyper)
    return zb, log_q, mA, mB


def _child_logp(theta_c: np.ndarray, T_c: np.ndarray, theta_p: np.ndarray, T_p: np.ndarray, syh_p: float,
                sT_p: float, hyper: Hyper) -> np.ndarray:
    """log G terms of children (n, F) that depend on their parent p."""
    J = distal_end(theta_p, T_p, syh_p)
    return (rotation_prior_logpdf(theta_c, np.broadcast_to(theta_p, theta_c.shape), hyper.kappa_rho, hyper.kappa_nd)
            + translation_prior_logpdf(T_c, J, sT_p))


def _children_assign(pair: _Pair, mA: tuple, mB: tuple, hyper: Hyper, rng: np.random.Generator,
                     target: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Give each child of the split node to A or B with probabilities from its prior under the fitted nodes."""
    h = pair.kids_theta.shape[0]
    if h == 0:
        return np.zeros(0, bool), 0.0
    la = _child_logp(pair.kids_theta, pair.kids_T, mA[0], mA[1], mA[3], mA[5], hyper)
    lb = _child_logp(pair.kids_theta, pair.kids_T, mB[0], mB[1], mB[3], mB[5], hyper)
    d = (lb - la).tolist()
    if target is None:
        u = rng.random(h)
        to_b = np.array([u[q] < math.exp(_log_sigmoid(d[q])) for q in range(h)], bool)
    else:
        to_b = np.asarray(target, bool)
    lq = sum(_log_sigmoid(v) if b else _log_sigmoid(-v) for v, b in zip(d, to_b))
    return to_b, float(lq)


def _pair_proposal(xA: np.ndarray, xB: np.ndarray, pair: _Pair, to_b: np.ndarray, hyper: Hyper,
                   rng: np.random.Generator, target: tuple[tuple, tuple] | None = None
                   ) -> tuple[tuple, tuple, float]:
    """Propose (or evaluate) A's and B's parameters, the outer node first."""
    kA, kB = pair.kids_T[~to_b], pair.kids_T[to_b]
    tA, tB = (None, None) if target is None else target
    if pair.kind == "up":
        phiB, lb = _node_proposal(xB, pair.J, pair.s_par, kB, hyper, rng, tB, toward=xA.mean(0))
        phiA, la = _node_proposal(xA, distal_end(phiB[0], phiB[1], phiB[3]), phiB[5], kA, hyper, rng, tA)
    elif pair.kind == "down":
        phiA, la = _node_proposal(xA, pair.J, pair.s_par, kA, hyper, rng, tA, toward=xB.mean(0))
        phiB, lb = _node_proposal(xB, distal_end(phiA[0], phiA[1], phiA[3]), phiA[5], kB, hyper, rng, tB)
    else:
        phiA, la = _node_proposal(xA, pair.J, pair.s_par, kA, hyper, rng, tA)
        phiB, lb = _node_proposal(xB, pair.J, pair.s_par, kB, hyper, rng, tB)
    return phiA, phiB, la + lb


def _phi(st: State, k: int) -> tuple:
    return (st.theta[k].copy(), st.T[k].copy(), float(st.s_x[k]), float(st.s_yh[k]), float(st.s_yv[k]),
            float(st.s_T[k]))


def _set_phi(st: State, k: int, phi: tuple) -> None:
    st.theta[k], st.T[k], st.s_x[k], st.s_yh[k], st.s_yv[k], st.s_T[k] = phi


def split_merge(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                stats: MoveStats | None = None, current: float | None = None) -> tuple[State, float]:
    """One Metropolis-Hastings split or merge proposal (after Jain & Neal's non-conjugate scheme).

    Two distinct points ``i`` and ``j`` are drawn (:func:`_choose_pair`: uniformly, or
    ``j`` from the neighbourhood of ``i``'s node). If they share node ``k``
    a split is proposed, of one of three kinds chosen uniformly: siblings (A and
    B both children of k's parent), chain down (B a child of A) or chain up (A a
    child of B, which takes k's place); A holds ``i``, B holds ``j``. Otherwise, if
    their nodes are siblings or parent and child, the merge that undoes such a
    split is proposed.

    The other points of the pair are allocated as Jain & Neal do: a launch state
    (random allocation, then ``n_launch`` restricted Gibbs scans) and a final
    restricted scan whose probability enters the acceptance ratio. Their scheme
    regenerates the new components' parameters by restricted Gibbs scans from
    prior draws; with 3F parameters per node (every frame's angle and
    translation) that essentially never proposes what the reverse move could
    reproduce. Here every node a move creates -- A and B for a split, the merged
    node for a merge -- gets parameters from a data-driven proposal with an
    exactly computed density (:func:`_node_proposal`), so the ratio is the
    posterior ratio over the proposal ratio, close to a Bayes factor of "one
    stick or two". The launch depends only on the data, the pair and the fixed
    surroundings, which both sides share. The merged node's children go to A or
    B with probabilities from their priors under the fitted A and B.

    Parameters
    ----------
    current : float, optional
        The log target of ``st`` if already known (saves recomputing it).

    Returns
    -------
    state : State
        The new state (``st`` itself when rejected).
    target : float
        Its log target.
    """
    if current is None:
        current = _target(st, data, hyper, cfg)
    I = data.n_points
    if I < 2:
        return st, current
    i, j = _choose_pair(st, rng)
    ci, cj = int(st.c[i]), int(st.c[j])
    if ci == cj:
        return _propose_split(st, data, hyper, rng, cfg, stats, i, j, ci, current)
    kind = _merge_kind(st, ci, cj)
    if kind is None:
        return st, current
    return _propose_merge(st, data, hyper, rng, cfg, stats, i, j, ci, cj, kind, current)


def _merge_kind(st: State, ci: int, cj: int) -> str | None:
    """How nodes ci and cj can merge: siblings, cj a child of ci, ci a child of cj; None otherwise."""
    if st.parent[ci] == st.parent[cj]:
        return "sib"
    if st.parent[cj] == ci:
        return "down"
    if st.parent[ci] == cj:
        return "up"
    return None


def _pair_pool(st: State, i: int) -> np.ndarray:
    """Points of i's node and of its parent, children and siblings, i excluded."""
    k = st.c[i]
    near = (st.parent == k) | (st.parent == st.parent[k])
    if st.parent[k] >= 0:
        near[st.parent[k]] = True
    near[k] = True
    pool = np.flatnonzero(near[st.c])
    return pool[pool != i]


def _pair_logprob(st: State, i: int, j: int, by_node: bool = False) -> float:
    """log probability that :func:`_choose_pair` (with ``by_node``) picks the ordered pair (i, j) in ``st``."""
    I = st.c.shape[0]
    pool = _pair_pool(st, i)
    if pool.size == 0:
        local = 1.0 / (I - 1)
    else:
        local = (1.0 / pool.size) if np.any(pool == j) else 0.0
    if by_node:
        if local == 0.0:
            return -math.inf
        return math.log(local / (st.K * np.count_nonzero(st.c == st.c[i])))
    return math.log(0.5 / (I * (I - 1)) + 0.5 * local / I)


def _choose_pair(st: State, rng: np.random.Generator, by_node: bool = False) -> tuple[int, int]:
    """An ordered pair of points: half the time uniform, half the time j near i in the tree.

    Drawing j among the points of i's node and its neighbours makes merges of
    adjacent nodes (and splits of one node) far more frequent than uniform
    pairs do; the probability of the pair in both states enters the ratio.
    With ``by_node``, i is drawn from a node drawn uniformly (so a one-point node
    is picked as often as any other) and j always near i.
    """
    I = st.c.shape[0]
    if by_node:
        members = np.flatnonzero(st.c == int(rng.integers(st.K)))
        i = int(members[rng.integers(members.size)])
    elif rng.random() < 0.5:
        i, j = (int(v) for v in rng.choice(I, size=2, replace=False))
        return i, j
    else:
        i = int(rng.integers(I))
    pool = _pair_pool(st, i)
    if pool.size == 0:
        j = int(rng.integers(I - 1))
        return i, j + (j >= i)
    return i, int(pool[rng.integers(pool.size)])


def _reattach_parents(st: State, nodes: list[int]) -> np.ndarray:
    """Where a re-attaching move may hang ``nodes`` (one node, or the two halves of a split, which
    share a parent or are parent and child): the root (-1) or any node outside their sub-trees,
    their current parent excluded."""
    A = ancestor_matrix(st.parent)
    inside = A[:, nodes].any(1)
    outer = [r for r in nodes if st.parent[r] not in nodes][0]
    cand = np.concatenate([[-1], np.flatnonzero(~inside)])
    return cand[cand != st.parent[outer]]


def _propose_split(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                   stats: MoveStats | None, i: int, j: int, k: int, current: float,
                   p_out: int | None = None, by_node: bool = False) -> tuple[State, float]:
    """Split node ``k`` (i to A, j to B); with ``p_out`` the split's outer node hangs from ``p_out``
    instead of k's parent and the children's translations are redrawn (:func:`reattach_move`)."""
    kind = ("sib", "down", "up")[int(rng.integers(3))]
    x = data.x_proposal
    members = np.flatnonzero(st.c == k)
    S = members[(members != i) & (members != j)]
    kids = st.children(k)
    pk = int(st.parent[k])
    moved = p_out is not None
    po = pk if p_out is None else int(p_out)
    J, s_par = _parent_of(st, hyper, po)
    pair = _Pair(kind, J, s_par, st.theta[kids], st.T[kids])
    in_b, lq_c, mA, mB = _restricted_scans(x, i, j, S, pair, hyper, cfg, rng)
    to_b, lq_h = _children_assign(pair, mA, mB, hyper, rng)
    a_pts = np.concatenate([[i], S[~in_b]])
    b_pts = np.concatenate([[j], S[in_b]])
    phiA, phiB, lq_ab = _pair_proposal(x[a_pts], x[b_pts], pair, to_b, hyper, rng)
    new = st.copy()
    _set_phi(new, k, phiA)
    b = new.add_node(k if kind == "down" else po, *phiB)
    new.c[b_pts] = b
    new.parent[kids[to_b]] = b
    if kind == "up":
        new.parent[k] = b
    else:
        new.parent[k] = po
    log_q = 0.0
    if moved:
        # The outer node moved: its children follow by fresh translations, counted both ways;
        # the reverse merge puts the merged node back under pk, proposing it given the
        # children as they are after this split.
        log_q += _redraw_translations(st, kids, x, hyper, None) - _redraw_translations(new, kids, x, hyper, rng)
        log_q += math.log(_reattach_parents(st, [k]).size) - math.log(_reattach_parents(new, [k, b]).size)
    J_m, s_m = _parent_of(st, hyper, pk)
    _, lq_m = _node_proposal(x[members], J_m, s_m, new.T[kids], hyper, rng, target=_phi(st, k))
    proposed = _target(new, data, hyper, cfg)
    log_ratio = (proposed - current - math.log(1.0 / 3.0) - lq_c - lq_h - lq_ab + lq_m + log_q
                 + _pair_logprob(new, i, j, by_node) - _pair_logprob(st, i, j, by_node))
    ok = math.log(rng.random()) < log_ratio
    if stats is not None:
        stats.add(f"{'reattach_' if moved else ''}split_{kind}", ok)
    return (new, proposed) if ok else (st, current)


def _propose_merge(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                   stats: MoveStats | None, i: int, j: int, a: int, b: int, kind: str,
                   current: float, p_in: int | None = None, by_node: bool = False) -> tuple[State, float]:
    """Merge nodes ``a`` (holding i) and ``b`` (holding j); with ``p_in`` the merged node hangs from
    ``p_in`` instead of the outer node's parent and its children's translations are redrawn
    (:func:`reattach_move`)."""
    x = data.x_proposal
    kids_a = st.children(a)
    kids_b = st.children(b)
    kids_a = kids_a[kids_a != b]
    kids_b = kids_b[kids_b != a]
    kids = np.concatenate([kids_a, kids_b])
    outer_node = b if kind == "up" else a
    outer = int(st.parent[outer_node])
    moved = p_in is not None
    pi = outer if p_in is None else int(p_in)
    J, s_par = _parent_of(st, hyper, outer)
    J_in, s_in = (J, s_par) if not moved else _parent_of(st, hyper, pi)
    members = np.flatnonzero((st.c == a) | (st.c == b))
    phiK, lq_m = _node_proposal(x[members], J_in, s_in, st.T[kids], hyper, rng)
    new = st.copy()
    new.c[new.c == b] = a
    new.parent[kids_b] = a
    new.parent[a] = pi
    _set_phi(new, a, phiK)
    keep = np.ones(st.K, bool)
    keep[b] = False
    new.keep_nodes(keep)
    log_q = 0.0
    kids_T = st.T[kids]
    if moved:
        # Children follow the merged node by fresh translations (counted both ways); the
        # reverse split hangs its outer node back under ``outer``, given the children as
        # they are after this merge.
        kids_new = kids - (kids > b)
        log_q += _redraw_translations(st, kids, x, hyper, None) - _redraw_translations(new, kids_new, x, hyper, rng)
        log_q += (math.log(_reattach_parents(st, [a, b]).size)
                  - math.log(_reattach_parents(new, [a - (a > b)]).size))
        kids_T = new.T[kids_new]
    proposed = _target(new, data, hyper, cfg)
    # The reverse split: allocation, children and both nodes' parameters as they are now.
    # Everything but the allocation's probability (log q_c <= 0, which needs the launch)
    # is computed first, so hopeless merges are rejected without building the launch.
    pair = _Pair(kind, J, s_par, st.theta[kids], kids_T)
    S = members[(members != i) & (members != j)]
    in_b = st.c[S] == b
    a_pts = np.concatenate([[i], S[~in_b]])
    b_pts = np.concatenate([[j], S[in_b]])
    mA, mB = _pair_means(x[a_pts], x[b_pts], pair, hyper)
    to_b = np.concatenate([np.zeros(kids_a.size, bool), np.ones(kids_b.size, bool)])
    _, lq_h = _children_assign(pair, mA, mB, hyper, rng, target=to_b)
    _, _, lq_ab = _pair_proposal(x[a_pts], x[b_pts], pair, to_b, hyper, rng, target=(_phi(st, a), _phi(st, b)))
    log_u = math.log(rng.random())
    bound = (proposed - current + math.log(1.0 / 3.0) + lq_h + lq_ab - lq_m + log_q
             + _pair_logprob(new, i, j, by_node) - _pair_logprob(st, i, j, by_node))
    ok = False
    if log_u < bound:
        _, lq_c, _, _ = _restricted_scans(x, i, j, S, pair, hyper, cfg, rng, target=in_b)
        ok = log_u < bound + lq_c
    if stats is not None:
        stats.add(f"{'reattach_' if moved else ''}merge_{kind}", ok)
    return (new, proposed) if ok else (st, current)


def reattach_move(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                  stats: MoveStats | None = None, current: float | None = None) -> tuple[State, float]:
    """Split-merge with re-attachment: a merge whose merged node hangs elsewhere, or a split whose
    outer half does (MH).

    The pair ``(i, j)`` is drawn by :func:`_choose_pair` with ``by_node``: ``i`` from a node
    drawn uniformly (a one-point node is chosen as often as any), ``j`` among the points
    of i's node and its neighbours; its probability in both states enters the ratio.
    If the two points share node
    ``k``, k is split as there (kind uniform, the launch and restricted scans, the
    children shared out, data-driven proposals of A and B), but the outer half (A, or
    B for a chain-up split) hangs from a new parent drawn uniformly among the root
    and the nodes outside k's sub-tree other than k's parent. If their nodes are
    siblings or parent and child, they are merged as there, but the merged node hangs
    from a new parent drawn the same way (outside the pair's sub-tree, its parent
    excluded). In both directions the nodes created are proposed under the new
    parent, and the children of the moved nodes get fresh translations from their
    conditionals given the proposed state (:func:`_redraw_translations`), so they
    follow. The two proposals are each other's reverse; the ratio holds the pair's
    probability in both states, the kind (1/3 for a split), both parent choices (the
    candidate sets have the same size: the same nodes lie outside the moved sub-tree),
    the allocation and children's sharing-out, both nodes' proposal densities and the
    children's translation densities, each computed both ways.

    It moves a stick together with its points to a joint elsewhere in one step. A
    chain can otherwise end with a stick attached through a one-point "connector"
    stick that spans a neighbour (the connector's point cannot leave: an internal
    singleton); undoing that needs the connector merged into its child and the merged
    stick re-hung at the neighbour's end, and the state in between is far worse.
    """
    if current is None:
        current = _target(st, data, hyper, cfg)
    if data.n_points < 2:
        return st, current
    i, j = _choose_pair(st, rng, by_node=True)
    ci, cj = int(st.c[i]), int(st.c[j])
    if ci == cj:
        cand = _reattach_parents(st, [ci])
        if cand.size == 0:
            return st, current
        p_out = int(cand[rng.integers(cand.size)])
        return _propose_split(st, data, hyper, rng, cfg, stats, i, j, ci, current, p_out=p_out, by_node=True)
    kind = _merge_kind(st, ci, cj)
    if kind is None:
        return st, current
    cand = _reattach_parents(st, [ci, cj])
    if cand.size == 0:
        return st, current
    p_in = int(cand[rng.integers(cand.size)])
    return _propose_merge(st, data, hyper, rng, cfg, stats, i, j, ci, cj, kind, current, p_in=p_in,
                          by_node=True)


def _prior_target(st: State, hyper: Hyper) -> float:
    """log tree prior plus every node's base density (no likelihood)."""
    return float(log_tree_prior(st.counts(), st.parent, st.lam) + node_prior_logpdf(st, hyper).sum())


def _target(st: State, data: Data, hyper: Hyper, cfg: SweepConfig) -> float:
    """log target of the structure moves: the observed-data log-joint (prior only without likelihood).

    The missing entries are integrated out, so a structure move is judged by the
    observed data alone; :func:`sweep` then redraws the missing entries from their
    conditional given the new state. (Judged on the completed data, a move would
    have to explain missing entries imputed from the current structure, which
    locks the structure in place.)
    """
    if cfg.likelihood:
        return log_joint(st, data, hyper, observed=True)
    return float(log_tree_prior(st.counts(), st.parent, st.lam) + node_prior_logpdf(st, hyper).sum())


# ------------------------------------------------------------- sub-tree move
def subtree_move(st: State, data: Data, hyper: Hyper, rng: np.random.Generator,
                 stats: MoveStats | None = None) -> None:
    """Metropolis-Hastings re-attachment of a sub-tree (section 3.1.3).

    The sub-tree root r is chosen in proportion to its number of points and its
    new parent uniformly among the nodes outside the sub-tree and the root,
    other than its current parent: a symmetric proposal, so the ratio is the
    tree prior's times r's base density under the new vs the old parent.
    """
    K = st.K
    if K < 2 and st.parent[0] == -1:
        return
    n = st.counts()
    r = int(rng.choice(K, p=n / n.sum()))
    A = ancestor_matrix(st.parent)
    inside = A[:, r]
    cand = np.concatenate([[-1], np.flatnonzero(~inside)])
    cand = cand[cand != st.parent[r]]
    if cand.size == 0:
        return
    p_new = int(cand[rng.integers(cand.size)])
    p_old = int(st.parent[r])

    def g(p: int) -> float:
        if p >= 0:
            th, J, sp = st.theta[p], distal_end(st.theta[p], st.T[p], st.s_yh[p]), st.s_T[p]
        else:
            th, J, sp = np.zeros_like(st.theta[r]), np.zeros_like(st.T[r]), hyper.root_precision
        return float(rotation_prior_logpdf(st.theta[r], th, hyper.kappa_rho, hyper.kappa_nd)
                     + translation_prior_logpdf(st.T[r], J, sp))

    old_tree = log_tree_prior(n, st.parent, st.lam, A)
    st.parent[r] = p_new
    new_tree = log_tree_prior(n, st.parent, st.lam)
    log_ratio = new_tree - old_tree + g(p_new) - g(p_old)
    ok = math.log(rng.random()) < log_ratio
    if not ok:
        st.parent[r] = p_old
    if stats is not None:
        stats.add("subtree", ok)


def reverse_path(st: State, data: Data, hyper: Hyper, rng: np.random.Generator,
                 stats: MoveStats | None = None) -> State:
    """Metropolis-Hastings reversal of the path from a root child down to a leaf.

    A chain can be described from either end: a stick attached at its proximal
    end ``T`` is the same stick attached at its distal end with its angles turned
    by pi (``theta' = theta + pi``, ``T' = T + exp(i theta) L``). The points' likelihood
    is unchanged (the local positions' prior is symmetric about ``L/2``); only the
    tree prior and the joints' and angles' priors change. The leaf is chosen
    uniformly; along the path ``r = a_1 -> ... -> a_m`` every ``a_i`` is flipped, the
    parent links reversed (``a_m`` becomes the root's child), and the other
    children of ``a_i``, which hang at the joint ``a_i``-``a_i+1``, move to ``a_i+1``. The move
    is its own inverse and the number of leaves is unchanged, so the proposal
    is symmetric. Without it a chain described from its middle (two root
    children meeting at their proximal ends) cannot become one chain.
    """
    K = st.K
    is_parent = np.zeros(K, bool)
    is_parent[st.parent[st.parent >= 0]] = True
    leaves = np.flatnonzero(~is_parent)
    leaf = int(leaves[rng.integers(leaves.size)])
    path = [leaf]
    while st.parent[path[-1]] >= 0:
        path.append(int(st.parent[path[-1]]))
    path = path[::-1]  # root child first
    new = st.copy()
    L = 6.0 / np.sqrt(st.s_yh)
    for q, a in enumerate(path):
        new.theta[a] = _wrap(st.theta[a] + np.pi)
        new.T[a] = st.T[a] + np.exp(1j * st.theta[a]) * L[a]
        new.parent[a] = path[q + 1] if q + 1 < len(path) else -1
        if q + 1 < len(path):
            others = st.children(a)
            others = others[others != path[q + 1]]
            new.parent[others] = path[q + 1]
    # The likelihood is invariant: compare priors only.
    log_ratio = _prior_target(new, hyper) - _prior_target(st, hyper)
    ok = math.log(rng.random()) < log_ratio
    if stats is not None:
        stats.add("reverse_path", ok)
    return new if ok else st


def _translation_conditionals(st: State, nodes: np.ndarray, x: np.ndarray, hyper: Hyper) -> list[tuple]:
    """Gaussian conditionals (mean, c, e) of the translations of ``nodes`` given the rest of ``st``.

    y integrated out, points' trajectories from ``x`` (the proposal data), the
    parent's distal end and the node's own children included
    (:func:`.model.translation_conditional`). The nodes must not be parent and
    child of each other, so that the conditionals are independent.
    """
    out = []
    for k in nodes.tolist():
        J, s_par, _ = _node_parent(st, hyper, k)
        kids = st.children(k)
        xs = x[st.c == k]
        out.append(translation_conditional(st.theta[k], st.s_x[k], st.s_yh[k], st.s_yv[k], xs.shape[0], xs.sum(0),
                                           J, s_par, kids.size, st.T[kids].sum(0), st.s_T[k]))
    return out


def _redraw_translations(st: State, nodes: np.ndarray, x: np.ndarray, hyper: Hyper,
                         rng: np.random.Generator | None) -> float:
    """Draw the translations of ``nodes`` from their conditionals in ``st`` (in place); log density.

    With ``rng`` None nothing is drawn and the log density of the current
    translations is returned (the reverse move's proposal density).

    A structure move that re-proposes a node moves its distal end; its
    children's joints, left where they were, would pay the whole mismatch
    (tens of nats per child at the default joint precision) and the move would
    almost never be accepted. Redrawing the children's translations as part of
    the proposal (and counting their density both ways) carries them along.
    """
    nodes = np.asarray(nodes, np.int64)
    if nodes.size == 0:
        return 0.0
    if np.isin(st.parent[nodes], nodes).any():
        raise ValueError("nodes whose translations are redrawn together must not be parent and child")
    lq = 0.0
    for k, (mean, c, e) in zip(nodes.tolist(), _translation_conditionals(st, nodes, x, hyper)):
        if rng is not None:
            st.T[k] = translation_sample(mean, st.theta[k], c, e, rng)
        lq += translation_conditional_logpdf(st.T[k], mean, st.theta[k], c, e)
    return lq


def rehang_move(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                stats: MoveStats | None = None, current: float | None = None) -> tuple[State, float]:
    """Sub-tree move whose root is re-fitted to its new parent (MH).

    As :func:`subtree_move` (root r chosen by its number of points, new parent
    uniform outside the sub-tree), but r's own parameters are drawn afresh from
    the data-driven node proposal under the new parent, so that r can turn to
    meet a joint elsewhere, and r's children's translations are redrawn from
    their conditionals given the proposed r (:func:`_redraw_translations`), so
    that they follow r's distal end. The reverse densities are those of r's
    current parameters under the same proposal from its old parent and of the
    children's current translations under their conditionals in the current state.
    """
    if current is None:
        current = _target(st, data, hyper, cfg)
    K = st.K
    n = st.counts()
    r = int(rng.choice(K, p=n / n.sum()))
    A = ancestor_matrix(st.parent)
    cand = np.concatenate([[-1], np.flatnonzero(~A[:, r])])
    cand = cand[cand != st.parent[r]]
    if cand.size == 0:
        return st, current
    p_new = int(cand[rng.integers(cand.size)])
    new, proposed, log_q = _rehang_proposal(st, data, hyper, rng, cfg, r, p_new)
    ok = math.log(rng.random()) < proposed - current + log_q
    if stats is not None:
        stats.add("rehang", ok)
    return (new, proposed) if ok else (st, current)


def _rehang_proposal(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig, r: int,
                     p_new: int) -> tuple[State, float, float]:
    """Re-hang node ``r`` under ``p_new`` (:func:`rehang_move`): new state, its log target, log q_rev - log q_fwd."""
    p_old = int(st.parent[r])
    x = data.x_proposal
    xr = x[st.c == r]
    kids = st.children(r)
    # Orientation of a root child: towards its children's points (unchanged by the move).
    toward = x[np.isin(st.c, kids)].mean(0) if kids.size else None
    none = np.zeros((0, st.T.shape[1]), complex)
    J_new, s_new = _parent_of(st, hyper, p_new)
    J_old, s_old = _parent_of(st, hyper, p_old)
    phi, lq = _node_proposal(xr, J_new, s_new, none, hyper, rng, toward=toward)
    _, lr = _node_proposal(xr, J_old, s_old, none, hyper, rng, target=_phi(st, r), toward=toward)
    new = st.copy()
    new.parent[r] = p_new
    _set_phi(new, r, phi)
    lq += _redraw_translations(new, kids, x, hyper, rng)
    lr += _redraw_translations(st, kids, x, hyper, None)
    return new, _target(new, data, hyper, cfg), lr - lq


def _reassign(kids_theta: np.ndarray, kids_T: np.ndarray, phi_a: tuple, phi_b: tuple, hyper: Hyper,
              rng: np.random.Generator, target: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Give each child to node a or b with probabilities from its prior under each; log probability."""
    pair = _Pair("sib", None, 1.0, kids_theta, kids_T)
    return _children_assign(pair, phi_a, phi_b, hyper, rng, target)


def swap_move(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
              stats: MoveStats | None = None, current: float | None = None) -> tuple[State, float]:
    """Metropolis-Hastings swap of a parent and its child, both re-proposed.

    An edge ``p -> c`` is chosen uniformly; ``c`` takes ``p``'s place under ``p``'s parent
    and ``p`` hangs from ``c``'s distal end. Both nodes' parameters are drawn from
    the data-driven node proposal (:func:`_node_proposal`), ``c`` first, then ``p``
    under the proposed ``c``; the other children of both are then shared out
    between them with probabilities from their priors under the proposed
    parameters, and their translations are redrawn from their conditionals
    given the proposed nodes (:func:`_redraw_translations`) so that they follow
    the joints. The reverse move is the same kind of swap on the edge
    ``c -> p`` and the number of edges is unchanged, so the acceptance ratio is the
    posterior ratio times the ratio of the proposal densities (the reverse
    sharing-out is evaluated with the children's proposed translations, as the
    reverse move would see them). It lets a stick turn round and take its place
    in a chain (with its neighbours' children following), which otherwise needs
    a long detour through worse states.
    """
    if current is None:
        current = _target(st, data, hyper, cfg)
    has = np.flatnonzero(st.parent >= 0)
    if has.size == 0:
        return st, current
    c = int(has[rng.integers(has.size)])
    new, proposed, log_q = _swap_proposal(st, data, hyper, rng, cfg, c)
    ok = math.log(rng.random()) < proposed - current + log_q
    if stats is not None:
        stats.add("swap", ok)
    return (new, proposed) if ok else (st, current)


def _swap_proposal(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                   c: int) -> tuple[State, float, float]:
    """Swap node ``c`` with its parent (:func:`swap_move`): new state, its log target, log q_rev - log q_fwd."""
    p = int(st.parent[c])
    g = int(st.parent[p])
    x = data.x_proposal
    J_g, s_g = _parent_of(st, hyper, g)
    kids_c = st.children(c)
    kids_p = st.children(p)
    kids_p = kids_p[kids_p != c]
    others = np.concatenate([kids_p, kids_c])
    none = np.zeros((0, st.T.shape[1]), complex)
    xc, xp = x[st.c == c], x[st.c == p]
    phi_c, lq_c = _node_proposal(xc, J_g, s_g, none, hyper, rng, toward=xp.mean(0) if J_g is None else None)
    phi_p, lq_p = _node_proposal(xp, distal_end(phi_c[0], phi_c[1], phi_c[3]), phi_c[5], none, hyper, rng)
    to_p, lq_h = _reassign(st.theta[others], st.T[others], phi_c, phi_p, hyper, rng)
    old_p, old_c = _phi(st, p), _phi(st, c)
    _, lr_p = _node_proposal(xp, J_g, s_g, none, hyper, rng, target=old_p, toward=xc.mean(0) if J_g is None else None)
    _, lr_c = _node_proposal(xc, distal_end(old_p[0], old_p[1], old_p[3]), old_p[5], none, hyper, rng, target=old_c)
    new = st.copy()
    new.parent[c] = g
    new.parent[p] = c
    new.parent[others] = np.where(to_p, p, c)
    _set_phi(new, c, phi_c)
    _set_phi(new, p, phi_p)
    lq_t = _redraw_translations(new, others, x, hyper, rng)
    lr_t = _redraw_translations(st, others, x, hyper, None)
    was_c = np.concatenate([np.zeros(kids_p.size, bool), np.ones(kids_c.size, bool)])
    _, lr_h = _reassign(new.theta[others], new.T[others], old_p, old_c, hyper, rng, target=was_c)
    proposed = _target(new, data, hyper, cfg)
    return new, proposed, lr_p + lr_c + lr_h + lr_t - lq_c - lq_p - lq_h - lq_t


def polish_tree(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
                rounds: int = 3, n_best: int = 3, relax: int = 4) -> State:
    """Greedy search over trees for the current partition (burn-in only: not a Markov kernel).

    Every swap of a node with its parent and every re-hang of a node under
    another node or the root is proposed once (:func:`_swap_proposal`,
    :func:`_rehang_proposal`); the ``n_best`` with the highest log target are
    relaxed by ``relax`` sweeps of the parameter kernels (structure fixed), as is
    the current state, and the best of them replaces the current state if its
    log target ends higher. Repeated for up to ``rounds`` rounds or until the
    current state wins. It mends what no single exact move can: a stick hung
    at the wrong end of a neighbour and contorted to meet it sits 100+ nats
    below the right tree, but a proposal's data-driven parameters are no match
    for the contorted ones until they have relaxed into the new tree.
    """
    fixed = SweepConfig(n_aux=cfg.n_aux, structure=False, likelihood=cfg.likelihood)
    for _ in range(rounds):
        if st.K < 2:
            return st
        A = ancestor_matrix(st.parent)
        cands = []
        for c in np.flatnonzero(st.parent >= 0).tolist():
            new, val, _ = _swap_proposal(st, data, hyper, rng, cfg, c)
            cands.append((val, new))
        for r in range(st.K):
            for p_new in [-1] + np.flatnonzero(~A[:, r]).tolist():
                if p_new != st.parent[r]:
                    new, val, _ = _rehang_proposal(st, data, hyper, rng, cfg, r, int(p_new))
                    cands.append((val, new))
        cands.sort(key=lambda t: -t[0])
        x0 = data.x.copy()  # relaxing re-imputes missing entries: each candidate from the same completion
        best_val, best, best_x = -np.inf, None, x0
        for _, new in cands[:n_best]:
            data.x = x0.copy()
            for _ in range(relax):
                new = sweep(new, data, hyper, rng, fixed)
            val = _target(new, data, hyper, cfg)
            if val > best_val:
                best_val, best, best_x = val, new, data.x
        data.x = x0.copy()
        cur = st.copy()
        for _ in range(relax):
            cur = sweep(cur, data, hyper, rng, fixed)
        if best is None or best_val <= _target(cur, data, hyper, cfg):
            return cur
        st = best
        data.x = best_x
    return st


# ------------------------------------------------------------- parameters
def _node_sums(st: State, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per node: number of points (K,) and the sum of their trajectories (K, F)."""
    K = st.K
    Z = np.zeros((K, x.shape[0]))
    Z[st.c, np.arange(x.shape[0])] = 1.0
    return Z.sum(1), Z @ x


def update_translations(st: State, data: Data, hyper: Hyper, rng: np.random.Generator,
                        likelihood: bool = True) -> None:
    """Gibbs update of every node's translations with y integrated out (exact eqs. 14-17)."""
    n, xsum = _node_sums(st, data.x)
    if not likelihood:
        n = np.zeros_like(n)
    for k in rng.permutation(st.K):
        J, s_par, _ = _node_parent(st, hyper, k)
        kids = st.children(k)
        mean, c, e = translation_conditional(st.theta[k], st.s_x[k], st.s_yh[k], st.s_yv[k], int(n[k]), xsum[k], J,
                                             s_par, kids.size, st.T[kids].sum(0), st.s_T[k])
        st.T[k] = translation_sample(mean, st.theta[k], c, e, rng)


def update_translations_given_y(st: State, data: Data, y: np.ndarray, hyper: Hyper,
                                rng: np.random.Generator, observed_only: bool = False) -> None:
    """Gibbs update of every node's translations given y (eqs. 15-17 with ``Delta x_i = x_i - R_k y_i``).

    Per frame the conditional is Gaussian with precision ``n_f s_x + h s_T + s_parent``,
    ``n_f`` the node's points counted in frame ``f``. With ``observed_only`` only the
    observed entries count (the missing ones integrated out: given y they are
    independent of everything but their own frame's parameters, so they simply
    drop out); ``y`` must then be a draw given the observed entries alone
    (:func:`.state.sample_y` with ``observed_only``). Otherwise the complete data
    (observed plus current imputation) are used.
    """
    K = st.K
    Z = np.zeros((K, data.n_points))
    Z[st.c, np.arange(data.n_points)] = 1.0
    if observed_only and data.has_missing:
        W = data.w
        nf = Z @ W  # (K, F)
        Zx = Z @ (W * data.x)
        Zy = Z @ (W * y[:, None])
    else:
        nf = np.repeat(Z.sum(1)[:, None], data.n_frames, axis=1)
        Zx = Z @ data.x
        Zy = np.repeat((Z @ y)[:, None], data.n_frames, axis=1)
    F = data.n_frames
    for k in rng.permutation(K):
        J, s_par, _ = _node_parent(st, hyper, k)
        kids = st.children(k)
        rot = np.exp(1j * st.theta[k])
        L = 6.0 / np.sqrt(st.s_yh[k])
        prec = nf[k] * st.s_x[k] + kids.size * st.s_T[k] + s_par
        b = s_par * J + st.s_x[k] * (Zx[k] - rot * Zy[k])
        if kids.size:
            b = b + st.s_T[k] * (st.T[kids].sum(0) - kids.size * rot * L)
        z = rng.standard_normal(F) + 1j * rng.standard_normal(F)
        st.T[k] = b / prec + z / np.sqrt(prec)


def _node_parent(st: State, hyper: Hyper, k: int) -> tuple[np.ndarray, float, np.ndarray]:
    p = int(st.parent[k])
    if p < 0:
        F = st.theta.shape[1]
        return np.zeros(F, complex), float(hyper.root_precision), np.zeros(F)
    return distal_end(st.theta[p], st.T[p], st.s_yh[p]), float(st.s_T[p]), st.theta[p]


def _log_marginal_theta(st: State, k: int, theta: np.ndarray, data: Data, idx: np.ndarray, hyper: Hyper,
                        likelihood: bool) -> tuple[float, tuple]:
    """log p(theta_k | rest) up to a constant, with y and T_k integrated out.

    Uses ``p(theta) = p(theta, T*) / p(T* | theta)`` at the conditional mean ``T*``.
    """
    J, s_par, th_par = _node_parent(st, hyper, k)
    kids = st.children(k)
    n = idx.size if likelihood else 0
    xs = data.x[idx]
    mean, c, e = translation_conditional(theta, st.s_x[k], st.s_yh[k], st.s_yv[k], n, xs.sum(0), J, s_par,
                                         kids.size, st.T[kids].sum(0), st.s_T[k])
    lp = float(rotation_prior_logpdf(theta, th_par, hyper.kappa_rho, hyper.kappa_nd)
               + translation_prior_logpdf(mean, J, s_par))
    if n:
        lp += float(marginal_loglik(xs, theta, mean, st.s_x[k], st.s_yh[k], st.s_yv[k]).sum())
    if kids.size:
        lp += float(_child_logp(st.theta[kids], st.T[kids], theta, mean, st.s_yh[k], st.s_T[k], hyper).sum())
    lp -= translation_conditional_logpdf(mean, mean, theta, c, e)
    return lp, (mean, c, e)


def rotation_shift(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, likelihood: bool = True,
                   stats: MoveStats | None = None) -> None:
    """Turn each stick about its joint in every frame at once (MH, y and T integrated out)."""
    for k in rng.permutation(st.K):
        idx = np.flatnonzero(st.c == k)
        u = rng.random()
        delta = np.pi if u < 0.1 else rng.normal(0.0, 0.03 if u < 0.55 else 0.3)
        th_new = st.theta[k] + delta
        lp_old, _ = _log_marginal_theta(st, k, st.theta[k], data, idx, hyper, likelihood)
        lp_new, (mean, c, e) = _log_marginal_theta(st, k, th_new, data, idx, hyper, likelihood)
        ok = math.log(rng.random()) < lp_new - lp_old
        if ok:
            st.theta[k] = _wrap(th_new)
            st.T[k] = translation_sample(mean, st.theta[k], c, e, rng)
        if stats is not None:
            stats.add("rotation_shift", ok)


def update_rotations(st: State, data: Data, y: np.ndarray, hyper: Hyper, rng: np.random.Generator,
                     likelihood: bool = True, stats: MoveStats | None = None, observed_only: bool = False) -> None:
    """Von Mises updates of every angle given y (eqs. 19-21), corrected for the chain's normalisers.

    Angles of one colour ``(f + 2 depth) mod 3`` are conditionally independent and
    are updated together. With ``observed_only`` the data term sums over the
    observed entries only (the missing ones integrated out given y; ``y`` must
    then be drawn given the observed entries alone).
    """
    K, F = st.theta.shape
    kr, kn = hyper.kappa_rho, hyper.kappa_nd
    A = ancestor_matrix(st.parent)
    depth = A.sum(1)
    colour = (np.arange(F)[None, :] + 2 * depth[:, None]) % 3
    Pm = np.zeros((K, K))  # Pm[k, c] = 1 when c is a child of k
    has = st.parent >= 0
    Pm[st.parent[has], np.flatnonzero(has)] = 1.0
    h = Pm.sum(1)
    L = 6.0 / np.sqrt(st.s_yh)
    if likelihood:
        Z = np.zeros((K, data.n_points))
        Z[st.c, np.arange(data.n_points)] = 1.0
        if observed_only and data.has_missing:
            Yx = Z @ (data.w * np.conj(y)[:, None] * data.x)  # (K, F)
            Ysum = Z @ (data.w * np.conj(y)[:, None])  # (K, F)
        else:
            Yx = Z @ (np.conj(y)[:, None] * data.x)  # (K, F)
            Ysum = (Z @ np.conj(y))[:, None]  # (K, 1)
    for col in range(3):
        mask = colour == col
        if not mask.any():
            continue
        e = np.exp(1j * st.theta)
        pe = np.where(has[:, None], e[np.maximum(st.parent, 0)], 1.0 + 0j)
        ab = kr * (pe + Pm @ e)
        ab[:, 1:] += kn * e[:, :-1]
        ab[:, :-1] += kn * e[:, 1:]
        csum = Pm @ st.T
        ab += (st.s_T * L)[:, None] * (csum - h[:, None] * st.T)
        if likelihood:
            ab += st.s_x[:, None] * (Yx - st.T * Ysum)
        prop = rng.vonmises(np.angle(ab), np.abs(ab))

        def g(theta_k: np.ndarray) -> np.ndarray:
            # Normalisers that depend on theta_kf: next frame's and children's same frame.
            ek = np.exp(1j * theta_k)
            out = np.zeros((K, F))
            nxt = np.abs(kn * ek[:, :-1] + kr * pe[:, 1:])
            out[:, :-1] -= log_i0(nxt)
            if has.any():
                ch = np.flatnonzero(has)
                # child c at frame f >= 1: A = |kn e^{i theta_c,f-1} + kr e^{i theta_pf}|
                Ac = np.abs(kn * e[ch, :-1] + kr * ek[st.parent[ch], 1:])
                out[:, 1:] -= Pm[:, ch] @ log_i0(Ac)
            return out

        log_acc = g(prop) - g(st.theta)
        ok = mask & (np.log(rng.random((K, F))) < log_acc)
        st.theta = np.where(ok, prop, st.theta)
        if stats is not None:
            stats.proposed["rotation"] = stats.proposed.get("rotation", 0) + int(mask.sum())
            stats.accepted["rotation"] = stats.accepted.get("rotation", 0) + int(ok.sum())


def update_precisions(st: State, data: Data, y: np.ndarray, hyper: Hyper, rng: np.random.Generator,
                      likelihood: bool = True) -> None:
    """Gamma updates of s_x and s_yv given y (conjugate)."""
    K = st.K
    c = st.c
    F = data.n_frames
    n = np.bincount(c, minlength=K).astype(float)
    if likelihood:
        res = data.x - np.exp(1j * st.theta[c]) * y[:, None] - st.T[c]
        rss = np.bincount(c, weights=(np.abs(res) ** 2).sum(1), minlength=K)
        st.s_x = rng.gamma(hyper.a_sx + n * F, 1.0 / (hyper.b_sx + 0.5 * rss))
        ss = np.bincount(c, weights=y.imag ** 2, minlength=K)
        st.s_yv = rng.gamma(hyper.a_syv + 0.5 * n, 1.0 / (hyper.b_syv + 0.5 * ss))
    else:
        st.s_x = rng.gamma(hyper.a_sx, 1.0 / hyper.b_sx, size=K)
        st.s_yv = rng.gamma(hyper.a_syv, 1.0 / hyper.b_syv, size=K)


def update_child_precisions(st: State, hyper: Hyper, rng: np.random.Generator) -> None:
    """Gamma update of every node's s_T from its children's translations (conjugate)."""
    K, F = st.theta.shape
    has = st.parent >= 0
    ch = np.flatnonzero(has)
    p = st.parent[ch]
    J = distal_end(st.theta[p], st.T[p], st.s_yh[p])
    ss = np.bincount(p, weights=(np.abs(st.T[ch] - J) ** 2).sum(1), minlength=K)
    h = np.bincount(p, minlength=K)
    st.s_T = rng.gamma(hyper.a_sT + h * F, 1.0 / (hyper.b_sT + 0.5 * ss))


def _slice_sample(logp, x0: np.ndarray, width: float, rng: np.random.Generator, max_steps: int = 8) -> np.ndarray:
    """Vectorised univariate slice sampling (Neal 2003, stepping out and shrinkage) of independent targets."""
    K = x0.shape[0]
    level = logp(x0) + np.log(rng.random(K))
    left = x0 - width * rng.random(K)
    right = left + width
    jl = np.floor(max_steps * rng.random(K)).astype(int)
    jr = max_steps - 1 - jl
    for _ in range(max_steps):
        grow = (jl > 0) & (logp(left) > level)
        if not grow.any():
            break
        left = np.where(grow, left - width, left)
        jl -= grow
    for _ in range(max_steps):
        grow = (jr > 0) & (logp(right) > level)
        if not grow.any():
            break
        right = np.where(grow, right + width, right)
        jr -= grow
    out = x0.copy()
    todo = np.ones(K, bool)
    for _ in range(200):
        cand = left + (right - left) * rng.random(K)
        cand = np.where(todo, cand, out)
        good = todo & (logp(cand) > level)
        out = np.where(good, cand, out)
        todo &= ~good
        if not todo.any():
            break
        lower = todo & (cand < x0)
        left = np.where(lower, cand, left)
        right = np.where(todo & ~lower, cand, right)
    return out


def slice_horizontal_precisions(st: State, data: Data, hyper: Hyper, rng: np.random.Generator,
                                likelihood: bool = True) -> None:
    """Slice sampling of every s_yh (it sets the stick length) in log space, y integrated out."""
    K, F = st.theta.shape
    c = st.c
    a, b = hyper.a_syh, hyper.b_syh
    if likelihood:
        z = np.exp(-1j * st.theta[c]) * (data.x - st.T[c])
        S1 = (np.abs(z) ** 2).sum(1)
        S2 = z.sum(1)
        sx = st.s_x[c]
        syv = st.s_yv[c]
    ch = np.flatnonzero(st.parent >= 0)
    p = st.parent[ch]
    w = st.T[ch] - st.T[p]
    W1 = np.bincount(p, weights=(np.abs(w) ** 2).sum(1), minlength=K)
    W2 = np.bincount(p, weights=(np.exp(-1j * st.theta[p]) * w).sum(1).real, minlength=K)
    hF = np.bincount(p, minlength=K) * F

    def logp(u: np.ndarray) -> np.ndarray:
        s = np.exp(u)
        L = 6.0 / np.sqrt(s)
        lp = a * u - b * s - 0.5 * st.s_T * (W1 - 2.0 * L * W2 + hF * L * L)
        if likelihood:
            sc = s[c]
            half = 0.5 * L[c]
            S = S1 - 2.0 * half * S2.real + F * half * half
            u_re = S2.real - F * half
            a_h = 1.0 / (F + sc / sx)
            a_v = 1.0 / (F + syv / sx)
            quad = sx * (S - a_h * u_re ** 2 - a_v * S2.imag ** 2)
            ll = -0.5 * np.log1p(sx * F / sc) - 0.5 * quad
            lp = lp + np.bincount(c, weights=ll, minlength=K)
        return lp

    st.s_yh = np.exp(_slice_sample(logp, np.log(st.s_yh), 0.3, rng))


def update_kappa_nd(st: State, hyper: Hyper, rng: np.random.Generator) -> Hyper:
    """Slice sampling of kappa_nd (an angle's tie to its previous frame) in log space; returns the new Hyper.

    Its conditional involves only the angles' chain prior (eqs. 4-5, every
    node's normalisers ``I0(A)`` included) and its Gamma(``kappa_nd_a``,
    ``kappa_nd_b``) prior: ``log p(u) = sum_k log G(theta_k | theta_parent; kappa_rho, e^u)
    + a u - b e^u`` for ``u = log kappa_nd`` (the Jacobian gives ``a`` instead of ``a - 1``).
    With the paper's fixed ``kappa_nd = 1`` an angle in a frame where its stick
    is unseen is known to within about 0.7 rad from its neighbouring frames, so
    the posterior-mean position of an occluded point shrinks towards the
    joint; figures that move smoothly from frame to frame get a far larger
    kappa_nd here, and occluded sticks follow their neighbouring frames.
    """
    has = st.parent >= 0
    th_par = np.where(has[:, None], st.theta[np.maximum(st.parent, 0)], 0.0)
    a, b = hyper.kappa_nd_a, hyper.kappa_nd_b

    def logp(u: np.ndarray) -> np.ndarray:
        k = float(np.exp(u[0]))
        return np.array([float(rotation_prior_logpdf(st.theta, th_par, hyper.kappa_rho, k).sum())
                         + a * u[0] - b * k])

    u = _slice_sample(logp, np.array([math.log(hyper.kappa_nd)]), 1.0, rng)
    return replace(hyper, kappa_nd=float(np.exp(u[0])))


def update_lambda(st: State, n_points: int, hyper: Hyper, rng: np.random.Generator) -> None:
    """Escobar & West (1995) auxiliary-variable update of lambda under a Gamma prior.

    The tree prior depends on lambda only through ``lambda^K Gamma(lambda) / Gamma(lambda + I)``,
    exactly as a Dirichlet process concentration does, so their update applies unchanged.
    """
    K = st.K
    eta = rng.beta(st.lam + 1.0, n_points)
    rate = hyper.lambda_b - math.log(eta)
    odds = (hyper.lambda_a + K - 1.0) / (n_points * rate)
    shape = hyper.lambda_a + K if rng.random() < odds / (1.0 + odds) else hyper.lambda_a + K - 1.0
    st.lam = float(rng.gamma(shape, 1.0 / rate))


def impute_missing(st: State, data: Data, y: np.ndarray, rng: np.random.Generator) -> None:
    """Draw every missing entry from the model given y (section 4.2)."""
    miss = ~data.observed
    if not miss.any():
        return
    ii, ff = np.nonzero(miss)
    k = st.c[ii]
    sd = 1.0 / np.sqrt(st.s_x[k])
    mean = np.exp(1j * st.theta[k, ff]) * y[ii] + st.T[k, ff]
    data.x[ii, ff] = mean + sd * (rng.standard_normal(ii.size) + 1j * rng.standard_normal(ii.size))


# -------------------------------------------------------------------- sweep
def sweep(st: State, data: Data, hyper: Hyper, rng: np.random.Generator, cfg: SweepConfig,
          stats: MoveStats | None = None) -> State:
    """One sweep: indicators, split-merge, tree moves, then every parameter and the missing values.

    Returns the (possibly new) state object; ``data.x`` is updated in place.
    """
    lik = cfg.likelihood
    if cfg.structure:
        gibbs_indicators(st, data, hyper, rng, cfg, stats)
        current = None
        for _ in range(cfg.n_split_merge):
            st, current = split_merge(st, data, hyper, rng, cfg, stats, current)
        for _ in range(cfg.n_subtree):
            subtree_move(st, data, hyper, rng, stats)
            st = reverse_path(st, data, hyper, rng, stats)
            st, _ = swap_move(st, data, hyper, rng, cfg, stats)
            st, _ = rehang_move(st, data, hyper, rng, cfg, stats)
            st, _ = reattach_move(st, data, hyper, rng, cfg, stats)
    if lik and data.has_missing:
        # The structure moves above and this block target the posterior with the
        # missing entries integrated out (given y they drop out of the translation
        # and rotation conditionals), so that a stick hidden in a frame follows its
        # joint and neighbouring frames instead of the values imputed from its own
        # current pose (data augmentation would make those frames crawl). None of
        # them reads the current imputation, so drawing a fresh one from
        # p(x_mis | state, x_obs) afterwards makes the whole a valid kernel on the
        # joint of state and missing entries. The kernels below use the completion.
        y = sample_y(st, data, rng, observed_only=True)
        update_translations_given_y(st, data, y, hyper, rng, observed_only=True)
        update_rotations(st, data, y, hyper, rng, lik, None, observed_only=True)
        impute_missing(st, data, y, rng)
    update_translations(st, data, hyper, rng, lik)
    rotation_shift(st, data, hyper, rng, lik, stats)
    y = sample_y(st, data, rng)
    update_rotations(st, data, y, hyper, rng, lik, stats)
    y = sample_y(st, data, rng)
    update_precisions(st, data, y, hyper, rng, lik)
    if lik:
        impute_missing(st, data, y, rng)
    update_child_precisions(st, hyper, rng)
    slice_horizontal_precisions(st, data, hyper, rng, lik)
    if hyper.update_lambda and cfg.structure:
        update_lambda(st, data.n_points, hyper, rng)
    return st
