"""Scores: known answers, invariances and errors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stickfigure as sf
from stickfigure import metrics as m


def test_ari_and_misclassification_known_answers():
    t = [0, 0, 0, 1, 1, 1, 2, 2]
    assert m.adjusted_rand_index(t, [5, 5, 5, 3, 3, 3, 9, 9]) == 1.0
    assert m.misclassification_rate(t, [5, 5, 5, 3, 3, 3, 9, 9]) == 0.0
    # one point wrong
    assert m.misclassification_rate(t, [1, 1, 0, 0, 0, 0, 2, 2]) == pytest.approx(1 / 8)
    # fewer predicted clusters: a whole true cluster is unmatched
    assert m.misclassification_rate(t, [0, 0, 0, 1, 1, 1, 1, 1]) == pytest.approx(2 / 8)
    # more predicted clusters: the smaller split-off part is wrong
    assert m.misclassification_rate(t, [0, 0, 4, 1, 1, 1, 2, 2]) == pytest.approx(1 / 8)
    # unknown true labels are ignored, unassigned predictions are errors
    assert m.misclassification_rate([0, 0, -1, 1], [0, -1, 1, 1]) == pytest.approx(1 / 3)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 4), min_size=2, max_size=30), st.permutations(range(5)))
def test_scores_are_invariant_to_renaming(labels, perm):
    t = np.array(labels)
    p = np.asarray(perm)[t]
    assert m.adjusted_rand_index(t, p) == pytest.approx(1.0)
    assert m.misclassification_rate(t, p) == 0.0


def test_stick_to_part_and_edge_scores():
    labels_true = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
    edges_true = [(0, 1), (1, 2)]
    # learned: stick 3 is a second piece of part 2 -> self-loop edge dropped
    labels_pred = np.array([1, 1, 1, 0, 0, 0, 2, 2, 3])
    mapping = m.stick_to_part(labels_pred, labels_true)
    np.testing.assert_array_equal(mapping, [1, 0, 2, 2])
    sc = m.edge_scores(labels_pred, [(1, 0), (0, 2), (2, 3)], labels_true, edges_true)
    assert sc["edge_precision"] == 1.0 and sc["edge_recall"] == 1.0 and sc["edge_f1"] == 1.0
    assert not sc["exact"]  # four sticks for three parts
    exact = m.edge_scores([1, 1, 1, 0, 0, 0, 2, 2, 2], [(0, 1), (0, 2)], labels_true, edges_true)
    assert exact["exact"] and exact["edges_mapped"] == [(0, 1), (1, 2)]
    wrong = m.edge_scores([1, 1, 1, 0, 0, 0, 2, 2, 2], [(1, 2), (0, 2)], labels_true, edges_true)
    assert wrong["edge_precision"] == 0.5 and wrong["edge_recall"] == 0.5 and not wrong["exact"]
    none = m.edge_scores([0] * 9, [], labels_true, edges_true)
    assert np.isnan(none["edge_precision"]) and none["edge_recall"] == 0.0 and none["edge_f1"] == 0.0


def test_imputation_rmse():
    truth = np.zeros((3, 4, 2))
    pred = truth.copy()
    pred[0, 1] = [3.0, 4.0]
    mask = np.zeros((3, 4), bool)
    mask[0, 1] = mask[2, 2] = True
    assert m.imputation_rmse(pred, truth, mask, per="point") == pytest.approx(np.sqrt(25 / 2))
    assert m.imputation_rmse(pred, truth, mask) == pytest.approx(np.sqrt(25 / 4))
    assert np.isnan(m.imputation_rmse(pred, truth, np.zeros((3, 4), bool)))
    pred[2, 2] = np.nan
    with pytest.raises(ValueError, match="no prediction"):
        m.imputation_rmse(pred, truth, mask)
    with pytest.raises(ValueError, match="mask"):
        m.imputation_rmse(truth, truth, np.ones(3, bool))
    with pytest.raises(ValueError, match="per"):
        m.imputation_rmse(truth, truth, mask, per="frame")


def test_score_skeleton_with_truth_and_joint_error():
    tr = sf.synthetic.random_figure(n_sticks=3, frames=20, noise=0.0, seed=1)
    skel = sf.Skeleton(method="sfm", labels=tr.labels_true, n_sticks=3, edges=list(tr.edges_true),
                       joints=tr.joints_true + 0.5, n_dims=2)
    sc = m.score_skeleton(skel, tr)
    assert sc["ari"] == 1.0 and sc["misclassification"] == 0.0 and sc["exact"]
    assert sc["edge_f1"] == 1.0 and sc["coherent_sticks"] == 1.0 and sc["anatomical_edges"] == 1.0
    assert sc["joint_error"] == pytest.approx(np.sqrt(0.5), rel=1e-9)
    bare = m.score_skeleton(skel, sf.Trajectories(tr.xy))
    assert set(bare) == {"n_sticks", "n_edges"}


def test_tree_consistency_on_a_coarse_and_a_wrong_skeleton():
    # True tree, a body in miniature: 0 pelvis - 1 thigh - 2 shin, 0 - 3 chest - 4 head; two points each.
    true = np.repeat(np.arange(5), 2)
    body = [(0, 1), (1, 2), (0, 3), (3, 4)]
    # Coarse but right: the leg (thigh and shin) one stick, hung from the pelvis; chest with head.
    coarse = np.array([0, 0, 1, 1, 1, 1, 2, 2, 2, 2])
    sc = m.tree_consistency(coarse, [(0, 1), (0, 2)], true, body)
    assert sc == {"coherent_sticks": 1.0, "anatomical_edges": 1.0}
    assert m.edge_scores(coarse, [(0, 1), (0, 2)], true, body)["edge_f1"] < 1.0  # the majority mapping is not
    # The leg hung from the head stick: one of two edges wrong.
    sc = m.tree_consistency(coarse, [(1, 2), (0, 2)], true, body)
    assert sc["anatomical_edges"] == 0.5 and sc["coherent_sticks"] == 1.0
    sc = m.tree_consistency(coarse, [(1, 2), (0, 2)], true, body, detail=True)
    assert sc["non_anatomical"] == [(1, 2)] and sc["incoherent"] == []
    # A stick holding a shin point and a head point is not a piece of the body; points of no
    # part (-1) are left out, and a stick holding only those counts for nothing.
    mixed = np.array([0, 0, 1, 1, 1, 1, 2, 2, 2, 1])
    assert m.tree_consistency(mixed, [], true, body)["coherent_sticks"] == pytest.approx(2 / 3)
    assert m.tree_consistency(mixed, [], true, body, detail=True)["incoherent"] == [1]
    assert np.isnan(m.tree_consistency(mixed, [], true, body)["anatomical_edges"])
    t2 = true.copy()
    t2[[4, 5]] = -1
    sc = m.tree_consistency(np.array([0, 0, 1, 1, 3, 3, 2, 2, 2, 2]), [(1, 3)], t2, body)
    assert sc["coherent_sticks"] == 1.0 and np.isnan(sc["anatomical_edges"])
    with pytest.raises(ValueError, match="edges_pred"):
        m.tree_consistency(coarse, [(0, 7)], true, body)


def test_score_errors():
    with pytest.raises(ValueError, match="labels_pred"):
        m.adjusted_rand_index([0, 1, 1], [0, 1])
    with pytest.raises(ValueError, match="all -1"):
        m.misclassification_rate([-1, -1], [0, 1])
    with pytest.raises(ValueError, match="edges_pred"):
        m.edge_scores([0, 1], [(0, 5)], [0, 1], [(0, 1)])
    tr = sf.synthetic.random_figure(n_sticks=2, frames=10, seed=0)
    with pytest.raises(ValueError, match="points"):
        m.score_skeleton(sf.Skeleton(method="sfm", labels=[0, 0], n_sticks=1), tr)
    with pytest.raises(TypeError):
        m.score_skeleton("model", tr)
