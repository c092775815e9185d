"""Checking the initial sticks: split non-rigid ones, join rigidly moving pairs (an extension).

The paper takes the number of sticks from Affinity Propagation and never
changes it (resampling only moves single points). When the clustering puts
two parts into one group, or one part into two, the merge search cannot
repair it. After the first EM run (no joints yet) every stick is therefore
checked by BIC with a common noise level ``sigma^2`` (the median per-stick
residual variance, robust to the sticks being tested):

* split: the stick's points are clustered in two
  (:func:`stickfigure.segmentation.affinity_propagation_segments` with
  ``n_segments=2``), each half fitted by structure from motion; the split is
  kept when ``(RSS_one - RSS_two) / (2 sigma^2) > k/2 log N`` with
  ``k = F (3 + D)`` the extra motion parameters and N the number of observed
  coordinates;
* join: two sticks are made one when one stick's motion explains the other's
  points (each point's local coordinates refitted) at a loss below ``k/2 log N``
  in the same units.

Both change only sticks without joints, before any merge, so the model is
re-initialised from the new assignments (docs/em.md).
"""

from __future__ import annotations

import numpy as np

from .initialise import initial_state
from .model import Observations, Priors, StickState
from .updates import em_sweep

__all__ = ["noise_variance", "split_candidates", "join_candidates", "refine_labels"]


def _sfm_rss(obs: Observations, idx: np.ndarray, rng: np.random.Generator, n_iter: int = 60) -> float:
    """Residual sum of squares of one rigid orthographic body fitted to the points ``idx``.

    Structure from motion, refined by ``n_iter`` rotation/shape updates (the
    metric upgrade alone is poor for a handful of points: 4 points fit any
    affine motion exactly and leave the metric constraints to the noise).
    """
    sub = obs.take(idx)
    pri = Priors()
    st = initial_state(sub, np.zeros(idx.size, np.int64), 1, pri, rng, n_ends=2)
    for it in range(n_iter):
        em_sweep(st, sub, pri, global_rotations=it % 10 == 0, use_polar=it == 0)
    return float(st.design(sub).residual_sq(st.rot, st.trans, st.local)[0])


def noise_variance(st: StickState, obs: Observations) -> tuple[np.ndarray, float]:
    """Per-stick residual sums of squares (S,) and a robust noise variance per coordinate.

    Each stick's variance is corrected for the degrees of freedom its fit used
    (``3 + D`` motion parameters per frame it is seen in, 3 local coordinates per
    point), so sticks with few points do not look less noisy than they are; the
    noise variance is the lower quartile over sticks, so up to three quarters of
    the sticks may be bad without inflating it.
    """
    des = st.design(obs)
    rss = des.residual_sq(st.rot, st.trans, st.local)
    D = obs.n_dims
    n = des.n.sum(axis=1) * D
    seen = (des.n > 0).sum(axis=1)
    dof = n - seen * (3 + D) - 3 * np.bincount(st.labels, minlength=st.n_sticks)
    ok = dof > 0
    var = float(np.quantile(rss[ok] / dof[ok], 0.25)) if ok.any() else float(rss.sum() / max(n.sum(), 1))
    return rss, max(var, 1e-300)


def split_candidates(st: StickState, obs: Observations, rng: np.random.Generator, *, min_points: int
                     ) -> list[tuple[int, np.ndarray]]:
    """Sticks worth splitting in two: [(stick, labels of its points 0/1)]."""
    from ...segmentation import affinity_propagation_segments

    rss, var = noise_variance(st, obs)
    N = float(obs.mask.sum() * obs.n_dims)
    F, D = obs.n_frames, obs.n_dims
    penalty = 0.5 * F * (3 + D) * np.log(N)
    out = []
    for s in range(st.n_sticks):
        idx = np.flatnonzero(st.labels == s)
        if idx.size < 2 * max(min_points, 4):
            continue
        # Only sticks that fit clearly worse than the others can gain that much.
        if rss[s] / (2.0 * var) - obs.mask[idx].sum() * D / 2.0 < penalty:
            continue
        xy = np.where(obs.mask[idx][..., None] > 0, obs.w[idx], np.nan)
        halves = affinity_propagation_segments(xy, n_segments=2, random_state=rng)
        if np.bincount(halves, minlength=2).min() < min_points:
            continue
        two = sum(_sfm_rss(obs, idx[halves == h], rng) for h in (0, 1))
        if (rss[s] - two) / (2.0 * var) > penalty:
            out.append((s, halves))
    return out


def join_candidates(st: StickState, obs: Observations, priors: Priors) -> list[tuple[int, int]]:
    """Pairs of sticks that move as one rigid body, best first (each stick at most once).

    Joining b into a costs ``sum_{p in b} (|w_p - R_a l_pa - t_a|^2) - RSS_b`` with each
    point's coordinates refitted on a (:func:`assign.candidate_fits`, the same fit the
    resampling uses), i.e. a's motion has to explain b's points too; the pair is
    joined when the cheaper direction loses less than ``F (3 + D) / 2 log N`` (in units
    of ``2 sigma^2``), the motion parameters the join saves.
    """
    from .assign import candidate_fits

    S = st.n_sticks
    if S < 2:
        return []
    rss, var = noise_variance(st, obs)
    N = float(obs.mask.sum() * obs.n_dims)
    F, D = obs.n_frames, obs.n_dims
    penalty = 0.5 * F * (3 + D) * np.log(N)
    _, sq = candidate_fits(st, obs, priors)  # (P, S)
    moved = np.zeros((S, S))  # moved[b, a] = RSS of b's points on a
    np.add.at(moved, st.labels, sq)
    loss = (moved - rss[:, None]) / (2.0 * var)
    loss = np.minimum(loss, loss.T)
    np.fill_diagonal(loss, np.inf)
    found = [(float(loss[a, b]), (a, b)) for a in range(S) for b in range(a + 1, S) if loss[a, b] < penalty]
    used: set[int] = set()
    out = []
    for _, (a, b) in sorted(found):
        if a not in used and b not in used:
            out.append((a, b))
            used |= {a, b}
    return out


def refine_labels(st: StickState, obs: Observations, rng: np.random.Generator, *, min_points: int,
                  priors: Priors | None = None) -> tuple[np.ndarray, dict]:
    """New assignments after the split and join checks (unchanged when none applies)."""
    labels = st.labels.copy()
    S = st.n_sticks
    splits = split_candidates(st, obs, rng, min_points=min_points)
    joins = join_candidates(st, obs, priors or Priors())
    split_sticks = {s for s, _ in splits}
    for s, halves in splits:
        idx = np.flatnonzero(st.labels == s)
        labels[idx[halves == 1]] = S
        S += 1
    for a, b in joins:
        if a in split_sticks or b in split_sticks:
            continue
        labels[labels == b] = a
    _, labels = np.unique(labels, return_inverse=True)
    return labels, {"splits": [int(s) for s, _ in splits], "joins": [[int(a), int(b)] for a, b in joins]}
