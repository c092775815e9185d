"""How many joints an em stick may be on: the hub rule and the sub-tree moves' spare endpoint.

A stick has ``n_ends`` endpoints, so it is on at most that many joints. A body's
thorax is on four (neck, two shoulders, lumbar). ``hub_end`` gives one more endpoint to
the sticks with the most points (models/em/model.py, ``StickState.joint_capacity``).
``spare_end`` gives one more to every stick for the sub-tree moves
(models/em/tree.py, ``with_spare_endpoint``).
"""

from __future__ import annotations

import numpy as np
import pytest

import stickfigure as sf
from stickfigure.models.em import fit_stages
from stickfigure.models.em.model import (Priors, free_endpoint_terms, hub_endpoints, normalise, objective,
                                        structure_log_prior)
from stickfigure.models.em.structure import EMSettings, bic, merge_candidates, n_parameters, stick_edges
from stickfigure.models.em.tree import detach_endpoint, with_spare_endpoint, without_spare_endpoints


def _edges(edges):
    return sorted(tuple(sorted(map(int, e))) for e in edges)


@pytest.fixture(scope="module")
def fitted():
    """A 4-stick figure fitted from its true groups with three endpoints per stick."""
    traj = sf.synthetic.random_figure(n_sticks=4, frames=60, noise=0.01, seed=5)
    settings, priors = EMSettings(n_iter=100), Priors()
    stages, sel, _, _ = fit_stages(traj, settings, priors, np.random.default_rng(0), labels=traj.labels_true,
                                   n_ends=3)
    obs, _, _ = normalise(traj.xy)
    return traj, stages[sel].state, obs, settings, priors


def test_a_spare_endpoint_per_stick_and_back(fitted):
    traj, st, obs, settings, priors = fitted
    S, E = st.n_sticks, st.ends_per_stick
    wide = with_spare_endpoint(st, priors)
    assert wide.ends_per_stick == E + 1 and wide.n_vertices == st.n_vertices + S
    assert _edges(stick_edges(wide)[0]) == _edges(stick_edges(st)[0])
    # Each stick's old endpoints keep their places; the spare is last, alone on its vertex,
    # at the centroid of its stick's points.
    spare = np.arange(S) * (E + 1) + E
    np.testing.assert_array_equal(np.delete(wide.ends, spare, axis=0), st.ends)
    assert np.all(wide.vertex_counts()[wide.vertex_of[spare]] == 1)
    size = np.bincount(st.labels, minlength=S)
    centroid = np.stack([st.local[st.labels == s].mean(axis=0) for s in range(S)])
    np.testing.assert_allclose(wide.ends[spare], centroid)
    assert size.min() > 0 and np.isfinite(objective(wide, obs, priors))
    back = without_spare_endpoints(wide)
    assert back is not None and back.ends_per_stick == E
    for name in ("vertex_of", "ends", "mu_e", "tau_e", "mu_v", "tau_v", "alpha", "beta"):
        np.testing.assert_array_equal(getattr(back, name), getattr(st, name), err_msg=name)
    assert objective(back, obs, priors) == pytest.approx(objective(st, obs, priors), rel=1e-12)


def test_free_endpoints_and_the_bic(fitted):
    # A spare endpoint per stick explains nothing; its vertex chain alone adds about
    # D/2 log(tau_t / 2 pi) a frame to the objective (model.free_endpoint_terms). BIC with
    # free_ends=False leaves it out, so the wider model differs only by the structure prior
    # log P(G), whose weights d_j = n_j / (E S) change with E; the default counts it.
    traj, st, obs, settings, priors = fitted
    wide = with_spare_endpoint(st, priors)
    gain = objective(wide, obs, priors) - objective(st, obs, priors)
    prior = (structure_log_prior(wide.labels, wide.n_sticks, wide.vertex_of, wide.n_vertices)
             - structure_log_prior(st.labels, st.n_sticks, st.vertex_of, st.n_vertices))
    assert gain - prior > 2.0 * st.n_sticks * st.n_frames
    assert free_endpoint_terms(wide, obs, priors) - free_endpoint_terms(st, obs, priors) == pytest.approx(
        gain - prior, rel=1e-9)

    def change(free_ends):
        return (bic(wide, obs, objective(wide, obs, priors), priors, free_ends)
                - bic(st, obs, objective(st, obs, priors), priors, free_ends))

    assert change(False) == pytest.approx(prior, abs=1e-6 * abs(gain))
    assert change(True) == pytest.approx(gain, rel=1e-9)


def test_bic_free_ends_reaches_the_recorded_stages():
    # Stage 0 (no joints yet) is the same model either way; with bic_free_ends=False its
    # recorded BIC is lower by the terms of its 9 endpoints, all free.
    traj = sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.01, seed=2)
    kw = dict(random_state=0, labels=traj.labels_true, n_iter=60)
    counted = sf.fit(traj, method="em", **kw)
    left = sf.fit(traj, method="em", bic_free_ends=False, **kw)
    a, b = counted.info["stages"][0], left.info["stages"][0]
    assert a["objective"] == b["objective"] and a["labels"] == b["labels"]
    assert a["bic"] - b["bic"] > 2.0 * 3 * 3 * 60  # 9 free endpoints, 60 frames
    assert left.params["bic_free_ends"] is False
    with pytest.raises(ValueError, match="bic_free_ends"):
        sf.fit(traj, method="em", bic_free_ends="no", **kw)


