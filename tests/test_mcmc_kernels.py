"""Geweke-style joint-distribution tests of the parameter kernels, and the model's algebra.

Marginal-conditional simulator: exact draws of (parameters, data) from the
prior and the data model. Successive-conditional simulator: start from such a
draw, then alternate the kernel under test (which must leave the posterior
of its block invariant) with a fresh draw of the data given the parameters.
Every step leaves the joint distribution invariant, so after a few steps the
parameters must still be distributed as the prior; replicas are independent,
so two-sample tests apply without autocorrelation corrections.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import ks_2samp, multivariate_normal

from stickfigure.models.mcmc import kernels as K
from stickfigure.models.mcmc.model import (
    Hyper,
    marginal_loglik,
    rotation_prior_logpdf,
    sample_rotation_prior,
    translation_conditional,
    translation_conditional_logpdf,
    translation_sample,
)
from stickfigure.models.mcmc.prior import sample_tree_prior
from stickfigure.models.mcmc.state import Data, State, sample_node_parameters, sample_y, simulate_data

# Sharp data (noise ~0.03 against a spread of 0.1 along a stick) so that errors in the
# kernels show; the paper's b_sx = 1 hides them under noise of 0.3.
HYPER = Hyper(root_precision=1.0, update_lambda=False, b_sx=0.01)
F = 4


def _fixed_state(rng: np.random.Generator) -> State:
    """Three nodes (a root child with two children), 5 points, parameters from the prior."""
    st = State(c=np.array([0, 0, 1, 1, 2]), parent=np.array([-1, 0, 0]), theta=np.zeros((3, F)),
               T=np.zeros((3, F), complex), s_x=np.ones(3), s_yh=np.ones(3), s_yv=np.ones(3), s_T=np.ones(3),
               lam=1.0)
    sample_node_parameters(st, HYPER, rng)
    return st


def _stats(st: State, x: np.ndarray) -> np.ndarray:
    """Statistics of (parameters, data): the joint distribution is what must be preserved."""
    local = np.exp(-1j * st.theta[st.c]) * (x - st.T[st.c])  # points in their stick's frame
    per_node = np.array([local[st.c == k].mean() for k in range(st.K)])
    return np.concatenate([np.cos(st.theta[:, 1]), np.sin(st.theta[:, 2]), st.T[:, 0].real, st.T[:, 3].imag,
                           np.log(st.s_x), np.log(st.s_yh), np.log(st.s_yv), np.log(st.s_T),
                           per_node.real, per_node.imag])


def _kernel(name: str):
    def step(st: State, data: Data, rng: np.random.Generator) -> State:
        if name == "translations":
            K.update_translations(st, data, HYPER, rng)
        elif name == "translations_given_y":
            K.update_translations_given_y(st, data, sample_y(st, data, rng), HYPER, rng)
        elif name == "rotations":
            K.update_rotations(st, data, sample_y(st, data, rng), HYPER, rng)
        elif name == "rotation_shift":
            K.rotation_shift(st, data, HYPER, rng)
        elif name == "precisions":
            K.update_precisions(st, data, sample_y(st, data, rng), HYPER, rng)
        elif name == "child_precisions":
            K.update_child_precisions(st, HYPER, rng)
        elif name == "horizontal_precisions":
            K.slice_horizontal_precisions(st, data, HYPER, rng)
        elif name == "sweep":
            st = K.sweep(st, data, HYPER, rng, K.SweepConfig(structure=False))
        else:  # pragma: no cover
            raise KeyError(name)
        return st

    return step


def _geweke(step, n_rep: int, n_steps: int, seed: int, observed: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Prior draws vs the successive-conditional simulator; ``observed`` (I, F) hides entries.

    With hidden entries the chain's state includes their current values: every
    step draws complete data from the model and hides nothing from the kernel
    but the mask (the kernel may overwrite the hidden values: it samples them).
    """
    rng = np.random.default_rng(seed)
    prior, after = [], []
    for _ in range(n_rep):
        st0 = _fixed_state(rng)
        prior.append(_stats(st0, simulate_data(st0, rng)[1]))
        st = _fixed_state(rng)
        _, x = simulate_data(st, rng)
        mask = np.ones(x.shape, bool) if observed is None else observed
        data = Data(x=x, observed=mask)
        for s in range(n_steps):
            if s:
                _, data.x = simulate_data(st, rng)
            st = step(st, data, rng)
        after.append(_stats(st, data.x))
    return np.array(prior), np.array(after)


