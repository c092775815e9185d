"""em's sub-tree moves (models/em/tree.py): a part hung from the wrong stick is moved back."""

from __future__ import annotations

import numpy as np
import pytest

import stickfigure as sf
from stickfigure.models.em import fit_stages
from stickfigure.models.em.model import Priors, normalise, objective
from stickfigure.models.em.structure import EMSettings, apply_merge, bic, merge_candidates, run_em, stick_edges
from stickfigure.models.em.structure import components
from stickfigure.models.em.tree import cut_proposals, detach_endpoint, join_trees, reattach_subtrees


@pytest.fixture(scope="module")
def star():
    """A 3-stick figure (one stick with two children), fitted from its true groups."""
    traj = sf.synthetic.random_figure(n_sticks=3, frames=60, noise=0.01, seed=7)
    settings, priors = EMSettings(n_iter=100), Priors()
    stages, sel, _, _ = fit_stages(traj, settings, priors, np.random.default_rng(0), labels=traj.labels_true)
    obs, _, _ = normalise(traj.xy)
    return traj, stages[sel].state, obs, settings, priors


def _norm(edges):
    return sorted(tuple(sorted(e)) for e in edges)


def _rewired(star):
    """The fitted figure with its leaf's joint cut and the leaf joined to the other child instead."""
    traj, st, obs, settings, priors = star
    edges, verts = stick_edges(st)
    deg = np.bincount(np.ravel(edges), minlength=st.n_sticks)
    leaf = int(np.flatnonzero(deg == 1)[0])
    other = int(({0, 1, 2} - {leaf, int(np.argmax(deg))}).pop())
    E = st.ends_per_stick
    j = verts[[i for i, e in enumerate(edges) if leaf in e][0]]
    e = int([x for x in np.flatnonzero(st.vertex_of == j) if x // E == leaf][0])
    cut = detach_endpoint(st, e, priors)
    c = [c for c in merge_candidates(cut, settings) if set((c.ends // E).tolist()) == {leaf, other}][0]
    wrong = apply_merge(cut, c, priors, settings, None)
    wrong, value, _ = run_em(wrong, obs, priors, settings, 100, np.random.default_rng(1))
    return wrong, value, leaf, other


def test_detach_endpoint_cuts_the_tree(star):
    traj, st, obs, settings, priors = star
    E = st.ends_per_stick
    j = int(np.flatnonzero(st.vertex_counts() >= 2)[0])
    e = int(np.flatnonzero(st.vertex_of == j)[0])
    cut = detach_endpoint(st, e, priors)
    assert cut.n_vertices == st.n_vertices + 1 and cut.vertex_of[e] == st.n_vertices
    assert np.sum(cut.vertex_of == j) == np.sum(st.vertex_of == j) - 1
    assert len(stick_edges(cut)[0]) == len(stick_edges(st)[0]) - 1
    partner = int([x for x in np.flatnonzero(st.vertex_of == j) if x != e][0] // E)
    assert tuple(sorted((int(e // E), partner))) not in set(map(tuple, map(sorted, stick_edges(cut)[0])))
    np.testing.assert_allclose(cut.mu_v[-1], st.mu_e[e])
    assert np.all(np.isfinite(objective(cut, obs, priors)))


def test_a_fitted_tree_offers_no_cut(star):
    traj, st, obs, settings, priors = star
    assert cut_proposals(st, obs, 0.8) == []
    value = objective(st, obs, priors)
    same, v, n, moves = reattach_subtrees(st, obs, priors, settings, np.random.default_rng(0), value,
                                          lambda s, val: bic(s, obs, val, priors))
    assert moves == [] and same is st and v == value and n == 0


def test_leaf_hung_from_the_wrong_stick_is_moved_back(star):
    # Known answer: the leaf's joint is cut and the leaf joined to the other child, and EM
    # re-fitted (the tree a greedy merge or a contracted stick can leave). The least-squares
    # joint of the leaf with its true parent is far better than its joint with the other
    # child, so the cut is proposed; the merge scoring picks the true link and BIC keeps it.
    traj, st, obs, settings, priors = star
    wrong, value, leaf, other = _rewired(star)
    assert _norm(stick_edges(wrong)[0]) != _norm(stick_edges(st)[0])
    props = cut_proposals(wrong, obs, 0.8)
    assert props and props[0][0] < 0.1
    back, v, n, moves = reattach_subtrees(wrong, obs, priors, settings, np.random.default_rng(2), value,
                                          lambda s, val: bic(s, obs, val, priors))
    assert _norm(stick_edges(back)[0]) == _norm(stick_edges(st)[0])
    assert len(moves) == 1 and set(moves[0]["was"]) == {leaf, other} and n > 0
    assert bic(back, obs, v, priors) > bic(wrong, obs, value, priors)
    # The joint is back where it was: the leaf's joint with its parent.
    E = st.ends_per_stick

    def leaf_joint(s):
        shared = np.flatnonzero(s.vertex_counts() >= 2)
        return s.mu_v[[j for j in shared if leaf in np.flatnonzero(s.vertex_of == j) // E][0]]

    assert np.sqrt(np.mean(np.sum((leaf_joint(back) - leaf_joint(st)) ** 2, axis=-1))) < 0.05


def test_reattach_is_a_parameter(star):
    traj = star[0]
    labels = traj.labels_true
    sk = sf.fit(traj, method="em", random_state=0, labels=labels, n_iter=60, reattach=False)
    assert all(s["reattached"] == [] for s in sk.info["stages"])


def test_join_trees_rejoins_a_cut_leaf_where_it_belongs(star):
    # Known answer: the leaf's joint cut leaves a forest of two trees; joined down to one, the
    # leaf goes back to its true parent (the best-scoring merge between the trees).
    traj, st, obs, settings, priors = star
    edges, verts = stick_edges(st)
    deg = np.bincount(np.ravel(edges), minlength=st.n_sticks)
    leaf = int(np.flatnonzero(deg == 1)[0])
    E = st.ends_per_stick
    j = verts[[i for i, e in enumerate(edges) if leaf in e][0]]
    e = int([x for x in np.flatnonzero(st.vertex_of == j) if x // E == leaf][0])
    cut = detach_endpoint(st, e, priors)
    cut, value, _ = run_em(cut, obs, priors, settings, 50, np.random.default_rng(1))
    assert components(cut)[0].max() == 1 and len(stick_edges(cut)[0]) == 1
    same, v2, n0, none = join_trees(cut.copy(), obs, priors, settings, np.random.default_rng(2), value, 2)
    assert none == [] and n0 == 0 and v2 == value  # already within max_trees: nothing to do
    joined, _, sweeps, done = join_trees(cut, obs, priors, settings, np.random.default_rng(2), value, 1)
    assert len(done) == 1 and leaf in done[0] and sweeps > 0
    assert components(joined)[0].max() == 0
    assert _norm(stick_edges(joined)[0]) == _norm(edges)