@pytest.fixture(scope="module")
def one_point_limbs():
    """A hub of 8 points with three 1-point limbs, fitted from its true groups with the
    assignments held: the selected stage joins limbs 1 and 2 to the hub; limb 3 is free."""
    traj = sf.synthetic.star(n_limbs=3, frames=60, seed=1, hub_points=8, limb_points=1)
    settings = EMSettings(n_iter=100, refine_sticks=False, resample_every=0, unpair=False, bridge_points=0,
                          split_hubs=False)
    stages, sel, _, _ = fit_stages(traj, settings, Priors(), np.random.default_rng(0), labels=traj.labels_true,
                                   n_ends=3)
    obs, _, _ = normalise(traj.xy)
    return stages[sel].state, obs


def test_a_stick_turns_freely_about_the_line_through_two_anchors(one_point_limbs):
    # The premise of bic_rotations="identified": a 1-point stick on one joint turned about the
    # line through its point and its jointed endpoint, by another angle in every frame, moves
    # neither (nor any observation's prediction); only its free endpoints move.
    from scipy.spatial.transform import Rotation

    st, obs = one_point_limbs
    E, F = st.ends_per_stick, st.n_frames
    counts = st.vertex_counts()[st.vertex_of]
    s = 1
    assert np.count_nonzero(st.labels == s) == 1 and np.count_nonzero(counts[s * E:(s + 1) * E] >= 2) == 1
    p = int(np.flatnonzero(st.labels == s)[0])
    e = s * E + int(np.flatnonzero(counts[s * E:(s + 1) * E] >= 2)[0])
    x, k = st.local[p], st.ends[e]
    axis = (k - x) / np.linalg.norm(k - x)
    Q = Rotation.from_rotvec(np.random.default_rng(3).uniform(-1.0, 1.0, F)[:, None] * axis).as_matrix()
    turned = st.copy()
    turned.rot = st.rot.copy()
    turned.trans = st.trans.copy()
    turned.rot[s] = st.rot[s] @ Q  # (F, D, 3)
    turned.trans[s] = st.trans[s] + np.einsum("fdk,fk->fd", st.rot[s], x - Q @ x)
    np.testing.assert_allclose(turned.point_predictions(), st.point_predictions(), atol=1e-12)
    before, after = st.end_predictions(), turned.end_predictions()
    np.testing.assert_allclose(after[e], before[e], atol=1e-12)
    free = [i for i in range(s * E, (s + 1) * E) if i != e]
    assert all(np.abs(after[i] - before[i]).max() > 1e-3 for i in free)


def test_identified_rotations_in_the_parameter_count(one_point_limbs):
    # Hub: 8 points, 3 angles a frame either way. Limbs 1 and 2: a point and a joint, 2
    # identified angles. Limb 3: a point and no joint, none. So "identified" counts
    # (1 + 1 + 3) F fewer parameters; with only large sticks the two counts agree.
    st, obs = one_point_limbs
    assert sorted(map(tuple, stick_edges(st)[0])) == [(0, 1), (0, 2)]
    assert n_parameters(st, obs, "all") - n_parameters(st, obs, "identified") == 5 * st.n_frames
    logN = np.log(obs.mask.sum() * obs.n_dims)
    assert bic(st, obs, 0.0, Priors(), rotations="identified") - bic(st, obs, 0.0, Priors()) == pytest.approx(
        2.5 * st.n_frames * logN)
    with pytest.raises(ValueError, match="rotations"):
        n_parameters(st, obs, "some")


def test_identified_rotations_change_nothing_with_large_sticks(fitted):
    traj, st, obs, settings, priors = fitted
    assert np.bincount(st.labels).min() >= 3
    assert n_parameters(st, obs, "identified") == n_parameters(st, obs, "all")


def test_bic_rotations_reaches_the_recorded_stages():
    # Stage 0 (no joints yet) is the same model either way; its three 1-point limbs have one
    # anchor each, no identified angle, so its recorded BIC is higher by 9 F / 2 log N.
    traj = sf.synthetic.star(n_limbs=3, frames=60, seed=1, hub_points=8, limb_points=1)
    kw = dict(random_state=0, labels=traj.labels_true, n_iter=60, resample_every=0, refine_sticks=False)
    every = sf.fit(traj, method="em", **kw)
    identified = sf.fit(traj, method="em", bic_rotations="identified", **kw)
    a, b = every.info["stages"][0], identified.info["stages"][0]
    assert a["objective"] == b["objective"] and a["labels"] == b["labels"] == traj.labels_true.tolist()
    logN = np.log(2 * traj.n_points * traj.n_frames)
    assert b["bic"] - a["bic"] == pytest.approx(4.5 * traj.n_frames * logN)
    assert identified.params["bic_rotations"] == "identified"
    with pytest.raises(ValueError, match="bic_rotations"):
        sf.fit(traj, method="em", bic_rotations="some", **kw)