def _min_pvalue(a: np.ndarray, b: np.ndarray) -> float:
    return min(ks_2samp(a[:, j], b[:, j]).pvalue for j in range(a.shape[1]))


KERNELS = ["translations", "translations_given_y", "rotations", "rotation_shift", "precisions", "child_precisions",
           "horizontal_precisions"]


@pytest.mark.parametrize("name", KERNELS)
def test_parameter_kernel_geweke(name):
    prior, after = _geweke(_kernel(name), n_rep=500, n_steps=3, seed=1)
    # Bonferroni over the statistics: each KS test at 1e-3 / n.
    assert _min_pvalue(prior, after) > 1e-3 / prior.shape[1]


def _observed_only_step(st: State, data: Data, rng: np.random.Generator) -> State:
    """The sweep's block for missing data: y given the visible entries, T and theta given y
    and the visible entries, then a fresh completion of the hidden ones."""
    y = sample_y(st, data, rng, observed_only=True)
    K.update_translations_given_y(st, data, y, HYPER, rng, observed_only=True)
    K.update_rotations(st, data, y, HYPER, rng, observed_only=True)
    K.impute_missing(st, data, y, rng)
    return st


# Point 0 hidden in frames 1-2 and point 4 (alone at node 2) in frame 3: a whole stick unseen in a frame.
_MASK = np.ones((5, F), bool)
_MASK[0, 1:3] = False
_MASK[4, 3] = False


def test_observed_only_updates_geweke():
    """T and theta updated with the hidden entries integrated out, then re-imputed, keep the joint."""
    prior, after = _geweke(_observed_only_step, n_rep=500, n_steps=3, seed=3, observed=_MASK)
    assert _min_pvalue(prior, after) > 1e-3 / prior.shape[1]


def test_geweke_with_missing_catches_a_stale_completion():
    """The same block without the fresh completion (y drawn from the visible entries, the
    hidden ones left as they were) is not a valid kernel on the joint; the test sees it."""

    def stale(st, data, rng):
        y = sample_y(st, data, rng, observed_only=True)
        K.update_translations_given_y(st, data, y, HYPER, rng, observed_only=True)
        K.update_rotations(st, data, y, HYPER, rng, observed_only=True)
        return st

    prior, after = _geweke(stale, n_rep=500, n_steps=3, seed=3, observed=_MASK)
    assert _min_pvalue(prior, after) < 1e-6


def test_geweke_catches_printed_eq17():
    """The printed translation update (eq. 17 with Delta x_i = x_i - R L/2, i.e. y_i set to its
    prior mean) is not the conditional; the Geweke test must reject it."""

    def printed(st, data, rng):
        half = 3.0 / np.sqrt(st.s_yh[st.c]) + 0j
        K.update_translations_given_y(st, data, half, HYPER, rng)
        return st

    prior, after = _geweke(printed, n_rep=500, n_steps=3, seed=1)
    assert _min_pvalue(prior, after) < 1e-6


@pytest.mark.slow
def test_full_parameter_sweep_geweke():
    prior, after = _geweke(_kernel("sweep"), n_rep=1500, n_steps=4, seed=2)
    assert _min_pvalue(prior, after) > 1e-3 / prior.shape[1]


