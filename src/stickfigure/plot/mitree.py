"""Diagnostics of the "mi-tree" method: the mutual-information heat map and the recovered tree.

The heat map is the paper's Figs. 6.1-6.3 (d): the adjacency matrix of the
mutual-information graph, intensity = edge weight. The tree panel is their
(e): the segments and the recovered edges, drawn at the segments' image
positions in a chosen frame with the estimated joints.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..skeleton import Skeleton
from ..trajectories import Trajectories

__all__ = ["plot_mutual_information", "plot_tree", "figure"]


def _check(skeleton: Skeleton) -> None:
    if skeleton.method != "mi-tree" or "mutual_information" not in skeleton.state:
        raise ValueError(f"need a skeleton fitted by mi-tree, got one from {skeleton.method!r}")


def _names(skeleton: Skeleton, names: list[str] | None) -> list[str]:
    if names is None:
        return [f"S{s + 1}" for s in range(skeleton.n_sticks)]
    if len(names) != skeleton.n_sticks:
        raise ValueError(f"names must have one entry per segment ({skeleton.n_sticks}), got {len(names)}")
    return list(names)


def plot_mutual_information(skeleton: Skeleton, ax: Any = None, *, names: list[str] | None = None,
                            which: str = "mutual_information", show_tree: bool = True) -> Any:
    """Heat map of the pairwise mutual information (or of the relative-motion entropies).

    Parameters
    ----------
    skeleton : Skeleton
        Fitted by "mi-tree".
    ax : matplotlib Axes, optional
    names : list of str, optional
        Segment names (default S1, S2, ...).
    which : {"mutual_information", "conditional_entropy"}
        The matrix to draw; for the conditional entropy, low = strongly related,
        so its colour scale is reversed.
    show_tree : bool
        Outline the cells of the recovered tree's edges.

    Returns
    -------
    matplotlib Axes
    """
    import matplotlib.pyplot as plt

    _check(skeleton)
    if which not in ("mutual_information", "conditional_entropy"):
        raise ValueError(f"which must be 'mutual_information' or 'conditional_entropy', got {which!r}")
    M = np.asarray(skeleton.state.get(which), float)
    labels = _names(skeleton, names)
    if ax is None:
        _, ax = plt.subplots(figsize=(4, 3.6))
    # The undefined diagonal in a colour outside the gray scale.
    cmap = plt.get_cmap("gray" if which == "mutual_information" else "gray_r").with_extremes(bad="#c6dbef")
    im = ax.imshow(np.ma.masked_invalid(M), cmap=cmap, interpolation="nearest")
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.04,
                       label="mutual information (nats)" if which == "mutual_information" else "H(relative motion)")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_yticks(range(len(labels)), labels)
    if show_tree:
        from matplotlib.patches import Rectangle

        for a, b in skeleton.edges:
            for i, j in ((a, b), (b, a)):
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, edgecolor="tab:red", lw=1.5))
    ax.set_title("mutual information" if which == "mutual_information" else "relative-motion entropy")
    return ax


def plot_tree(skeleton: Skeleton, traj: Trajectories | None = None, ax: Any = None, *, frame: int = 0,
              names: list[str] | None = None) -> Any:
    """The recovered tree over one frame: points coloured by segment, joints, and edges.

    Each segment is drawn at the image centroid of its fitted pose; an edge goes
    from the parent's centroid through the joint to the child's centroid.

    Parameters
    ----------
    skeleton : Skeleton
        Fitted by "mi-tree".
    traj : Trajectories, optional
        The data, to draw the observed points of that frame.
    ax : matplotlib Axes, optional
    frame : int
    names : list of str, optional

    Returns
    -------
    matplotlib Axes
    """
    import matplotlib.pyplot as plt

    _check(skeleton)
    if skeleton.motions is None:
        raise ValueError("the skeleton has no motions to draw")
    F = skeleton.motions.shape[1]
    if not -F <= frame < F:
        raise ValueError(f"frame must be in [0, {F}), got {frame}")
    labels = _names(skeleton, names)
    if ax is None:
        _, ax = plt.subplots(figsize=(4, 4))
    colours = plt.get_cmap("tab10")
    centres = skeleton.motions[:, frame, :, 3]  # translation = image centroid of each centred shape
    if traj is not None:
        xy = traj.xy[:, frame]
        for s in range(skeleton.n_sticks):
            m = skeleton.labels == s
            ax.scatter(xy[m, 0], xy[m, 1], s=10, color=colours(s % 10))
    else:
        pred = skeleton.predict()[:, frame]
        for s in range(skeleton.n_sticks):
            m = skeleton.labels == s
            ax.scatter(pred[m, 0], pred[m, 1], s=10, color=colours(s % 10))
    for k, (p, c) in enumerate(skeleton.edges):
        path = [centres[p]]
        if skeleton.joints is not None:
            jrow = skeleton.edge_joints[k] if skeleton.edge_joints is not None else k
            path.append(skeleton.joints[jrow, frame])
            ax.plot(*skeleton.joints[jrow, frame], "ko", ms=5)
        path.append(centres[c])
        path = np.array(path)
        ax.plot(path[:, 0], path[:, 1], "k-", lw=1.5)
    for s in range(skeleton.n_sticks):
        ax.annotate(labels[s], centres[s], color=colours(s % 10), fontweight="bold",
                    xytext=(4, 4), textcoords="offset points")
    ax.set_aspect("equal")
    if traj is not None and traj.image_size is not None:
        ax.invert_yaxis()  # pixel coordinates have y down
    ax.set_title(f"recovered tree (frame {frame})")
    return ax


def figure(skeleton: Skeleton, traj: Trajectories | None = None, *, frame: int = 0,
           names: list[str] | None = None) -> Any:
    """Heat map of the mutual information, of the relative-motion entropy, and the tree, side by side."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    plot_mutual_information(skeleton, axes[0], names=names)
    plot_mutual_information(skeleton, axes[1], names=names, which="conditional_entropy")
    plot_tree(skeleton, traj, axes[2], frame=frame, names=names)
    fig.tight_layout()
    return fig
