"""The tree prior of Meeds et al. and the structure kernels that must leave it invariant.

Without likelihood the posterior is the prior, so every structure kernel
applied to exact prior draws must give back the prior's distribution over
configurations (partition + tree), which we know exactly by enumeration.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from scipy.stats import chisquare, ks_2samp

from stickfigure.models.mcmc import kernels as K
from stickfigure.models.mcmc.model import Hyper
from stickfigure.models.mcmc.prior import (
    ancestor_matrix,
    canonical_key,
    enumerate_configurations,
    log_tree_prior,
    sample_tree_prior,
    subtree_sizes,
)
from stickfigure.models.mcmc.state import Data, State, sample_prior_state

HYPER = Hyper(root_precision=1.0, update_lambda=False)
# Loose node priors for the structure-move tests: with the paper's hyper-parameters a
# prior draw's nodes are so tightly tied (joints within 0.1 of the parent's end) that
# the data-driven proposals of split-merge, swap, re-hang and sub-tree moves are
# essentially never accepted without a likelihood, and an invariance test of them would
# pass whatever they did. Here they are accepted 5-25% of the time.
LOOSE = Hyper(root_precision=1.0, update_lambda=False, b_sx=1000.0, kappa_rho=0.1, kappa_nd=0.1, a_sT=2.0, b_sT=2.0)
CFG = K.SweepConfig(likelihood=False, n_aux=2, n_launch=1)


def _exact(n_points: int, lam: float) -> dict:
    return {canonical_key(c, p): float(np.exp(lp)) for c, p, lp in enumerate_configurations(n_points, lam)}


def _chi2_pvalue(counts: Counter, exact: dict) -> float:
    keys = list(exact)
    assert set(counts) <= set(keys), "a kernel produced a configuration that is not a valid tree"
    n = sum(counts.values())
    obs = np.array([counts.get(k, 0) for k in keys], float)
    exp = np.array([exact[k] * n for k in keys])
    # Pool rare cells so the chi-square approximation holds.
    rare = exp < 5
    if rare.any():
        obs = np.append(obs[~rare], obs[rare].sum())
        exp = np.append(exp[~rare], exp[rare].sum())
    return float(chisquare(obs, exp).pvalue)


@pytest.mark.parametrize("n_points", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("lam", [0.3, 1.0, 2.5])
def test_configuration_probabilities_sum_to_one(n_points, lam):
    total = sum(np.exp(lp) for *_, lp in enumerate_configurations(n_points, lam))
    assert total == pytest.approx(1.0, abs=1e-12)


def test_counts_match_known_small_cases():
    # Two points: together (prob 1/(1+lam)) or apart (lam/(1+lam)), apart split into
    # siblings (1/2) and either chain (1/4 each: the parent must come first).
    lam = 1.7
    probs = {frozenset(p for p in k): v for k, v in _exact(2, lam).items()}
    together = [v for k, v in probs.items() if len(k) == 1]
    assert together == [pytest.approx(1 / (1 + lam))]
    apart = sorted(v for k, v in probs.items() if len(k) == 2)
    assert apart == pytest.approx(sorted([lam / (1 + lam) / 2, lam / (1 + lam) / 4, lam / (1 + lam) / 4]))


def test_generative_process_matches_closed_form():
    """Direct draws of the paper's urn-plus-permutation process follow log_tree_prior."""
    rng = np.random.default_rng(0)
    lam = 1.3
    exact = _exact(4, lam)
    counts = Counter(canonical_key(*sample_tree_prior(4, lam, rng)) for _ in range(6000))
    assert _chi2_pvalue(counts, exact) > 1e-3


def test_subtree_sizes_and_cycles():
    parent = np.array([-1, 0, 1, 0])
    counts = np.array([2, 3, 1, 4])
    np.testing.assert_allclose(subtree_sizes(counts, parent), [10, 4, 1, 4])
    with pytest.raises(ValueError, match="cycle"):
        ancestor_matrix(np.array([1, 0]))
    with pytest.raises(ValueError, match="feasible"):
        enumerate_configurations(9, 1.0)


def test_log_prior_is_label_free():
    rng = np.random.default_rng(1)
    c, parent = sample_tree_prior(12, 2.0, rng)
    counts = np.bincount(c)
    perm = rng.permutation(parent.size)  # relabel nodes
    inv = np.argsort(perm)
    parent2 = np.where(parent[perm] >= 0, inv[np.maximum(parent[perm], 0)], -1)
    assert log_tree_prior(counts[perm], parent2, 2.0) == pytest.approx(log_tree_prior(counts, parent, 2.0))


