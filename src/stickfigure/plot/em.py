"""Diagnostics of the "em" method (Ross, Tarlow & Zemel): the structure at every merge stage
and the objective against stage (the paper's Figs. 4-6, top and bottom-left).

Every stage is drawn on the frame the fit recorded (``info["reference_frame"]``,
the frame with the most visible points): points coloured by the stage's sticks,
each stick as lines between its joints (or along its points when it has fewer
than two), joints as white circles. The stage the selection criterion picked is
framed. Overlays of the selected skeleton on chosen frames use the generic
:func:`stickfigure.plot.plot_frames`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..skeleton import Skeleton
from ..trajectories import Trajectories

__all__ = ["stage_kind", "plot_stage", "plot_stages", "plot_objective", "figure"]


def _check(skeleton: Skeleton) -> list[dict]:
    stages = skeleton.info.get("stages") if skeleton.method == "em" else None
    if not stages:
        raise ValueError(f"need a skeleton fitted by em (with its merge stages), got one from {skeleton.method!r}")
    return stages


def _xy(traj: Trajectories | np.ndarray | None, frame: int) -> np.ndarray | None:
    if traj is None:
        return None
    xy = traj.xy if isinstance(traj, Trajectories) else np.asarray(traj, dtype=float)
    if xy.ndim != 3 or xy.shape[2] != 2:
        raise ValueError(f"traj must hold 2D trajectories (P, F, 2), got shape {xy.shape}")
    if not 0 <= frame < xy.shape[1]:
        raise ValueError(f"frame {frame} is outside the {xy.shape[1]} frames of traj")
    return xy[:, frame]


def _stick_lines(stage: dict, pts: np.ndarray | None) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Line segments per stick, the stick of each segment and the joint positions of a stage."""
    from scipy.sparse.csgraph import minimum_spanning_tree

    labels = np.asarray(stage["labels"])
    vertex_of = np.asarray(stage["vertex_of"])
    ends = np.asarray(stage["ends_xy"], dtype=float)
    joints = np.asarray(stage["joints_xy"], dtype=float)
    S = int(stage["n_sticks"])
    E = vertex_of.size // max(S, 1)
    count = np.bincount(vertex_of, minlength=joints.shape[0])
    segs: list[np.ndarray] = []
    owner: list[int] = []
    for s in range(S):
        mine = np.arange(E * s, E * (s + 1))
        anchors = ends[mine[count[vertex_of[mine]] >= 2]]
        member = pts[labels == s] if pts is not None else np.zeros((0, 2))
        member = member[np.isfinite(member).all(axis=1)]
        if anchors.shape[0] >= 2:
            d = np.linalg.norm(anchors[:, None] - anchors[None], axis=2)
            tree = minimum_spanning_tree(d + 1e-12).tocoo()
            for a, b in zip(tree.row, tree.col):
                segs.append(np.stack([anchors[a], anchors[b]]))
                owner.append(s)
        elif anchors.shape[0] == 1 and member.shape[0]:
            far = member[np.argmax(np.linalg.norm(member - anchors[0], axis=1))]
            segs.append(np.stack([anchors[0], far]))
            owner.append(s)
        elif member.shape[0] >= 2:
            c = member.mean(axis=0)
            _, _, Vt = np.linalg.svd(member - c, full_matrices=False)
            proj = (member - c) @ Vt[0]
            segs.append(np.stack([c + proj.min() * Vt[0], c + proj.max() * Vt[0]]))
            owner.append(s)
    return segs, np.asarray(owner, dtype=int), joints[count >= 2]


def stage_kind(stage: dict, index: int) -> str:
    """What made a stage (for titles): the first EM run, a merge, or one of the moves after the
    search (re-split pairs, dissolved sticks, the held-out check, trees joined to ``max_trees``,
    pairs parted, bridges, hubs split, sub-tree moves; docs/em.md section 6)."""
    if stage.get("merged") is not None:
        return "merge"
    if stage.get("joined"):
        return "trees joined"
    if stage.get("bridged"):
        return "bridges"
    if stage.get("unpaired"):
        return "pairs parted"
    if stage.get("hubs"):
        return "hubs split"
    if stage.get("reattached"):
        return "sub-tree moves"
    if stage.get("heldout"):
        return "held-out check"
    if stage.get("dissolved") and stage.get("moved"):
        return "re-split, dissolved"
    if stage.get("dissolved"):
        return "dissolved"
    if stage.get("moved"):
        return "re-split"
    return "EM" if index == 0 else "after the search"


