"""The nonparametric prior over trees of Meeds et al. (section 2.2).

Generative process (section 2.2.1): points arrive one by one; point ``i`` joins an
occupied node with probability ``n_k / (lambda + i - 1)`` or starts a new node with
probability ``lambda / (lambda + i - 1)``; a new node's parent is uniform over the
occupied nodes and the root. Finally the points are randomly permuted.

Probability of a configuration
------------------------------
A configuration is a partition of the points into node sets ``C_1..C_K`` plus a
parent for every node set (another node set or the root); node labels carry no
meaning. Its probability under the process above is::

    P = lambda^K Gamma(lambda) / Gamma(lambda + I) * prod_k (n_k - 1)!     (Polya urn)
        * 1 / K!                                                            (parent choices)
        * prod_k n_k / N_k                                                  (order consistency)

where ``N_k`` is the number of points in the sub-tree rooted at ``k``. Derivation: the
urn gives every sequence with these block sizes the same probability; the ``j``-th
node to appear picks its parent among ``j`` candidates (``1/K!`` overall); and the
random permutation turns a configuration into the generated one only if every
node's first point comes after its parent's first point. The order in which the
blocks' first points arrive under a uniform permutation is that of independent
Exponential(n_k) clocks (min of n_k uniforms, mapped by ``-log(1 - t)``), and for a
forest the events "k precedes its whole sub-tree" are independent with
probabilities ``n_k / N_k`` (the weighted hook-length formula). The test suite
checks by exact enumeration that these probabilities sum to one and match the
generative process.

Consequences for inference (section 2.2.3)
------------------------------------------
* The exact Gibbs conditional of one point's indicator is not eqs. 11-12 but
  (counts ``n``, sub-tree sizes ``N`` without the point)::

      P(c_i = k)            ~ (n_k + 1)  prod_{a in path(k)} N_a / (N_a + 1)  F(x_i | phi_k)
      P(new child of node j) ~ lambda / (K + 1) prod_{a in path(j)} N_a / (N_a + 1)  F(x_i | phi_new)

  where ``path(k)`` is ``k`` and its ancestors (empty for the root). Eqs. 11-12 are the
  sequential "treat i as the last point" probabilities, which ignore the
  permutation; with them the sampler would not leave the prior invariant.
* An internal singleton (a node with one point and children) cannot lose its
  point: the configuration without it is not a tree. This is the paper's
  internal-singleton rule, and it falls out of the formula.
"""

from __future__ import annotations

from itertools import product
from typing import Hashable, Iterator

import numpy as np
from scipy.special import gammaln

__all__ = [
    "ancestor_matrix",
    "subtree_sizes",
    "depths",
    "log_tree_prior",
    "sample_tree_prior",
    "canonical_key",
    "enumerate_configurations",
]


def ancestor_matrix(parent: np.ndarray) -> np.ndarray:
    """A[j, a] = True when node ``a`` is ``j`` or one of its ancestors, shape (K, K)."""
    K = len(parent)
    A = np.zeros((K, K), dtype=bool)
    for j in range(K):
        a = j
        steps = 0
        while a >= 0:
            A[j, a] = True
            a = parent[a]
            steps += 1
            if steps > K:
                raise ValueError("parent array has a cycle")
    return A


def subtree_sizes(counts: np.ndarray, parent: np.ndarray, A: np.ndarray | None = None) -> np.ndarray:
    """Number of points in the sub-tree of every node, shape (K,)."""
    if A is None:
        A = ancestor_matrix(parent)
    return A.T.astype(float) @ np.asarray(counts, float)


def depths(parent: np.ndarray) -> np.ndarray:
    """Depth of every node (children of the root have depth 1), shape (K,)."""
    return ancestor_matrix(parent).sum(1)


def log_tree_prior(counts: np.ndarray, parent: np.ndarray, lam: float, A: np.ndarray | None = None) -> float:
    """log P(configuration) of the tree prior (see the module docstring).

    Parameters
    ----------
    counts : ndarray of int, shape (K,)
        Points at each node (all >= 1).
    parent : ndarray of int, shape (K,)
        Parent of each node, -1 for the root.
    lam : float
        Growth parameter.
    """
    counts = np.asarray(counts, float)
    K = counts.shape[0]
    I = counts.sum()
    N = subtree_sizes(counts, parent, A)
    return float(K * np.log(lam) + gammaln(lam) - gammaln(lam + I) + gammaln(counts + 1.0).sum()
                 - np.log(N).sum() - gammaln(K + 1.0))


def sample_tree_prior(n_points: int, lam: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One draw of (indicators, parents) from the generative process of section 2.2.1.

    Returns
    -------
    c : ndarray of int, shape (n_points,)
        Node of every point (nodes numbered in order of creation).
    parent : ndarray of int, shape (K,)
        Parent of every node, -1 for the root.
    """
    seq = np.empty(n_points, np.int64)
    counts: list[int] = []
    parent: list[int] = []
    for i in range(n_points):
        w = np.array(counts + [lam], float)
        k = int(rng.choice(len(w), p=w / w.sum()))
        if k == len(counts):
            counts.append(0)
            parent.append(int(rng.integers(len(parent) + 1)) - 1)  # uniform over root and occupied nodes
        counts[k] += 1
        seq[i] = k
    return seq[rng.permutation(n_points)], np.array(parent, np.int64)


def canonical_key(c: np.ndarray, parent: np.ndarray) -> Hashable:
    """A label-free key of a configuration: each node set with its parent's node set."""
    c = np.asarray(c)
    members = [tuple(np.flatnonzero(c == k).tolist()) for k in range(len(parent))]
    return frozenset((members[k], members[p] if p >= 0 else ()) for k, p in enumerate(parent))


def _set_partitions(n: int) -> Iterator[list[int]]:
    """Restricted growth strings of length n (every set partition once)."""
    def rec(prefix: list[int], m: int) -> Iterator[list[int]]:
        if len(prefix) == n:
            yield list(prefix)
            return
        for v in range(m + 2):
            prefix.append(v)
            yield from rec(prefix, max(m, v))
            prefix.pop()
    if n == 0:
        yield []
        return
    yield from rec([0], 0)


def enumerate_configurations(n_points: int, lam: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Every configuration of ``n_points`` points with its prior log-probability (small n only).

    Returns
    -------
    list of (c, parent, log_p)
    """
    if n_points > 6:
        raise ValueError(f"enumeration is only feasible for a few points, got n_points={n_points}")
    out = []
    for rgs in _set_partitions(n_points):
        c = np.array(rgs, np.int64)
        K = int(c.max()) + 1
        counts = np.bincount(c, minlength=K)
        for par in product(range(-1, K), repeat=K):
            parent = np.array(par, np.int64)
            if np.any(parent == np.arange(K)):
                continue
            try:
                A = ancestor_matrix(parent)
            except ValueError:
                continue
            out.append((c, parent, log_tree_prior(counts, parent, lam, A)))
    return out
