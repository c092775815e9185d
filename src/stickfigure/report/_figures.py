"""Figures for the report, as PNG data URIs.

The method-specific diagnostics come from each method's plot module
(``stickfigure.plot.em``, ``.mcmc``, ``.mitree``, ...): the report calls its
``report_figures(skeleton, traj)`` (a list of ``(caption, Figure)``) or its
``figure(skeleton, traj)`` (one Figure), whichever exists. A method without a
plot module gets tables of its raw ``skeleton.info`` instead (see ``_html``).
"""

from __future__ import annotations

import base64
import importlib
import io
import warnings
from typing import Any

import numpy as np

from ..skeleton import Skeleton
from ..trajectories import Trajectories

__all__ = ["to_data_uri", "tree_figure", "method_figures", "joint_angle_figure", "plot_module"]

#: Plot module of each method (``stickfigure.plot.<module>``).
_PLOT_MODULES = {"em": "em", "mcmc": "mcmc", "mi-tree": "mitree", "yan-pollefeys": "yan_pollefeys",
                 "sfm": "sfm", "multibody-sfm": "sfm"}


def to_data_uri(fig: Any, *, dpi: int = 110) -> str:
    """PNG data URI of a matplotlib figure; the figure is closed."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight", facecolor="white")
    finally:
        plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def plot_module(method: str) -> Any:
    """The plot module of ``method``, or None when it does not exist (yet)."""
    name = _PLOT_MODULES.get(method, method.replace("-", "_"))
    try:
        return importlib.import_module(f"stickfigure.plot.{name}")
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("stickfigure.plot"):
            return None
        raise


def tree_figure(skeleton: Skeleton) -> Any:
    """The learned tree as a graph (:func:`stickfigure.plot.draw_tree`), sized to the tree."""
    import matplotlib.pyplot as plt

    from ..plot import draw_tree

    parent = skeleton.parents()
    depth = np.zeros(skeleton.n_sticks, int)
    for s in range(skeleton.n_sticks):
        p = parent[s]
        while p >= 0:
            depth[s] += 1
            p = parent[p]
    leaves = skeleton.n_sticks - len({int(p) for p in parent if p >= 0})
    fig, ax = plt.subplots(figsize=(max(3.0, min(10.0, 1.0 * leaves + 1.5)), max(2.2, min(7.0, 1.0 * (depth.max() + 1.5)))))
    draw_tree(ax, skeleton)
    ax.set_title("learned tree (each tree hangs from its largest stick)", fontsize=10)
    return fig


def method_figures(skeleton: Skeleton, traj: Trajectories) -> tuple[list[tuple[str, str]], list[str]]:
    """The method's own diagnostic figures.

    Returns
    -------
    figures : list of (caption, data URI)
    notes : list of str
        Why something is missing (no plot module, or it failed).
    """
    mod = plot_module(skeleton.method)
    if mod is None:
        return [], [f"stickfigure.plot has no module for {skeleton.method!r}; its raw diagnostics are listed below."]
    figs: list[tuple[str, str]] = []
    notes: list[str] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            if hasattr(mod, "report_figures"):
                for caption, fig in mod.report_figures(skeleton, traj):
                    figs.append((str(caption), to_data_uri(getattr(fig, "figure", fig))))
            elif hasattr(mod, "figure"):
                fig = mod.figure(skeleton, traj)
                doc = (mod.figure.__doc__ or "").strip().splitlines()
                caption = doc[0].replace("``", "") if doc else f"{skeleton.method} diagnostics"
                figs.append((caption, to_data_uri(getattr(fig, "figure", fig))))
            else:
                notes.append(f"stickfigure.plot.{mod.__name__.rsplit('.', 1)[-1]} has no report_figures() or figure().")
        except Exception as exc:  # a broken figure must not cost the user the whole report
            notes.append(f"the {skeleton.method} diagnostic figure failed: {type(exc).__name__}: {exc}")
    return figs, notes


def joint_angle_figure(angles: np.ndarray, names: list[str], frame_numbers: np.ndarray,
                       frame_rate: float | None) -> Any:
    """Joint angles (degrees) against time, one line per joint."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3))
    t = frame_numbers / frame_rate if frame_rate else frame_numbers
    for k, name in enumerate(names):
        ax.plot(t, angles[:, k], lw=1.3, label=name)
    ax.set_xlabel("time (s)" if frame_rate else "frame")
    ax.set_ylabel("angle (degrees)")
    ax.grid(alpha=0.3)
    if len(names) <= 12:
        ax.legend(fontsize=8, ncol=min(4, len(names)), loc="upper right", frameon=False)
    ax.set_title("joint angles (angle between the joined sticks)", fontsize=10)
    return fig