def plot_stage(skeleton: Skeleton, stage: int, traj: Trajectories | np.ndarray | None = None, ax: Any = None, *,
               image_y_down: bool | None = None, point_size: float = 14.0, title: bool = True) -> Any:
    """Draw the structure of one merge stage on the recorded reference frame.

    Parameters
    ----------
    skeleton : Skeleton
        Fitted by method "em".
    stage : int
        0 (no joints) to the number of merges.
    traj : Trajectories or ndarray (P, F, 2), optional
        The trajectories the skeleton was fitted to (for the points).
    ax : matplotlib Axes, optional
    image_y_down : bool, optional
        Draw with y pointing down (default: when ``traj.image_size`` is set).

    Returns
    -------
    matplotlib Axes
    """
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    from . import stick_colors

    stages = _check(skeleton)
    if not -len(stages) <= stage < len(stages):
        raise ValueError(f"stage must be in 0 .. {len(stages) - 1}, got {stage}")
    st = stages[stage]
    if ax is None:
        _, ax = plt.subplots(figsize=(3.2, 3.2))
    frame = int(skeleton.info.get("reference_frame", 0))
    pts = _xy(traj, frame)
    labels = np.asarray(st["labels"])
    colors = stick_colors(int(st["n_sticks"]))
    segs, owner, joints = _stick_lines(st, pts)
    if segs:
        ax.add_collection(LineCollection(segs, colors=colors[owner], linewidths=3.0, zorder=2))
    if pts is not None:
        ok = np.isfinite(pts).all(axis=1)
        ax.scatter(pts[ok, 0], pts[ok, 1], s=point_size, c=colors[labels[ok]], edgecolors="k", linewidths=0.3,
                   zorder=3)
    if joints.size:
        ax.scatter(joints[:, 0], joints[:, 1], s=45, facecolors="white", edgecolors="k", linewidths=1.0, zorder=4)
    allxy = [a for a in (pts, joints, *segs) if a is not None and a.size]
    if allxy:
        xy = np.concatenate([a.reshape(-1, 2) for a in allxy])
        xy = xy[np.isfinite(xy).all(axis=1)]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        pad = 0.08 * max(float(np.max(hi - lo)), 1e-9)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    down = image_y_down if image_y_down is not None else bool(isinstance(traj, Trajectories) and traj.image_size)
    if down:
        ax.invert_yaxis()
    ax.set_xticks([])
    ax.set_yticks([])
    selected = int(skeleton.info.get("selected_stage", -1)) == (stage % len(stages))
    if title:
        k = stage % len(stages)
        ax.set_title(f"stage {k}: {stage_kind(st, k)}" + (" (selected)" if selected else ""), fontsize=9)
    if selected:
        for spine in ax.spines.values():
            spine.set_linewidth(2.5)
            spine.set_color("tab:red")
    return ax


def plot_stages(skeleton: Skeleton, traj: Trajectories | np.ndarray | None = None, *, ncols: int | None = None,
                size: float = 2.6) -> Any:
    """A grid with the structure of every merge stage (the paper's Figs. 4-6, top).

    Returns
    -------
    matplotlib Figure
    """
    import matplotlib.pyplot as plt

    stages = _check(skeleton)
    n = len(stages)
    ncols = ncols or min(n, 6)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(size * ncols, size * nrows), squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        if k < n:
            plot_stage(skeleton, k, traj, ax)
        else:
            ax.axis("off")
    fig.tight_layout()
    return fig


def plot_objective(skeleton: Skeleton, ax: Any = None, *, bic: bool = True) -> Any:
    """The objective (negative free energy) after every merge stage (Fig. 4, bottom-left).

    The BIC-penalised value is drawn on a second axis when ``bic``; the stage the
    fit selected is marked.
    """
    import matplotlib.pyplot as plt

    stages = _check(skeleton)
    if ax is None:
        _, ax = plt.subplots(figsize=(4.2, 3.0))
    k = np.arange(len(stages))
    obj = np.array([s["objective"] for s in stages], dtype=float)
    ax.plot(k, obj, "o-", color="tab:blue", label="objective")
    sel = int(skeleton.info.get("selected_stage", int(np.argmax(obj))))
    ax.plot([sel], [obj[sel]], "*", ms=14, color="tab:red", label=f"selected ({skeleton.info.get('selection')})")
    ax.set_xlabel("merge stage")
    ax.set_ylabel("expected complete log-likelihood")
    ax.set_xticks(k)
    if bic:
        ax2 = ax.twinx()
        ax2.plot(k, [s["bic"] for s in stages], "s--", color="tab:gray", ms=4, label="BIC")
        ax2.set_ylabel("BIC (objective - k/2 log N)", color="tab:gray")
    ax.legend(loc="lower right", fontsize=8)
    return ax


def figure(skeleton: Skeleton, traj: Trajectories | np.ndarray | None = None, path: Any = None, *,
           frames: Any = None) -> Any:
    """Stages, objective curve and (when ``traj`` is given) overlays of the selected skeleton.

    Parameters
    ----------
    skeleton : Skeleton
    traj : Trajectories, optional
    path : str or Path, optional
        Write a PNG there (atomically) and return its path; else return the Figure.
    frames : frame indices for the overlays (default: four spread over the sequence)
    """
    import matplotlib.pyplot as plt

    stages = _check(skeleton)
    n = len(stages)
    ncols = min(max(n, 4), 6)
    rows_st = math.ceil(n / ncols)
    over = traj is not None and isinstance(traj, Trajectories)
    nrows = rows_st + 1 + (1 if over else 0)
    fig = plt.figure(figsize=(2.6 * ncols, 2.6 * nrows))
    gs = fig.add_gridspec(nrows, ncols)
    for k in range(n):
        plot_stage(skeleton, k, traj, fig.add_subplot(gs[k // ncols, k % ncols]))
    plot_objective(skeleton, fig.add_subplot(gs[rows_st, : max(ncols // 2, 2)]))
    if over:
        from . import draw_frame, select_frames

        idx = select_frames(frames, traj.n_frames, default_count=min(4, ncols))
        for c, f in enumerate(idx[:ncols]):
            draw_frame(fig.add_subplot(gs[rows_st + 1, c]), traj, skeleton, int(f))
    fig.tight_layout()
    if path is None:
        return fig
    from . import _save_figure

    out = _save_figure(fig, path)
    plt.close(fig)
    return out