@pytest.mark.slow
def test_full_sampler_geweke_with_structure():
    """The whole sweep, structure moves included, with the likelihood: node counts stay at the prior's."""
    rng = np.random.default_rng(4)
    hyper = Hyper(root_precision=1.0, update_lambda=False)
    I, Fr = 3, 2
    from stickfigure.models.mcmc.state import sample_prior_state

    k_prior, k_after = [], []
    cfg = K.SweepConfig(n_aux=3, n_split_merge=2, n_launch=1, n_subtree=1)
    for _ in range(1500):
        k_prior.append(sample_prior_state(I, Fr, hyper, rng, lam=1.0).K)
        st = sample_prior_state(I, Fr, hyper, rng, lam=1.0)
        _, x = simulate_data(st, rng)
        data = Data(x=x, observed=np.ones(x.shape, bool))
        for _ in range(3):
            st = K.sweep(st, data, hyper, rng, cfg)
            _, data.x = simulate_data(st, rng)
        k_after.append(st.K)
    from scipy.stats import chisquare

    kk = sorted(set(k_prior) | set(k_after))
    obs = np.array([k_after.count(k) for k in kk], float)
    exp = np.array([k_prior.count(k) for k in kk], float)
    assert chisquare(obs, exp * obs.sum() / exp.sum()).pvalue > 1e-3


def test_lambda_update_keeps_its_prior():
    rng = np.random.default_rng(5)
    hyper = Hyper(lambda_a=2.0, lambda_b=1.5)
    I = 20
    draws, after = [], []
    for _ in range(3000):
        lam = rng.gamma(hyper.lambda_a, 1.0 / hyper.lambda_b)
        c, parent = sample_tree_prior(I, lam, rng)
        st = State(c=c, parent=parent, theta=np.zeros((parent.size, 1)), T=np.zeros((parent.size, 1), complex),
                   s_x=np.ones(parent.size), s_yh=np.ones(parent.size), s_yv=np.ones(parent.size),
                   s_T=np.ones(parent.size), lam=lam)
        K.update_lambda(st, I, hyper, rng)
        draws.append(rng.gamma(hyper.lambda_a, 1.0 / hyper.lambda_b))
        after.append(st.lam)
    assert ks_2samp(draws, after).pvalue > 1e-3


def test_kappa_nd_update_keeps_its_prior():
    """kappa_nd drawn from its prior, angles from the chain prior given it, then the slice
    update: kappa_nd must still follow its prior (and it must move)."""
    from dataclasses import replace

    from stickfigure.models.mcmc.state import sample_prior_state

    rng = np.random.default_rng(6)
    base = Hyper(update_kappa_nd=True, kappa_nd_a=3.0, kappa_nd_b=0.5, root_precision=1.0)
    draws, after = [], []
    for _ in range(1500):
        kappa = rng.gamma(base.kappa_nd_a, 1.0 / base.kappa_nd_b)
        hy = replace(base, kappa_nd=kappa)
        st = sample_prior_state(6, 5, hy, rng, lam=1.0)
        after.append(K.update_kappa_nd(st, hy, rng).kappa_nd)
        draws.append(rng.gamma(base.kappa_nd_a, 1.0 / base.kappa_nd_b))
    assert ks_2samp(draws, after).pvalue > 1e-3
    wrong = []
    for _ in range(1500):  # power: the same update under a prior the angles did not come from
        hy = replace(base, kappa_nd=rng.gamma(base.kappa_nd_a, 1.0 / base.kappa_nd_b))
        st = sample_prior_state(6, 5, replace(hy, kappa_nd=3.0 * hy.kappa_nd), rng, lam=1.0)
        wrong.append(K.update_kappa_nd(st, hy, rng).kappa_nd)
    assert ks_2samp(draws, wrong).pvalue < 1e-6


# --------------------------------------------------------------- algebra
def _dense(x, theta, T, s_x, s_yh, s_yv):
    Fr = theta.size
    R = np.zeros((2 * Fr, 2))
    for f in range(Fr):
        c, s = np.cos(theta[f]), np.sin(theta[f])
        R[2 * f:2 * f + 2] = [[c, -s], [s, c]]
    L = 6 / np.sqrt(s_yh)
    mu = R @ np.array([L / 2, 0]) + np.column_stack([T.real, T.imag]).ravel()
    C = R @ np.diag([1 / s_yh, 1 / s_yv]) @ R.T + np.eye(2 * Fr) / s_x
    return mu, C, R


