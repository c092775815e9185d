"""em's bridges (models/em/bridge.py): a point that bends a stick becomes a stick of its own."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import stickfigure as sf
from stickfigure.models.em import fit_stages
from stickfigure.models.em.bridge import (
    bridge_points,
    bridge_threshold,
    insert_bridge,
    lever_points,
)
from stickfigure.models.em.model import Priors, normalise, objective
from stickfigure.models.em.structure import (
    EMSettings,
    bic,
    components,
    merge_candidates,
    run_em,
)


@pytest.fixture(scope="module")
def star():
    """A 3-stick figure fitted from its true groups, and the same with one point put on a far stick."""
    traj = sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.01, seed=7)
    settings, priors = EMSettings(n_iter=100, resample_every=0), Priors()
    stages, sel, _, _ = fit_stages(traj, replace(settings, bridge_points=0), priors, np.random.default_rng(0),
                                   labels=traj.labels_true)
    st = stages[sel].state
    obs, _, _ = normalise(traj.xy)
    # The point farthest from another stick's points, moved onto that stick: a lever it must bend to.
    lab = st.labels
    best = (-1.0, 0, 0)
    for p in range(obs.n_points):
        for s in range(st.n_sticks):
            if s != lab[p]:
                d = float(np.mean(np.linalg.norm(obs.w[lab == s] - obs.w[p], axis=-1)))
                best = max(best, (d, p, s))
    _, p, s = best
    wrong = st.copy()
    wrong.labels = lab.copy()
    wrong.labels[p] = s
    wrong._design = None
    wrong, value, _ = run_em(wrong, obs, priors, settings, 60, np.random.default_rng(1), resample=False)
    return traj, st, wrong, value, p, obs, settings, priors


def test_the_screen_flags_only_the_foreign_point(star):
    traj, st, wrong, value, p, obs, settings, priors = star
    limit = bridge_threshold(obs)
    N = obs.mask.sum() * obs.n_dims
    assert limit == pytest.approx(0.25 * (3 * obs.n_frames + 9) * np.log(N))
    right = lever_points(st, obs, priors)
    assert right and max(x for x, _, _ in right) < limit  # a rigid figure has no lever point
    rows = lever_points(wrong, obs, priors)
    assert rows[0][2] == p and rows[0][1] == wrong.labels[p] and rows[0][0] > limit
    # Far ahead of the next (the bent stick's own points gain too when one of them leaves the
    # jointed model for a free refit, but p is the one it bends to).
    assert rows[0][0] > 3 * rows[1][0]


def test_insert_bridge_makes_a_one_point_stick_in_two_joints(star):
    traj, st, wrong, value, p, obs, settings, priors = star
    E = wrong.ends_per_stick
    j = int(np.flatnonzero(wrong.vertex_counts() >= 2)[0])
    e = int(np.flatnonzero(wrong.vertex_of == j)[0])
    out = insert_bridge(wrong, obs, priors, settings, p, e, np.random.default_rng(2))
    assert out is not None
    new, val, sweeps, record = out
    S = wrong.n_sticks
    assert new.n_sticks == S + 1 and record["point"] == p and record["detached"] == e // E
    assert np.flatnonzero(new.labels == S).tolist() == [p]
    others = np.arange(obs.n_points) != p
    np.testing.assert_array_equal(new.labels[others], wrong.labels[others])
    assert new.joints_per_stick()[S] == 2 and S in record["linked"]
    assert components(new)[0].max() == components(wrong)[0].max()  # still one tree
    assert sweeps > 0 and np.isfinite(val) and val == pytest.approx(objective(new, obs, priors))
    # Its free endpoint may not become a third joint: a 1-point stick would be a free hub.
    assert all(S not in set((c.ends // E).tolist()) for c in merge_candidates(new, settings))


def test_bridge_points_takes_the_point_off_the_stick_it_bent(star):
    traj, st, wrong, value, p, obs, settings, priors = star

    def crit(s, v):
        return bic(s, obs, v)

    new, val, sweeps, kept = bridge_points(wrong, obs, priors, settings, np.random.default_rng(3), value, crit, 2)
    assert len(kept) == 1 and kept[0]["point"] == p
    assert np.sum(new.labels == new.labels[p]) == 1 and crit(new, val) > crit(wrong, value)
    assert components(new)[0].max() == 0
    # On the right figure nothing passes the screen: the model comes back unchanged.
    v0 = objective(st, obs, priors)
    same, v, n, none = bridge_points(st, obs, priors, settings, np.random.default_rng(3), v0, crit, 2)
    assert none == [] and same is st and v == v0 and n == 0


def test_bridge_points_is_a_parameter(star):
    traj = star[0]
    with pytest.raises(ValueError, match="bridge_points"):
        sf.fit(traj, method="em", bridge_points=-1)
    sk = sf.fit(traj, method="em", random_state=0, labels=traj.labels_true, n_iter=60, bridge_points=0)
    assert all(s["bridged"] == [] for s in sk.info["stages"])


def test_a_bridge_stage_is_named_in_the_pictures():
    from stickfigure.plot.em import stage_kind

    assert stage_kind({"merged": None, "bridged": [{"point": 3, "detached": 0, "linked": [1, 4]}]}, 5) == "bridges"


def test_bridge_points_gives_the_same_model_in_one_process_or_two(star):
    # Half of a candidate's trials run in a forked child with n_jobs > 1; each trial draws from
    # its own generator, so the kept bridge and its fit are the same bits.
    traj, st, wrong, value, p, obs, settings, priors = star

    def crit(s, v):
        return bic(s, obs, v)

    one = bridge_points(wrong, obs, priors, replace(settings, n_jobs=1), np.random.default_rng(4), value, crit, 2)
    two = bridge_points(wrong, obs, priors, replace(settings, n_jobs=2), np.random.default_rng(4), value, crit, 2)
    assert one[1] == two[1] and one[2] == two[2] and one[3] == two[3]
    np.testing.assert_array_equal(one[0].labels, two[0].labels)
    np.testing.assert_array_equal(one[0].rot, two[0].rot)


@pytest.mark.parametrize("n_ends", [2, 5])
def test_insert_bridge_with_any_number_of_endpoints(n_ends):
    # n_ends has no upper bound: the new stick gets one endpoint in the joint and n_ends - 1 free.
    traj = sf.synthetic.random_figure(n_sticks=3, frames=40, noise=0.01, seed=7)
    obs, _, _ = normalise(traj.xy)
    settings = EMSettings(n_iter=40, resample_every=0, n_ends=n_ends, bridge_points=0)
    stages, sel, _, _ = fit_stages(traj, settings, Priors(), np.random.default_rng(0), labels=traj.labels_true,
                                   n_ends=n_ends)
    st = stages[sel].state
    j = int(np.flatnonzero(st.vertex_counts() >= 2)[0])
    e = int(np.flatnonzero(st.vertex_of == j)[0])
    p = int(np.flatnonzero(st.labels != e // n_ends)[0])
    new, _, _, record = insert_bridge(st, obs, Priors(), settings, p, e, np.random.default_rng(1))
    assert new.ends.shape == ((st.n_sticks + 1) * n_ends, 3) and record["point"] == p
    assert new.joints_per_stick()[-1] == 2
