"""Synthetic figures of a given tree for the tests of em's moves (a helper module, not tests)."""

from __future__ import annotations

import numpy as np


def figure(seed: int, parent: list, lengths: list, attach: list, counts: list, frames: int, *,
           along: tuple[float, float], spread: float, root_motion: float = 1.0):
    """A random figure of the given tree: points ``along`` each stick's length, ``spread`` off it."""
    from scipy.spatial.transform import Rotation

    from stickfigure.synthetic import FigureSpec, _finish, _forward_kinematics, _smooth_rotvecs

    rng = np.random.default_rng(seed)
    n = len(parent)
    lengths, counts = np.asarray(lengths, float), np.asarray(counts)
    labels = np.repeat(np.arange(n), counts)
    local = np.concatenate([np.c_[rng.uniform(*along, c) * lengths[s], rng.normal(0, spread, (c, 2))]
                            for s, c in enumerate(counts)])
    spec = FigureSpec(parent=np.asarray(parent), attach=np.asarray(attach, float), lengths=lengths, local=local,
                      labels=labels)
    rest = rng.uniform(-np.pi, np.pi, size=(n, 1, 3))
    motion = _smooth_rotvecs(rng, n, frames, 0.9, False)
    motion[0] *= root_motion
    rel = Rotation.from_rotvec((rest + motion).reshape(-1, 3)).as_matrix().reshape(n, frames, 3, 3)
    pts, joints = _forward_kinematics(spec, rel, np.zeros((frames, 3)))
    return _finish(pts, joints, spec, rng, 0.01, (30.0, 20.0), False, {"generator": "test"}, frame_rate=30.0)


def jointed(traj, labels, pairs):
    """EM from ``labels`` (3 ends a stick), then each stick pair in ``pairs`` merged at its best joint."""
    from dataclasses import replace

    from stickfigure.models.em.initialise import initial_state
    from stickfigure.models.em.model import Priors, normalise
    from stickfigure.models.em.structure import EMSettings, apply_merge, merge_candidates, run_em, score_candidates

    obs, _, _ = normalise(traj.xy)
    settings, priors = EMSettings(n_iter=100, resample_every=0), Priors()
    rng = np.random.default_rng(0)
    st, value, _ = run_em(initial_state(obs, labels, int(labels.max()) + 1, priors, rng, n_ends=3), obs, priors,
                          settings, 100, rng)
    E = st.ends_per_stick
    for pair in pairs:
        cands = [c for c in merge_candidates(st, replace(settings, max_candidates=None))
                 if set((c.ends // E).tolist()) == pair]
        blocks = score_candidates(st, obs, priors, settings, cands, rng)
        b = int(np.argmax([c.score for c in cands]))
        st = apply_merge(st, cands[b], priors, settings, blocks[b])
        st, value, _ = run_em(st, obs, priors, settings, 100, rng)
    return st, value, obs, settings, priors