def _data(rng: np.random.Generator, n_points: int, n_frames: int) -> Data:
    x = rng.normal(size=(n_points, n_frames)) + 1j * rng.normal(size=(n_points, n_frames))
    return Data(x=x, observed=np.ones((n_points, n_frames), bool))


def _gibbs(st, data, rng, hyper=HYPER, stats=None):
    K.gibbs_indicators(st, data, hyper, rng, CFG, stats)
    return st


def _split_merge(st, data, rng, hyper=HYPER, stats=None):
    return K.split_merge(st, data, hyper, rng, CFG, stats)[0]


def _subtree(st, data, rng, hyper=HYPER, stats=None):
    K.subtree_move(st, data, hyper, rng, stats)
    return st


def _reverse(st, data, rng, hyper=HYPER, stats=None):
    return K.reverse_path(st, data, hyper, rng, stats)


def _reattach(st, data, rng, hyper=HYPER, stats=None):
    return K.reattach_move(st, data, hyper, rng, CFG, stats)[0]


def _swap(st, data, rng, hyper=HYPER, stats=None):
    return K.swap_move(st, data, hyper, rng, CFG, stats)[0]


def _rehang(st, data, rng, hyper=HYPER, stats=None):
    return K.rehang_move(st, data, hyper, rng, CFG, stats)[0]


STRUCTURE_KERNELS = {"gibbs": _gibbs, "split_merge": _split_merge, "subtree": _subtree,
                     "reverse_path": _reverse, "swap": _swap, "rehang": _rehang,
                     "reattach": _reattach}


def _param_stats(st: State) -> np.ndarray:
    """Label-free statistics of the node parameters: those of point 0's node and its parent link."""
    k = st.c[0]
    p = st.parent[k]
    J = np.zeros(st.T.shape[1], complex) if p < 0 else st.T[p] + np.exp(1j * st.theta[p]) * 6 / np.sqrt(st.s_yh[p])
    return np.array([st.T[k, 0].real, st.T[k, -1].imag, abs(st.T[k, 0] - J[0]), np.cos(st.theta[k, 0]),
                     np.sin(st.theta[k, -1]), np.log(st.s_x[k]), np.log(st.s_yh[k]), np.log(st.s_T[k])])


def _apply_to_prior_draws(kernel, n_draws: int, n_points: int, seed: int, repeats: int = 2, hyper: Hyper = HYPER,
                          n_frames: int = 2) -> tuple[Counter, np.ndarray, np.ndarray, K.MoveStats]:
    """Configurations and parameter statistics after ``kernel``, and of fresh prior draws."""
    rng = np.random.default_rng(seed)
    counts: Counter = Counter()
    stats = K.MoveStats()
    after, prior = [], []
    for _ in range(n_draws):
        prior.append(_param_stats(sample_prior_state(n_points, n_frames, hyper, rng, lam=1.0)))
        st = sample_prior_state(n_points, n_frames, hyper, rng, lam=1.0)
        data = _data(rng, n_points, n_frames)
        for _ in range(repeats):
            st = kernel(st, data, rng, hyper, stats)
        counts[canonical_key(st.c, st.parent)] += 1
        after.append(_param_stats(st))
    return counts, np.array(prior), np.array(after), stats


def _min_ks(a: np.ndarray, b: np.ndarray) -> float:
    return min(ks_2samp(a[:, j], b[:, j]).pvalue for j in range(a.shape[1]))


@pytest.mark.parametrize("name", sorted(STRUCTURE_KERNELS))
def test_structure_kernel_leaves_prior_invariant(name):
    """Exact prior draws pushed through the kernel keep the prior over configurations and parameters.

    Loose node priors (``LOOSE``), so that every kernel is accepted often enough
    for the test to see what it does (checked: at least 3% of its proposals).
    """
    counts, prior, after, stats = _apply_to_prior_draws(STRUCTURE_KERNELS[name], 500, 3, seed=11, hyper=LOOSE)
    assert _chi2_pvalue(counts, _exact(3, 1.0)) > 1e-3
    assert _min_ks(prior, after) > 1e-3 / prior.shape[1]
    if name != "gibbs":  # Gibbs has no rejections
        rate = sum(stats.accepted.values()) / sum(stats.proposed.values())
        assert rate > 0.03, f"{name} accepted only {rate:.3f} of its proposals: the test would be vacuous"


def test_invariance_check_has_power():
    """A kernel that ignores the prior (re-attach a random node to the root) is caught."""

    def to_root(st, data, rng, hyper, stats):
        k = int(rng.integers(st.K))
        st.parent[k] = -1
        return st

    counts, *_ = _apply_to_prior_draws(to_root, 500, 3, seed=11, repeats=1, hyper=LOOSE)
    assert _chi2_pvalue(counts, _exact(3, 1.0)) < 1e-4