def test_no_spare_to_remove_from_a_full_stick():
    # The hub of a 3-limb star fitted with three endpoints is on a joint at every endpoint.
    traj = sf.synthetic.star(n_limbs=3, frames=60, seed=1)
    settings, priors = EMSettings(n_iter=100), Priors()
    stages, sel, _, _ = fit_stages(traj, settings, priors, np.random.default_rng(0), labels=traj.labels_true,
                                   n_ends=3)
    st = stages[sel].state
    assert _edges(stick_edges(st)[0]) == [(0, 1), (0, 2), (0, 3)]
    assert st.joints_per_stick()[0] == 3
    assert without_spare_endpoints(st) is None
    assert without_spare_endpoints(with_spare_endpoint(st, priors)) is not None


def _gained(st, cands):
    """The sticks each merge puts on a new joint (those of its endpoints that were alone)."""
    return [set((c.ends[st.vertex_counts()[st.vertex_of[c.ends]] == 1] // st.ends_per_stick).tolist())
            for c in cands]


def test_the_hub_rule_caps_every_stick_but_the_largest():
    # A small hub (4 points) with three larger limbs (7 each), one limb cut off: the hub is on
    # two joints. Without the rule it may take a third; with it, only the largest sticks (the
    # limbs) may use their last endpoint, so the hub offers none of its own to a merge.
    traj = sf.synthetic.star(n_limbs=3, frames=60, seed=1, hub_points=4, limb_points=7)
    settings, priors = EMSettings(n_iter=100, refine_sticks=False), Priors()
    stages, sel, _, _ = fit_stages(traj, settings, priors, np.random.default_rng(0), labels=traj.labels_true,
                                   n_ends=3)
    st = stages[sel].state
    assert _edges(stick_edges(st)[0]) == [(0, 1), (0, 2), (0, 3)]
    E = st.ends_per_stick
    e = int([x for x in np.flatnonzero(st.vertex_counts()[st.vertex_of] >= 2) if x // E == 1][0])
    cut = detach_endpoint(st, e, priors)
    assert cut.joints_per_stick().tolist() == [2, 0, 1, 1]
    assert np.all(cut.joint_capacity() == E) and cut.open_sticks().all()
    assert any(0 in g for g in _gained(cut, merge_candidates(cut, settings)))
    with hub_endpoints(True):
        np.testing.assert_array_equal(cut.joint_capacity(), [E - 1, E, E, E])
        np.testing.assert_array_equal(cut.open_sticks(), [False, True, True, True])
        cands = merge_candidates(cut, settings)
    assert np.all(cut.joint_capacity() == E)  # the switch is off again outside the block
    assert cands and not any(0 in g for g in _gained(cut, cands))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_hub_of_four_limbs_gets_all_four_with_the_hub_rule(seed):
    # Known answer: three endpoints hold three limbs; the fourth cannot join the hub. With
    # hub_end the hub (the stick with the most points) has a fourth endpoint.
    traj = sf.synthetic.star(n_limbs=4, frames=120, seed=seed)
    truth = _edges(traj.edges_true)
    plain = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, hub_end=False)
    assert _edges(plain.edges) != truth
    assert np.bincount(np.ravel(plain.edges), minlength=5)[0] <= 3
    hub = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, hub_end=True)
    assert _edges(hub.edges) == truth
    assert np.asarray(hub.state["ends"]).shape[0] == 5 * 4


def test_the_spare_endpoint_lets_a_full_hub_take_back_its_limb():
    # Known answer: a 4-limb star joined into one tree (max_trees=1) with three endpoints a
    # stick. Here the search hangs limb 2 on limb 3; the hub is on a joint at all three of its
    # endpoints, so the sub-tree move has nowhere right to put it. With a spare endpoint a
    # stick it moves limb 2 to the hub, and the spare endpoints stay (the hub is on four).
    traj = sf.synthetic.star(n_limbs=4, frames=120, seed=2)
    truth = _edges(traj.edges_true)
    plain = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, max_trees=1, spare_end=False,
                   hub_end=False)
    assert _edges(plain.edges) != truth and (2, 3) in _edges(plain.edges)
    spare = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, max_trees=1, spare_end=True,
                   hub_end=False)
    assert _edges(spare.edges) == truth
    moves = [m for s in spare.info["stages"] for m in s["reattached"]]
    assert moves == [{"sticks": [0, 2], "was": [2, 3]}]
    assert np.asarray(spare.state["ends"]).shape[0] == 4 * spare.n_sticks


def test_spare_end_and_hub_end_are_parameters():
    traj = sf.synthetic.random_figure(n_sticks=3, frames=60, seed=7)
    for name in ("spare_end", "hub_end"):
        with pytest.raises(ValueError, match=name):
            sf.fit(traj, method="em", **{name: "yes"})
    sk = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, n_iter=60, spare_end=False,
                hub_end=False)
    assert np.asarray(sk.state["ends"]).shape[0] == 3 * sk.n_sticks
