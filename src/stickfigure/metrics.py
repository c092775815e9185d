"""Scores of a learned skeleton against ground truth.

Segmentation
    :func:`adjusted_rand_index` (scikit-learn) and the Hopkins 155
    :func:`misclassification_rate` (the share of points whose label is wrong
    under the best one-to-one matching of learned to true clusters).
Structure
    :func:`stick_to_part` maps each learned stick to the true part holding most
    of its points; :func:`edge_scores` maps the learned edges through it and
    compares them, undirected, with ``edges_true`` (precision, recall, F1 and
    the exact-structure flag). :func:`tree_consistency` does without the
    mapping, for skeletons coarser than the truth (a whole leg as one stick):
    the share of sticks whose true parts are one connected piece of the true
    tree, and of edges whose two sticks' parts together are.
Imputation
    :func:`imputation_rmse` over a mask of hidden entries.
Joints
    :func:`joint_position_error` (mean distance between learned and true joints
    of matched edges).

:func:`score_skeleton` returns every score the available ground truth allows.
Points whose true label is -1 (unknown) are left out of every segmentation
and structure score.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._validation import as_float_array, check_labels
from .skeleton import Skeleton
from .trajectories import Trajectories

__all__ = [
    "adjusted_rand_index",
    "misclassification_rate",
    "stick_to_part",
    "edge_scores",
    "tree_consistency",
    "imputation_rmse",
    "joint_position_error",
    "score_skeleton",
]


def _pair(labels_true: Any, labels_pred: Any) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(labels_true)
    if t.ndim != 1:
        raise ValueError(f"labels_true must have shape (P,), got {t.shape}")
    t = check_labels(t, t.shape[0], "labels_true")
    p = check_labels(labels_pred, t.shape[0], "labels_pred")
    keep = t >= 0
    if not keep.any():
        raise ValueError("labels_true has no known label (all -1)")
    return t[keep], p[keep]


def adjusted_rand_index(labels_true: Any, labels_pred: Any) -> float:
    """Adjusted Rand index of two segmentations (1 = identical up to renaming).

    Points with ``labels_true == -1`` are ignored; a predicted -1 (unassigned)
    counts as one more cluster.
    """
    from sklearn.metrics import adjusted_rand_score

    t, p = _pair(labels_true, labels_pred)
    return float(adjusted_rand_score(t, p))


def misclassification_rate(labels_true: Any, labels_pred: Any) -> float:
    """Hopkins 155 misclassification rate: wrongly labelled points under the best matching.

    Learned and true clusters are matched one to one so as to maximise the
    number of points whose labels agree (Hungarian algorithm on the contingency
    table, :func:`scipy.optimize.linear_sum_assignment`); the numbers of
    clusters may differ, and points in unmatched clusters (or predicted -1)
    count as errors.

    Returns
    -------
    float
        In [0, 1].
    """
    from scipy.optimize import linear_sum_assignment

    t, p = _pair(labels_true, labels_pred)
    ut, it = np.unique(t, return_inverse=True)
    p_ok = p >= 0
    up, ip = np.unique(p[p_ok], return_inverse=True)
    C = np.zeros((ut.size, max(up.size, 1)))
    np.add.at(C, (it[p_ok], ip), 1)
    r, c = linear_sum_assignment(-C)
    return float(1.0 - C[r, c].sum() / t.size)


def stick_to_part(labels_pred: Any, labels_true: Any, n_sticks: int | None = None) -> np.ndarray:
    """The true part holding most of each learned stick's points, shape (S,) (-1 for an empty stick).

    Ties go to the lower part number. Points with an unknown true label are ignored.
    """
    t = np.asarray(labels_true)
    t = check_labels(t, t.shape[0] if t.ndim == 1 else -1, "labels_true")
    p = check_labels(labels_pred, t.shape[0], "labels_pred")
    S = int(p.max(initial=-1)) + 1 if n_sticks is None else int(n_sticks)
    n_parts = int(t.max(initial=-1)) + 1
    out = -np.ones(S, np.int64)
    ok = (p >= 0) & (t >= 0)
    if n_parts == 0 or not ok.any():
        return out
    C = np.zeros((S, n_parts), np.int64)
    np.add.at(C, (p[ok], t[ok]), 1)
    has = C.sum(axis=1) > 0
    out[has] = np.argmax(C[has], axis=1)
    return out


def _undirected(edges: Any) -> set[tuple[int, int]]:
    return {(min(int(a), int(b)), max(int(a), int(b))) for a, b in edges if int(a) != int(b)}


def _structure_inputs(labels_pred: Any, edges_pred: Any, labels_true: Any, n_sticks: int | None
                      ) -> tuple[np.ndarray, np.ndarray, int, list[tuple[int, int]]]:
    """Checked true labels, learned labels, stick count and learned edges (a list: any iterable
    is read once); every learned edge must name sticks below that count."""
    t = np.asarray(labels_true)
    t = check_labels(t, t.shape[0] if t.ndim == 1 else -1, "labels_true")
    p = check_labels(labels_pred, t.shape[0], "labels_pred")
    S = int(p.max(initial=-1)) + 1 if n_sticks is None else int(n_sticks)
    edges = [(int(a), int(b)) for a, b in edges_pred]
    for a, b in edges:
        if not (0 <= a < S and 0 <= b < S):
            raise ValueError(f"edges_pred refers to stick {max(a, b)}, but there are {S} sticks")
    return t, p, S, edges


def edge_scores(
    labels_pred: Any,
    edges_pred: Any,
    labels_true: Any,
    edges_true: Any,
    n_sticks: int | None = None,
) -> dict[str, Any]:
    """Compare a learned tree with the true one through the stick-to-part mapping.

    Each learned edge ``(a, b)`` becomes ``(part(a), part(b))``; edges that map
    to a self-loop (both sticks on one true part) are dropped, duplicates count
    once. Precision, recall and F1 are over undirected edges. ``exact`` is True
    when the learned skeleton has as many sticks as there are true parts, the
    mapping is a bijection and the mapped edge set equals the true one.

    Returns
    -------
    dict
        ``edge_precision``, ``edge_recall``, ``edge_f1``, ``exact``, ``mapping``
        (list, stick -> part), ``edges_mapped`` (sorted list of pairs).
        Precision is NaN without learned edges, recall NaN without true edges;
        F1 is 0 when either is 0 or undefined while the other is not, and 1
        when both edge sets are empty.
    """
    t, p, S, edges_pred = _structure_inputs(labels_pred, edges_pred, labels_true, n_sticks)
    mapping = stick_to_part(p, t, S)
    mapped = {(mapping[a], mapping[b]) for a, b in edges_pred if mapping[a] >= 0 and mapping[b] >= 0}
    pred = _undirected(mapped)
    true = _undirected(edges_true)
    tp = len(pred & true)
    precision = tp / len(pred) if pred else float("nan")
    recall = tp / len(true) if true else float("nan")
    if not pred and not true:
        f1 = 1.0
    elif tp == 0:
        f1 = 0.0
    else:
        f1 = 2 * precision * recall / (precision + recall)
    n_parts = max(int(t.max(initial=-1)) + 1, 0)
    used = mapping[mapping >= 0]
    bijection = S == n_parts and used.size == S and np.unique(used).size == S
    exact = bool(bijection and pred == true)
    return {"edge_precision": precision, "edge_recall": recall, "edge_f1": f1, "exact": exact,
            "mapping": mapping.tolist(), "edges_mapped": sorted(pred)}


def tree_consistency(labels_pred: Any, edges_pred: Any, labels_true: Any, edges_true: Any,
                     n_sticks: int | None = None, *, detail: bool = False) -> dict[str, Any]:
    """Does a learned skeleton join its sticks as the true tree does, at its own coarseness?

    A stick is *coherent* when the true parts of its points form one connected
    piece of the true tree (``edges_true``): a stick holding a whole leg is, one
    holding an elbow and a knee marker is not. An edge is *anatomical* when the
    parts of its two sticks together form one connected piece: a leg stick joined
    to the pelvis stick is, a leg joined to the head is not. Unlike
    :func:`edge_scores` nothing is mapped to a majority part, so a coarse but
    correct skeleton scores well.

    Parameters
    ----------
    labels_pred : array_like of int, shape (P,)
    edges_pred : sequence of (int, int)
        Stick pairs.
    labels_true : array_like of int, shape (P,)
        -1 for points of no part (left out).
    edges_true : sequence of (int, int)
        Part pairs of the true tree.
    n_sticks : int, optional
    detail : bool
        Also name the failures: ``incoherent`` (the sticks that are not coherent)
        and ``non_anatomical`` (the edges that are not anatomical).

    Returns
    -------
    dict
        ``coherent_sticks``: the share of coherent sticks among those holding a
        point of a known part; ``anatomical_edges``: the share of anatomical
        edges among the learned edges between such sticks (NaN when there is none).
    """
    import networkx as nx

    t, p, S, edges_pred = _structure_inputs(labels_pred, edges_pred, labels_true, n_sticks)
    tree = nx.Graph()
    tree.add_nodes_from(range(int(t.max(initial=-1)) + 1))
    tree.add_edges_from(_undirected(edges_true))
    parts = [set(t[(p == s) & (t >= 0)].tolist()) for s in range(S)]

    def connected(nodes: set[int]) -> bool:
        return nx.is_connected(tree.subgraph(nodes))

    known = [s for s in range(S) if parts[s]]
    coherent = [connected(parts[s]) for s in known]
    judged = [(a, b) for a, b in edges_pred if parts[a] and parts[b]]
    anatomical = [connected(parts[a] | parts[b]) for a, b in judged]
    out: dict[str, Any] = {"coherent_sticks": float(np.mean(coherent)) if known else float("nan"),
                           "anatomical_edges": float(np.mean(anatomical)) if anatomical else float("nan")}
    if detail:
        out["incoherent"] = [s for s, ok in zip(known, coherent) if not ok]
        out["non_anatomical"] = [(int(a), int(b)) for (a, b), ok in zip(judged, anatomical) if not ok]
    return out


def imputation_rmse(predicted: Any, truth: Any, mask: Any, *, per: str = "coordinate") -> float:
    """Root-mean-square error of predictions on the hidden entries.

    Parameters
    ----------
    predicted, truth : array_like, shape (P, F, D)
    mask : array_like of bool, shape (P, F)
        The hidden entries to score.
    per : {"coordinate", "point"}
        ``"coordinate"`` (default): ``sqrt(mean over hidden entries and coordinates
        of the squared error)``, directly comparable with a per-coordinate noise
        std. ``"point"``: ``sqrt(mean over hidden entries of |error|^2)`` (sqrt(D)
        times larger for isotropic errors).

    Returns
    -------
    float
        NaN when the mask is empty.

    Raises
    ------
    ValueError
        Mismatched shapes, or a hidden entry with no prediction / no truth.
    """
    pred = as_float_array(predicted, "predicted", ndim=3, shape_text="(P, F, D)")
    tru = as_float_array(truth, "truth", shape=pred.shape, shape_text=f"{pred.shape}")
    m = np.asarray(mask)
    if m.shape != pred.shape[:2]:
        raise ValueError(f"mask must have shape {pred.shape[:2]}, got {m.shape}")
    m = m.astype(bool)
    if per not in ("coordinate", "point"):
        raise ValueError(f"per must be 'coordinate' or 'point', got {per!r}")
    if not m.any():
        return float("nan")
    e = pred[m] - tru[m]
    if np.isnan(e).any():
        bad = int(np.isnan(e).any(axis=1).sum())
        raise ValueError(f"{bad} hidden entries have no prediction or no true value (NaN)")
    sq = np.sum(e * e, axis=1)
    return float(np.sqrt(np.mean(sq) / (pred.shape[2] if per == "coordinate" else 1)))


def joint_position_error(skeleton: Skeleton, traj: Trajectories) -> float:
    """Mean distance between learned joints and the true joints of the edges they match.

    A learned edge matches a true edge when its sticks map (:func:`stick_to_part`)
    onto the true edge's two parts; the error of a matched edge is the mean,
    over frames where both are finite, of the distance between the learned
    joint and the true joint; the result is the mean over matched edges.

    Returns
    -------
    float
        NaN when nothing can be compared (no joints, no true joints, no matched edge).
    """
    if skeleton.joints is None or traj.joints_true is None or traj.labels_true is None or not traj.edges_true:
        return float("nan")
    if skeleton.joints.shape[1:] != traj.joints_true.shape[1:]:
        raise ValueError(f"skeleton joints {skeleton.joints.shape} and true joints {traj.joints_true.shape} "
                         "cover different frames or dimensions")
    mapping = stick_to_part(skeleton.labels, traj.labels_true, skeleton.n_sticks)
    true_index = {(min(a, b), max(a, b)): j for j, (a, b) in enumerate(traj.edges_true)}
    errors = []
    for e, (a, b) in enumerate(skeleton.edges):
        pa, pb = mapping[a], mapping[b]
        key = (min(pa, pb), max(pa, pb))
        if pa < 0 or pb < 0 or key not in true_index:
            continue
        learned = skeleton.joints[skeleton.edge_joints[e]]
        true = traj.joints_true[true_index[key]]
        d = np.linalg.norm(learned - true, axis=-1)
        if np.isfinite(d).any():
            errors.append(float(np.nanmean(d)))
    return float(np.mean(errors)) if errors else float("nan")


def score_skeleton(skeleton: Skeleton, traj: Trajectories) -> dict[str, Any]:
    """Every score the ground truth of ``traj`` allows.

    Parameters
    ----------
    skeleton : Skeleton
        Fitted to ``traj`` (same points; joints over the same frames).
    traj : Trajectories
        With ``labels_true`` (segmentation scores), ``edges_true`` (structure
        scores) and ``joints_true`` (joint error) where available.

    Returns
    -------
    dict
        ``n_sticks`` always; with labels: ``n_parts_true``, ``ari``,
        ``misclassification``; with edges too: ``edge_precision``, ``edge_recall``,
        ``edge_f1``, ``exact``, ``coherent_sticks``, ``anatomical_edges``; with true
        joints and learned joints: ``joint_error``.
    """
    if not isinstance(skeleton, Skeleton):
        raise TypeError(f"skeleton must be a Skeleton, got {type(skeleton).__name__}")
    if not isinstance(traj, Trajectories):
        raise TypeError(f"traj must be a Trajectories, got {type(traj).__name__}")
    if skeleton.n_points != traj.n_points:
        raise ValueError(f"the skeleton has {skeleton.n_points} points but traj has {traj.n_points}")
    out: dict[str, Any] = {"n_sticks": skeleton.n_sticks, "n_edges": len(skeleton.edges)}
    if traj.labels_true is None or not (traj.labels_true >= 0).any():
        return out
    out["n_parts_true"] = traj.n_parts_true
    out["ari"] = adjusted_rand_index(traj.labels_true, skeleton.labels)
    out["misclassification"] = misclassification_rate(traj.labels_true, skeleton.labels)
    if traj.edges_true is not None:
        sc = edge_scores(skeleton.labels, skeleton.edges, traj.labels_true, traj.edges_true, skeleton.n_sticks)
        out.update({k: sc[k] for k in ("edge_precision", "edge_recall", "edge_f1", "exact")})
        out.update(tree_consistency(skeleton.labels, skeleton.edges, traj.labels_true, traj.edges_true,
                                    skeleton.n_sticks))
        if skeleton.joints is not None and traj.joints_true is not None:
            out["joint_error"] = joint_position_error(skeleton, traj)
    return out
