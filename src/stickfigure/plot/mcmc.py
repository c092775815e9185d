"""Diagnostics of the "mcmc" method (Meeds et al.): samples, predictive density, traces.

* :func:`plot_samples` -- several posterior stick figures at one frame (the
  paper's Figs. 6-7, top): points coloured by their stick in that sample, each
  stick drawn from its joint ``T`` to its distal end ``T + R L``, and a circle of
  radius ``1 / sqrt(s_T)`` at the distal end (where its children's joints are
  expected: the paper's Fig. 2).
* :func:`plot_predictive_density` -- contours of the predictive log-density of
  a point at one frame, averaged over posterior samples (Fig. 2, bottom right).
* :func:`plot_traces` -- log-joint and number of sticks against sweep, one line
  per chain, burn-in shaded.
* :func:`plot_n_sticks` -- the posterior over the number of sticks.
* :func:`figure` -- all of them on one page.

Every function takes the :class:`~stickfigure.skeleton.Skeleton` that
``fit(..., method="mcmc")`` returns; coordinates are the data's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..skeleton import Skeleton
from ..trajectories import Trajectories

__all__ = ["plot_samples", "plot_predictive_density", "plot_traces", "plot_n_sticks", "figure", "sample_sticks"]


def _check(skeleton: Skeleton) -> dict[str, np.ndarray]:
    if skeleton.method != "mcmc" or "sample_c" not in skeleton.state:
        raise ValueError(f"these plots need a skeleton from method 'mcmc', got one from {skeleton.method!r}")
    return skeleton.state


def _axes(ax: Any) -> Any:
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(4, 4))
    return ax


def _frame(skeleton: Skeleton, frame: int) -> int:
    F = skeleton.state["sample_theta"].shape[2]
    frame = int(frame)
    if not -F <= frame < F:
        raise ValueError(f"frame must be in [0, {F}), got {frame}")
    return frame % F


def sample_sticks(skeleton: Skeleton, sample: int, frame: int) -> dict[str, np.ndarray]:
    """One stored posterior sample at one frame, in data coordinates.

    Returns
    -------
    dict
        ``labels`` (P,), ``parent`` (K,), ``start``/``end`` (K, 2) joint and distal end of every
        stick, ``joint_sd`` (K,) the spread of its children's joints, ``points`` (P, 2)
        the sample's predicted positions.
    """
    state = _check(skeleton)
    D = state["sample_c"].shape[0]
    if not 0 <= sample < D:
        raise ValueError(f"sample must be in [0, {D}), got {sample}")
    f = _frame(skeleton, frame)
    cx, cy, scale = state["normalisation"]
    par = state["sample_parent"][sample]
    K = int((par > -2).sum())
    theta = state["sample_theta"][sample, :K, f]
    T = state["sample_T"][sample, :K, f, 0] + 1j * state["sample_T"][sample, :K, f, 1]
    prec = state["sample_prec"][sample, :K]
    L = 6.0 / np.sqrt(prec[:, 1])
    end = T + np.exp(1j * theta) * L
    c = state["sample_c"][sample]
    y = state["sample_y"][sample, :, 0] + 1j * state["sample_y"][sample, :, 1]
    pts = np.exp(1j * theta[c]) * y + T[c]

    def data(zz: np.ndarray) -> np.ndarray:
        return np.column_stack([zz.real * scale + cx, zz.imag * scale + cy])

    return {"labels": c, "parent": par[:K], "start": data(T), "end": data(end),
            "joint_sd": scale / np.sqrt(prec[:, 3]), "points": data(pts)}


def _distinct_samples(state: dict[str, np.ndarray], n: int) -> list[int]:
    """Up to n stored samples with different structures, the most probable first."""
    from ..models.mcmc.prior import canonical_key

    order = np.argsort(-state["sample_log_joint"])
    seen: set = set()
    out: list[int] = []
    for d in order:
        par = state["sample_parent"][d]
        key = canonical_key(state["sample_c"][d], par[par > -2])
        if key in seen:
            continue
        seen.add(key)
        out.append(int(d))
        if len(out) == n:
            break
    return out


def plot_samples(skeleton: Skeleton, frame: int = 0, n: int = 3, traj: Trajectories | None = None,
                 axes: Any = None, samples: list[int] | None = None) -> list[Any]:
    """Several posterior stick figures at one frame, different structures first (Figs. 6-7, top).

    Parameters
    ----------
    frame : int
    n : int
        Number of samples (the most probable distinct structures).
    traj : Trajectories, optional
        Draw the observed points of this frame instead of each sample's predictions.
    axes : sequence of Axes, optional
    samples : list of int, optional
        Stored sample indices to draw instead.

    Returns
    -------
    list of Axes
    """
    from . import stick_colors

    state = _check(skeleton)
    picks = samples if samples is not None else _distinct_samples(state, int(n))
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks), 3.2), squeeze=False)
        axes = list(axes[0])
    axes = list(axes)
    f = _frame(skeleton, frame)
    for ax, d in zip(axes, picks):
        s = sample_sticks(skeleton, d, f)
        K = s["parent"].shape[0]
        col = stick_colors(K)
        pts = s["points"]
        if traj is not None:
            obs = traj.xy[:, f]
            pts = np.where(np.isnan(obs), pts, obs)
        ax.scatter(pts[:, 0], pts[:, 1], c=col[s["labels"]], s=14, zorder=3)
        for k in range(K):
            a, b = s["start"][k], s["end"][k]
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", color=col[k], lw=2.5, zorder=2)
            ax.add_patch(_circle(b, s["joint_sd"][k], col[k]))
        ax.set_aspect("equal")
        ax.set_title(f"{K} sticks, log p = {state['sample_log_joint'][d]:.0f}", fontsize=9)
        if traj is not None and traj.image_size is not None:
            ax.invert_yaxis()
    return axes


def _circle(centre: np.ndarray, radius: float, color: Any) -> Any:
    from matplotlib.patches import Circle

    return Circle((float(centre[0]), float(centre[1])), float(radius), fill=False, color=color, lw=1.0, zorder=1)


def predictive_log_density(skeleton: Skeleton, frame: int, grid_x: np.ndarray, grid_y: np.ndarray,
                           max_samples: int = 50) -> np.ndarray:
    """Log-density of a point at ``frame``, averaged over posterior samples, on a grid.

    Each sample contributes the mixture over its sticks, weighted by their
    number of points, of the frame's marginal of eq. 13,
    ``N(T + R L/2, R Sigma_y R^T + I / s_x)``; the small weight a new stick would
    get is left out.

    Returns
    -------
    ndarray, shape (len(grid_y), len(grid_x))
    """
    state = _check(skeleton)
    f = _frame(skeleton, frame)
    cx, cy, scale = state["normalisation"]
    gx, gy = np.meshgrid((np.asarray(grid_x) - cx) / scale, (np.asarray(grid_y) - cy) / scale)
    pts = np.stack([gx.ravel(), gy.ravel()], 1)
    D = state["sample_c"].shape[0]
    pick = np.unique(np.linspace(0, D - 1, min(max_samples, D)).round().astype(int))
    total = np.zeros(pts.shape[0])
    for d in pick:
        par = state["sample_parent"][d]
        K = int((par > -2).sum())
        w = np.bincount(state["sample_c"][d], minlength=K) / state["sample_c"].shape[1]
        prec = state["sample_prec"][d, :K]
        th = state["sample_theta"][d, :K, f]
        T = state["sample_T"][d, :K, f]
        L = 6.0 / np.sqrt(prec[:, 1])
        R = np.stack([np.stack([np.cos(th), -np.sin(th)], -1), np.stack([np.sin(th), np.cos(th)], -1)], -2)
        mean = T + (R @ np.stack([L / 2, np.zeros(K)], -1)[..., None])[..., 0]
        Sy = np.zeros((K, 2, 2))
        Sy[:, 0, 0], Sy[:, 1, 1] = 1 / prec[:, 1], 1 / prec[:, 2]
        C = R @ Sy @ np.swapaxes(R, -1, -2) + np.eye(2) / prec[:, 0, None, None]
        Ci = np.linalg.inv(C)
        diff = pts[:, None, :] - mean[None]
        quad = np.einsum("pki,kij,pkj->pk", diff, Ci, diff)
        logn = -0.5 * quad - np.log(2 * np.pi) - 0.5 * np.log(np.linalg.det(C))[None]
        total += np.exp(logn) @ w
    dens = total / len(pick) / scale ** 2
    with np.errstate(divide="ignore"):
        return np.log(dens).reshape(gx.shape)


def plot_predictive_density(skeleton: Skeleton, frame: int = 0, traj: Trajectories | None = None, ax: Any = None,
                            grid: int = 120, levels: int = 12, max_samples: int = 50) -> Any:
    """Contours of the predictive log-density at one frame, averaged over samples (Fig. 2, bottom right)."""
    state = _check(skeleton)
    ax = _axes(ax)
    f = _frame(skeleton, frame)
    pts = state["predictive_mean"][:, f]
    if traj is not None:
        obs = traj.xy[:, f]
        pts = np.where(np.isnan(obs), pts, obs)
    lo, hi = pts.min(0), pts.max(0)
    pad = 0.15 * max(float((hi - lo).max()), 1e-9)
    gx = np.linspace(lo[0] - pad, hi[0] + pad, grid)
    gy = np.linspace(lo[1] - pad, hi[1] + pad, grid)
    logd = predictive_log_density(skeleton, f, gx, gy, max_samples)
    finite = logd[np.isfinite(logd)]
    floor = np.quantile(finite, 0.2) if finite.size else 0.0
    cs = ax.contourf(gx, gy, np.maximum(np.where(np.isfinite(logd), logd, floor), floor), levels=levels,
                     cmap="viridis")
    ax.scatter(pts[:, 0], pts[:, 1], s=8, c="w", edgecolors="k", linewidths=0.4, zorder=3)
    ax.set_aspect("equal")
    ax.set_title(f"predictive log-density, frame {f}", fontsize=9)
    ax.figure.colorbar(cs, ax=ax, fraction=0.046, pad=0.04)
    if traj is not None and traj.image_size is not None:
        ax.invert_yaxis()
    return ax


def plot_traces(skeleton: Skeleton, axes: Any = None) -> list[Any]:
    """Log-joint and number of sticks against sweep, one line per chain, burn-in shaded."""
    state = _check(skeleton)
    if axes is None:
        import matplotlib.pyplot as plt

        _, axes = plt.subplots(2, 1, figsize=(6, 4), sharex=True)
    axes = list(axes)
    lj = state["trace_log_joint"]
    ks = state["trace_n_sticks"]
    burn = int(skeleton.params.get("burn_in", 0))
    sweeps = np.arange(lj.shape[1])
    for c in range(lj.shape[0]):
        axes[0].plot(sweeps, lj[c], lw=0.8, label=f"chain {c}")
        axes[1].step(sweeps, ks[c], lw=0.8, where="post")
    for ax in axes:
        ax.axvspan(0, burn, color="0.9", zorder=0)
    post = lj[:, burn:] if burn < lj.shape[1] else lj
    lo, hi = np.quantile(post, [0.01, 1.0])
    axes[0].set_ylim(lo - 0.1 * (hi - lo + 1), hi + 0.1 * (hi - lo + 1))
    rhat = skeleton.info.get("rhat", {}).get("log_joint")
    axes[0].set_ylabel("log joint")
    axes[0].set_title("traces" + (f" (R-hat {rhat:.3f})" if rhat else ""), fontsize=9)
    axes[0].legend(fontsize=7, loc="lower right")
    axes[1].set_ylabel("sticks")
    axes[1].set_xlabel("sweep")
    return axes


def plot_n_sticks(skeleton: Skeleton, ax: Any = None) -> Any:
    """Bar chart of the posterior over the number of sticks."""
    _check(skeleton)
    ax = _axes(ax)
    post = {int(k): v for k, v in skeleton.info["n_sticks_posterior"].items()}
    ks = sorted(post)
    ax.bar(ks, [post[k] for k in ks], color="tab:blue")
    ax.set_xticks(ks)
    ax.set_xlabel("number of sticks")
    ax.set_ylabel("posterior probability")
    ax.set_ylim(0, 1)
    return ax


def figure(skeleton: Skeleton, traj: Trajectories | None = None, path: Any = None, *, frame: int | None = None,
           n_samples: int = 3) -> Any:
    """Samples at one frame, predictive density, traces and the posterior over the number of sticks.

    Parameters
    ----------
    path : str or Path, optional
        Write the picture there (atomically) and return its path; else return the Figure.
    frame : int, optional
        Frame to draw (default: the middle one).
    """
    import matplotlib.pyplot as plt

    state = _check(skeleton)
    F = state["sample_theta"].shape[2]
    f = F // 2 if frame is None else _frame(skeleton, frame)
    picks = _distinct_samples(state, n_samples)
    ncols = max(len(picks), 3)
    fig = plt.figure(figsize=(3.3 * ncols, 9.0))
    gs = fig.add_gridspec(3, ncols)
    plot_samples(skeleton, f, traj=traj, axes=[fig.add_subplot(gs[0, c]) for c in range(len(picks))], samples=picks)
    plot_predictive_density(skeleton, f, traj=traj, ax=fig.add_subplot(gs[1, 0]))
    plot_n_sticks(skeleton, fig.add_subplot(gs[1, 1]))
    plot_traces(skeleton, [fig.add_subplot(gs[2, : ncols - 1]), fig.add_subplot(gs[1, 2:] if ncols > 2 else gs[2, -1])])
    fig.tight_layout()
    if path is None:
        return fig
    from . import _save_figure

    out = _save_figure(fig, path)
    plt.close(fig)
    return out