def _lucky(rng):
    """A generator whose bare ``random()`` (the acceptance draw) always passes."""
    real = rng.random

    class Lucky:
        def __getattr__(self, name):
            return getattr(rng, name)

        def random(self, *a, **k):
            return real(*a, **k) if a or k else 1e-300

    return Lucky()


def test_parameter_check_has_power():
    """A re-hang whose uniform draws are all tiny, so that it accepts whatever its ratio (the
    re-fitted node's parameters then follow the data-driven proposal, not the prior), is
    caught by the parameter statistics."""

    def always(st, data, rng, hyper, stats):
        return K.rehang_move(st, data, hyper, _lucky(rng), CFG, stats)[0]

    _, prior, after, _ = _apply_to_prior_draws(always, 500, 3, seed=11, hyper=LOOSE)
    assert _min_ks(prior, after) < 1e-3 / prior.shape[1]


def test_reattach_check_has_power():
    """The re-attaching split-merge with its acceptance draw always passing is caught (its
    invariance test above is the same check on the real kernel)."""

    def always(st, data, rng, hyper, stats):
        return K.reattach_move(st, data, hyper, _lucky(rng), CFG, stats)[0]

    counts, *_ = _apply_to_prior_draws(always, 500, 3, seed=11, hyper=LOOSE)
    assert _chi2_pvalue(counts, _exact(3, 1.0)) < 1e-4


def test_internal_singleton_keeps_its_point():
    """Point 0 is alone at node 0, whose child explains it far better: it still cannot leave."""
    rng = np.random.default_rng(3)
    F = 6
    st = State(c=np.array([0, 1, 1, 1]), parent=np.array([-1, 0]), theta=np.zeros((2, F)),
               T=np.array([np.full(F, 50.0 + 0j), np.zeros(F, complex)]), s_x=np.full(2, 1e4),
               s_yh=np.full(2, 100.0), s_yv=np.full(2, 400.0), s_T=np.full(2, 100.0), lam=1.0)
    x = np.array([0.25, 0.3, 0.35, 0.2])[:, None] + 0.001 * rng.normal(size=(4, F))
    data = Data(x=x + 0j, observed=np.ones((4, F), bool))
    cfg = K.SweepConfig(n_aux=2)
    for _ in range(5):
        s = st.copy()
        K.gibbs_indicators(s, data, HYPER, rng, cfg)
        assert s.K == 2 and (s.c == s.c[0]).sum() == 1, "the internal singleton's point moved"
        assert np.all(s.c[1:] == s.c[1]) and s.parent[s.c[1]] == s.c[0]
    # Without the child the same point leaves at once.
    lone = State(c=np.array([0, 1, 1, 1]), parent=np.array([-1, -1]), theta=st.theta.copy(), T=st.T.copy(),
                 s_x=st.s_x.copy(), s_yh=st.s_yh.copy(), s_yv=st.s_yv.copy(), s_T=st.s_T.copy(), lam=1.0)
    K.gibbs_indicators(lone, data, HYPER, rng, cfg)
    assert lone.K == 1


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(STRUCTURE_KERNELS))
def test_structure_kernel_invariance_four_points(name):
    counts, prior, after, _ = _apply_to_prior_draws(STRUCTURE_KERNELS[name], 6000, 4, seed=5, hyper=LOOSE)
    assert _chi2_pvalue(counts, _exact(4, 1.0)) > 1e-3
    assert _min_ks(prior, after) > 1e-3 / prior.shape[1]


@pytest.mark.slow
def test_prior_chain_reproduces_node_counts():
    """A whole no-likelihood chain (every kernel, lambda fixed) samples the prior over K."""
    rng = np.random.default_rng(8)
    I = 5
    st = sample_prior_state(I, 2, HYPER, rng, lam=1.0)
    data = _data(rng, I, 2)
    ks = []
    for s in range(6000):
        st = K.sweep(st, data, HYPER, rng, CFG)
        if s % 3 == 0:
            ks.append(st.K)
    exact = Counter()
    for c, p, lp in enumerate_configurations(I, 1.0):
        exact[len(p)] += np.exp(lp)
    obs = Counter(ks)
    n = len(ks)
    kk = sorted(exact)
    # Thinned chain draws are nearly independent; allow for residual autocorrelation.
    stat = chisquare([obs.get(k, 0) for k in kk], [exact[k] * n for k in kk])
    assert stat.pvalue > 1e-4
