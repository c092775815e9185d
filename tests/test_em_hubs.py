"""em's hub splits (models/em/refine.split_hubs): a stick whose endpoints are all on joints, split in two."""

from __future__ import annotations

import numpy as np
import pytest
from _figures import figure, jointed

from stickfigure.metrics import adjusted_rand_index
from stickfigure.models.em.refine import apply_articulated_splits, split_hubs
from stickfigure.models.em.structure import bic, stick_edges


def _trunk_figure(seed: int, frames: int = 120):
    """A pelvis (4 points) with a leg (5); a thorax (4) on the pelvis with an arm (5) and a head (4)."""
    return figure(seed, [-1, 0, 0, 1, 1], [0.8, 0.8, 1.2, 1.0, 0.5],
                  [[0, 0, 0], [0.8, 0, 0], [0.0, 0, 0.3], [0.8, 0, 0.35], [0.8, 0, -0.1]], [4, 4, 5, 5, 4],
                  frames, along=(0.1, 0.9), spread=0.15, root_motion=0.5)


def _tree(st, labels_true):
    """The learned edges as pairs of true parts (each stick named by its points' part)."""
    part = [int(np.bincount(labels_true[st.labels == s]).argmax()) for s in range(st.n_sticks)]
    return {frozenset((part[a], part[b])) for a, b in stick_edges(st)[0]}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_hub_of_two_parts_is_split_with_each_joint_on_its_part(seed):
    # The pelvis and thorax as one stick holding the leg, the arm and the head: every endpoint
    # on a joint (CMU's torso stick). Split, the leg stays on the pelvis, the arm and the head go
    # with the thorax, and the pelvis and thorax are joined.
    traj = _trunk_figure(seed)
    T = traj.labels_true
    lumped = np.where(T == 1, 0, np.where(T > 1, T - 1, T))  # thorax on the pelvis's stick
    st, value, obs, settings, priors = jointed(traj, lumped, [{0, 1}, {0, 2}, {0, 3}])
    assert not (st.vertex_counts()[st.vertex_of[:3]] == 1).any()  # the hub has no free endpoint
    crit = lambda s, v: bic(s, obs, v, priors)  # noqa: E731
    new, val, _, split = split_hubs(st, obs, priors, settings, np.random.default_rng(0), value, crit)
    assert split == [0]
    assert crit(new, val) > crit(st, value)
    assert adjusted_rand_index(T, new.labels) == pytest.approx(1.0)
    assert _tree(new, T) == {frozenset(e) for e in [(0, 1), (0, 2), (1, 3), (1, 4)]}


def test_a_rigid_hub_is_left_alone():
    # The true groups: the pelvis holds the leg and the thorax, the thorax the arm and the head.
    # No stick bends, so nothing is split, whatever its joints.
    traj = _trunk_figure(0)
    T = traj.labels_true
    st, value, obs, settings, priors = jointed(traj, T, [{0, 1}, {0, 2}, {1, 3}, {1, 4}])
    crit = lambda s, v: bic(s, obs, v, priors)  # noqa: E731
    new, val, sweeps, split = split_hubs(st, obs, priors, settings, np.random.default_rng(0), value, crit)
    assert split == [] and sweeps == 0 and new is st


def test_a_hub_keeping_all_its_joints_on_one_piece_is_not_split():
    # Splitting a stick whose joints all lie nearer the piece it keeps would leave that piece no
    # endpoint for the joint with the new one: apply_articulated_splits leaves the model as it was.
    traj = _trunk_figure(0)
    T = traj.labels_true
    lumped = np.where(T == 1, 0, np.where(T > 1, T - 1, T))
    st, value, obs, settings, priors = jointed(traj, lumped, [{0, 1}, {0, 2}, {0, 3}])
    idx = np.flatnonzero(st.labels == 0)
    far = np.argsort(-np.min(np.linalg.norm(st.local[idx][:, None] - st.ends[None, :3], axis=-1), axis=1))[:1]
    second = np.zeros(idx.size, bool)
    second[far] = True  # one point, the farthest from every joint
    assert apply_articulated_splits(st, obs, priors, [(0, second)]) is st


def test_split_hubs_is_a_parameter_and_a_named_stage():
    import stickfigure as sf
    from stickfigure.plot.em import stage_kind

    traj = _trunk_figure(0, frames=40)
    with pytest.raises(ValueError, match="split_hubs"):
        sf.fit(traj, method="em", split_hubs="yes")
    sk = sf.fit(traj, method="em", random_state=0, n_iter=30, split_hubs=False)
    assert sk.info["settings"]["split_hubs"] is False
    assert all(s["hubs"] == [] for s in sk.info["stages"])
    assert stage_kind({"merged": None, "hubs": [2]}, 6) == "hubs split"