def test_marginal_likelihood_matches_dense_gaussian():
    rng = np.random.default_rng(0)
    Fr = 6
    theta = rng.uniform(-3, 3, Fr)
    T = rng.normal(size=Fr) + 1j * rng.normal(size=Fr)
    x = rng.normal(size=Fr) + 1j * rng.normal(size=Fr)
    mu, C, _ = _dense(x, theta, T, 7.0, 90.0, 300.0)
    xv = np.column_stack([x.real, x.imag]).ravel()
    assert marginal_loglik(x, theta, T, 7.0, 90.0, 300.0) == pytest.approx(multivariate_normal(mu, C).logpdf(xv))
    w = np.array([1, 0, 1, 1, 0, 1.0])
    keep = np.repeat(w > 0, 2)
    assert marginal_loglik(x, theta, T, 7.0, 90.0, 300.0, w) == pytest.approx(
        multivariate_normal(mu[keep], C[np.ix_(keep, keep)]).logpdf(xv[keep]))


def test_translation_conditional_matches_dense_algebra():
    rng = np.random.default_rng(1)
    Fr = 5
    theta = rng.uniform(-3, 3, Fr)
    sx, syh, syv = 7.0, 90.0, 300.0
    xs = rng.normal(size=(3, Fr)) + 1j * rng.normal(size=(3, Fr))
    J = rng.normal(size=Fr) + 1j * rng.normal(size=Fr)
    kids = rng.normal(size=(2, Fr)) + 1j * rng.normal(size=(2, Fr))
    mu0, C, R = _dense(xs[0], theta, np.zeros(Fr, complex), sx, syh, syv)
    Ci = np.linalg.inv(C)
    Lam = 3 * Ci + (2 * 30.0 + 50.0) * np.eye(2 * Fr)
    c2 = lambda z: np.column_stack([z.real, z.imag]).ravel()  # noqa: E731
    L = 6 / np.sqrt(syh)
    b = (Ci @ sum(c2(xi) - R @ [L / 2, 0] for xi in xs) + 30.0 * sum(c2(t) - R @ [L, 0] for t in kids)
         + 50.0 * c2(J))
    mean, c, e = translation_conditional(theta, sx, syh, syv, 3, xs.sum(0), J, 50.0, 2, kids.sum(0), 30.0)
    np.testing.assert_allclose(c2(mean), np.linalg.solve(Lam, b), atol=1e-10)
    Tt = rng.normal(size=Fr) + 1j * rng.normal(size=Fr)
    assert translation_conditional_logpdf(Tt, mean, theta, c, e) == pytest.approx(
        multivariate_normal(np.linalg.solve(Lam, b), np.linalg.inv(Lam)).logpdf(c2(Tt)))
    S = np.array([c2(translation_sample(mean, theta, c, e, rng)) for _ in range(20000)])
    np.testing.assert_allclose(np.cov(S.T), np.linalg.inv(Lam), atol=0.03 * np.abs(np.linalg.inv(Lam)).max())


def test_rotation_prior_is_normalised_and_sampled():
    """Per-frame normalised von Mises chain: quadrature of the density and draws agree."""
    rng = np.random.default_rng(2)
    par = np.array([0.3, -1.0])
    grid = np.linspace(-np.pi, np.pi, 400, endpoint=False)
    g1, g2 = np.meshgrid(grid, grid, indexing="ij")
    th = np.stack([g1, g2], -1)
    dens = np.exp(rotation_prior_logpdf(th, np.broadcast_to(par, th.shape), 1.0, 1.0))
    assert dens.sum() * (2 * np.pi / 400) ** 2 == pytest.approx(1.0, abs=1e-6)
    draws = sample_rotation_prior(np.broadcast_to(par, (20000, 2)), 1.0, 1.0, rng)
    m_draw = np.mean(np.cos(draws[:, 1]))
    m_quad = (dens * np.cos(g2)).sum() * (2 * np.pi / 400) ** 2
    assert m_draw == pytest.approx(m_quad, abs=0.02)
