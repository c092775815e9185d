"""em's bridges (models/em/bridge.py): a point that bends a stick becomes a stick of its own."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _figures import figure as _figure
from _figures import jointed

import stickfigure as sf
from stickfigure.models.em import fit_stages
from stickfigure.models.em.bridge import (
    bridge_points,
    bridge_threshold,
    insert_bridge,
    lever_points,
    split_pair,
    unpair_hubs,
)
from stickfigure.models.em.model import Priors, normalise, objective
from stickfigure.models.em.structure import (
    EMSettings,
    apply_merge,
    bic,
    components,
    merge_candidates,
    run_em,
    score_candidates,
    stick_edges,
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
    # It goes into the joint e left: one of its joints holds an endpoint that was on j, not a
    # free endpoint of a stick that was on j (which would make a new joint elsewhere).
    into = [x for x in np.flatnonzero(wrong.vertex_of == j) if x != e]
    own = set(new.vertex_of[E * S:E * (S + 1)].tolist())
    assert any(int(new.vertex_of[x]) in own for x in into)
    assert components(new)[0].max() == components(wrong)[0].max()  # still one tree
    assert sweeps > 0 and np.isfinite(val) and val == pytest.approx(objective(new, obs, priors))
    # Its free endpoint may not become a third joint: a 1-point stick would be a free hub.
    assert all(S not in set((c.ends // E).tolist()) for c in merge_candidates(new, settings))


def test_bridge_points_takes_the_point_off_the_stick_it_bent(star):
    traj, st, wrong, value, p, obs, settings, priors = star

    def crit(s, v):
        return bic(s, obs, v, priors)

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
        return bic(s, obs, v, priors)

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


# ----------------------------------------------------------------- 2-point hubs (unpair_hubs)
def _hub_figure(seed: int, frames: int = 120):
    """A pelvis (5 points) with two one-marker thighs on its end and a 4-point shin below each."""
    return _figure(seed, [-1, 0, 0, 1, 2], [0.6, 1.0, 1.0, 1.0, 1.0],
                   [[0, 0, 0], [0.6, 0, 0.15], [0.6, 0, -0.15], [1.0, 0, 0], [1.0, 0, 0]], [5, 1, 1, 4, 4], frames,
                   along=(0.2, 0.8), spread=0.2, root_motion=0.5)


def _lumped_hub(seed: int):
    """The hub figure with the two thigh markers on one stick, joined to the pelvis and both shins
    (the state CMU 85_02 left: LTHI+RTHI between the pelvis and the legs)."""
    traj = _hub_figure(seed)
    lab = traj.labels_true
    wrong = np.where(lab == 2, 1, np.where(lab > 2, lab - 1, lab))
    st, value, obs, settings, priors = jointed(traj, wrong, [{0, 1}, {1, 2}, {1, 3}])
    return traj, st, value, obs, settings, priors


@pytest.mark.parametrize("seed", [0, 1])
def test_unpair_hubs_parts_two_lumped_one_marker_segments(seed):
    traj, st, value, obs, settings, priors = _lumped_hub(seed)
    assert st.joints_per_stick().tolist() == [1, 3, 1, 1]  # the pair is the hub of three sticks
    p, q = np.flatnonzero(traj.labels_true == 1)[0], np.flatnonzero(traj.labels_true == 2)[0]

    def crit(s, v):
        return bic(s, obs, v, priors)

    new, val, sweeps, kept = unpair_hubs(st, obs, priors, settings, np.random.default_rng(1), value, crit)
    assert kept == [[p, q]] and sweeps > 0 and crit(new, val) > crit(st, value)
    assert new.n_sticks == 5 and components(new)[0].max() == 0
    # The known answer: the true groups and the true tree (stick numbers mapped through the points).
    from stickfigure.metrics import edge_scores

    assert len(set(zip(new.labels.tolist(), traj.labels_true.tolist()))) == 5
    scores = edge_scores(new.labels, stick_edges(new)[0], traj.labels_true, traj.edges_true)
    assert scores["edge_f1"] == 1.0 and scores["exact"]
    # On the right model nothing is tried: it comes back as it was.
    same, v, n, none = unpair_hubs(new, obs, priors, settings, np.random.default_rng(1), val, crit)
    assert none == [] and same is new and v == val and n == 0


def test_unpair_hubs_gives_the_same_model_in_one_process_or_two_and_spares_the_callers_stream():
    # Its trials are greedy trials (trials.greedy_trials): each draws from a generator spawned
    # from the caller's, so neither n_jobs nor the trials' own draws change what follows.
    traj, st, value, obs, settings, priors = _lumped_hub(1)
    settings = replace(settings, resample_every=10)  # so that a trial's EM run draws numbers

    def crit(s, v):
        return bic(s, obs, v, priors)

    rngs = [np.random.default_rng(1), np.random.default_rng(1)]
    one = unpair_hubs(st, obs, priors, replace(settings, n_jobs=1), rngs[0], value, crit)
    two = unpair_hubs(st, obs, priors, replace(settings, n_jobs=2), rngs[1], value, crit)
    assert one[3] == two[3] and len(one[3]) == 1
    assert one[1] == two[1] and one[2] == two[2]
    np.testing.assert_array_equal(one[0].labels, two[0].labels)
    np.testing.assert_array_equal(one[0].rot, two[0].rot)
    fresh = np.random.default_rng(1).random(3)
    np.testing.assert_array_equal(rngs[0].random(3), fresh)
    np.testing.assert_array_equal(rngs[1].random(3), fresh)


def test_split_pair_moves_each_joint_with_the_nearer_point():
    traj, st, value, obs, settings, priors = _lumped_hub(0)
    E = st.ends_per_stick
    out = split_pair(st, obs, priors, 1)
    assert out is not None and out.n_sticks == st.n_sticks + 1
    q = int(np.flatnonzero(out.labels == st.n_sticks)[0])
    # The pelvis and one shin stay with one point, the other shin goes with q: two trees.
    assert out.joints_per_stick()[1] + out.joints_per_stick()[-1] == 3
    assert components(out)[0].max() == 1
    shin_of_q = 2 if traj.labels_true[q] == 1 else 3  # the shin below q's thigh (stick numbers of st)
    mates = {int(x // E) for x in np.flatnonzero(np.isin(out.vertex_of, out.vertex_of[E * st.n_sticks:]))}
    assert shin_of_q in mates and 0 not in mates
    with pytest.raises(ValueError, match="stick of two"):
        split_pair(st, obs, priors, 0)


def test_unpair_is_a_parameter_and_a_named_stage():
    from stickfigure.plot.em import stage_kind

    traj = _hub_figure(0, frames=40)
    with pytest.raises(ValueError, match="unpair"):
        sf.fit(traj, method="em", unpair="yes")
    sk = sf.fit(traj, method="em", random_state=0, n_iter=40, unpair=False)
    assert all(s["unpaired"] == [] for s in sk.info["stages"])
    assert stage_kind({"merged": None, "unpaired": [[5, 6]]}, 4) == "pairs parted"


def test_two_one_point_sticks_are_linked_only_where_nothing_else_spans(monkeypatch):
    # A vertex of a 4-point stick and two 1-point sticks: the 1-point ones share a point
    # closely whatever they are, so the tree is the star from the other one.
    from types import SimpleNamespace

    import stickfigure.models.em.structure as structure

    residual = {(0, 1): 0.3, (0, 2): 0.2, (1, 2): 0.01}
    monkeypatch.setattr(structure, "joint_least_squares",
                        lambda st, sticks, k0: (None, residual[tuple(sorted(sticks))]))
    st = SimpleNamespace(labels=np.array([0, 0, 0, 0, 1, 2]), n_sticks=3, n_vertices=4, ends_per_stick=2,
                         vertex_of=np.array([0, 1, 0, 2, 0, 3]), ends=np.zeros((6, 3)),
                         stick_sizes=lambda: np.bincount(st.labels, minlength=st.n_sticks),
                         joints_per_stick=lambda: _joints_per_stick(st))
    assert stick_edges(st) == ([(0, 1), (0, 2)], [0, 0])
    # Two 2-point sticks may be a chain at that vertex: the residuals decide, as with three
    # 1-point sticks.
    for labels in ([0, 0, 0, 0, 1, 1, 2, 2], [0, 1, 2]):
        st.labels = np.array(labels)
        assert stick_edges(st) == ([(0, 2), (1, 2)], [0, 0])


def _joints_per_stick(st) -> np.ndarray:
    cnt = np.bincount(st.vertex_of, minlength=st.n_vertices)
    return (cnt[st.vertex_of] >= 2).reshape(st.n_sticks, -1).sum(axis=1)


def test_a_stick_joined_only_at_a_vertex_is_never_between_two_others(monkeypatch):
    # CMU 85_02 from 283/23 degrees: the head (4 points, no other joint), RSHO and RUPA
    # (1-point sticks, RSHO on the thorax 3, RUPA on the forearm 4) share one vertex. The
    # spanning tree of all three ran the shoulder through the head, whose residual with RUPA
    # is the smaller; the head is a leaf and hangs from the side holding more points.
    from types import SimpleNamespace

    import stickfigure.models.em.structure as structure

    residual = {(0, 1): 3.6e-6, (0, 2): 1.6e-6, (1, 2): 0.96e-6}
    monkeypatch.setattr(structure, "joint_least_squares",
                        lambda st, sticks, k0: (None, residual[tuple(sorted(sticks))]))
    labels = [0] * 4 + [1, 2] + [3] * 5 + [4] * 2
    st = SimpleNamespace(labels=np.array(labels), n_sticks=5, n_vertices=6, ends_per_stick=2,
                         vertex_of=np.array([0, 3, 0, 1, 0, 2, 1, 4, 2, 5]), ends=np.zeros((10, 3)),
                         stick_sizes=lambda: np.bincount(st.labels, minlength=st.n_sticks),
                         joints_per_stick=lambda: _joints_per_stick(st))
    assert stick_edges(st) == ([(0, 1), (1, 2), (1, 3), (2, 4)], [0, 0, 1, 2])
    # The forearm's side made the larger: the head hangs from RUPA.
    st.labels = np.array([0] * 4 + [1, 2] + [3] * 2 + [4] * 5)
    assert stick_edges(st)[0][:2] == [(0, 2), (1, 2)]
    # RUPA of two points, the head too: a 2-point leaf beside a through stick of more points
    # stays in the spanning tree, and may be a link of a chain there (CMU 85_02 from 254/33
    # degrees: LTHI+LKNE between the pelvis and the 1-point LSHN, hip and knee on one vertex).
    st.labels = np.array([0] * 2 + [1, 2, 2] + [3] * 5 + [4] * 2)
    residual.update({(0, 1): 1e-6, (0, 2): 1e-6, (1, 2): 9e-6})
    assert stick_edges(st)[0][:2] == [(0, 1), (0, 2)]
    # A head of four points with RUPA of two: the head hangs from RUPA, the through stick of
    # more than one point, whatever its residual with RSHO (placed CMU 131_01 from 181/15
    # degrees: the head, the 1-point LTHI and the pelvis; the hip ran through the head).
    st.labels = np.array([0] * 4 + [1, 2, 2] + [3] * 5 + [4] * 2)
    residual.update({(0, 1): 1e-9, (0, 2): 5e-6, (1, 2): 9e-6})
    assert stick_edges(st)[0][:2] == [(0, 2), (1, 2)]


def test_no_merge_makes_a_joint_of_one_point_sticks_only():
    # Two 1-point sticks turn freely about their points: a joint of theirs alone is fixed in
    # neither frame and ties nothing, while a criterion would still credit it as a joint.
    from stickfigure.models.em.initialise import initial_state

    traj = _hub_figure(0)
    obs, _, _ = normalise(traj.xy)
    settings, priors = EMSettings(n_iter=40, resample_every=0), Priors()
    rng = np.random.default_rng(0)
    st, _, _ = run_em(initial_state(obs, traj.labels_true, 5, priors, rng), obs, priors, settings, 40, rng)
    E = st.ends_per_stick
    assert np.bincount(st.labels).tolist() == [5, 1, 1, 4, 4]  # sticks 1 and 2: the thighs
    assert st.only_one_point_sticks(st.vertex_of[E * 1]) and not st.only_one_point_sticks(st.vertex_of[0])
    assert st.only_one_point_sticks(st.vertex_of[[E * 1, E * 2]])
    assert not st.only_one_point_sticks(st.vertex_of[[0, E * 1]])
    pairs = [set((c.ends // E).tolist()) for c in merge_candidates(st, replace(settings, max_candidates=None))]
    assert {1, 2} not in pairs and {0, 1} in pairs and {1, 3} in pairs
    # With the pelvis on the joint the second thigh may join it: the pelvis fixes where it is.
    c = next(c for c in merge_candidates(st, replace(settings, max_candidates=None))
             if set((c.ends // E).tolist()) == {0, 1})
    st = apply_merge(st, c, priors, settings, score_candidates(st, obs, priors, settings, [c], rng)[0])
    joined = [set((c.ends // E).tolist()) for c in merge_candidates(st, replace(settings, max_candidates=None))]
    assert {0, 1, 2} in joined and {1, 2} not in joined


def _y_figure(seed: int, frames: int = 120):
    """A torso (6 points) with a head (4) on its end and an arm (5) on a shoulder beside it."""
    return _figure(seed, [-1, 0, 0], [1.0, 0.5, 1.0], [[0, 0, 0], [1.0, 0, 0], [0.85, 0, 0.35]], [6, 4, 5], frames,
                   along=(0.1, 0.9), spread=0.15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_dissolved_link_hangs_its_part_where_its_near_point_went(seed):
    # A stick of a head point and the torso point nearest the shoulder, between the head and
    # the arm (CMU's RBHD+RSHO with the upper arm on it). Dissolved, the torso point goes back
    # to the torso, on the head's side: the arm hangs there, not on the head, which a
    # contraction of the stick's two joints would give.
    from stickfigure.models.em.initialise import initial_state
    from stickfigure.models.em.refine import dissolve_stick

    traj = _y_figure(seed)
    T = traj.labels_true
    obs, _, _ = normalise(traj.xy)
    joint = {frozenset(map(int, e)): traj.joints_true[k] for k, e in enumerate(traj.edges_true)}

    def dist(idx, j):  # (n,) mean image distance of the points idx from joint j
        return np.nanmean(np.linalg.norm(traj.xy[idx] - joint[frozenset(j)][None], axis=-1), axis=1)

    torso, heads = np.flatnonzero(T == 0), np.flatnonzero(T == 1)
    near = int(torso[np.argmin(dist(torso, {0, 2}))])  # the torso point nearest the shoulder
    head = int(heads[np.argmax(dist(heads, {0, 1}))])  # the head point farthest from the neck
    labels = T.copy()
    labels[[near, head]] = 3
    settings, priors = EMSettings(n_iter=100, resample_every=0), Priors()
    rng = np.random.default_rng(0)
    st, _, _ = run_em(initial_state(obs, labels, 4, priors, rng), obs, priors, settings, 100, rng)
    E = st.ends_per_stick
    for pair in ({0, 1}, {1, 3}, {2, 3}):
        cands = [c for c in merge_candidates(st, replace(settings, max_candidates=None))
                 if set((c.ends // E).tolist()) == pair]
        c = min(cands, key=lambda c: c.residual)
        st = apply_merge(st, c, priors, settings, score_candidates(st, obs, priors, settings, [c], rng)[0])
        st, _, _ = run_em(st, obs, priors, settings, 60, rng)
    assert sorted(map(sorted, stick_edges(st)[0])) == [[0, 1], [1, 3], [2, 3]]
    out = dissolve_stick(st, obs, priors, 3)
    assert out.labels[near] == 0 and np.all(out.labels[T == 2] == 2)
    assert sorted(map(sorted, stick_edges(out)[0])) == [[0, 1], [0, 2]]
    assert components(out)[0].max() == 0



def test_insert_bridge_scores_only_links_into_the_joint_it_left(star, monkeypatch):
    # The new stick may link to the endpoints still on e's joint, not to another (free) endpoint
    # of a stick on it: that makes a new joint elsewhere (on CMU 85_02 the right upper arm's
    # marker, bridged at the forearm's joint, was hung on the head's free end). Such a link is
    # offered here beside the search's own candidates, ranked first; it must not be scored.
    import stickfigure.models.em.structure as structure
    from stickfigure.models.em.structure import Candidate

    traj, st, wrong, value, p, obs, settings, priors = star
    E = wrong.ends_per_stick
    candidates, score = structure.merge_candidates, structure.score_candidates
    scored: list[np.ndarray] = []
    into: list[int] = []

    def offering(st_, settings_, seen=None):
        out = candidates(st_, settings_, seen)
        free = st_.vertex_counts()[st_.vertex_of] == 1
        S = st_.n_sticks - 1  # the new stick
        z = next(x for x in range(E * S, E * (S + 1)) if free[x])
        partners = {x // E for x in into}
        for y in np.flatnonzero(free[:E * S]):
            if y // E in partners and y not in into:
                v = sorted((int(st_.vertex_of[z]), int(st_.vertex_of[y])))
                out.append(Candidate(v[0], v[1], -1.0, np.array([z, y]), st_.ends[[z, y]].copy()))
        return out

    def recording(st_, obs_, priors_, settings_, cands, rng):
        scored.extend(np.asarray(c.ends) for c in cands)
        return score(st_, obs_, priors_, settings_, cands, rng)

    monkeypatch.setattr(structure, "merge_candidates", offering)
    monkeypatch.setattr(structure, "score_candidates", recording)
    tried = 0
    for j in np.flatnonzero(wrong.vertex_counts() >= 2):
        for e in np.flatnonzero(wrong.vertex_of == j):
            if np.count_nonzero(wrong.labels == e // E) < 2:
                continue
            scored.clear()
            into[:] = [int(x) for x in np.flatnonzero(wrong.vertex_of == j) if x != e]
            insert_bridge(wrong, obs, priors, settings, p, int(e), np.random.default_rng(2))
            assert scored and all(np.isin(ends, into).any() for ends in scored)
            tried += 1
    assert tried > 0
