"""The result type every method returns, and its files.

A :class:`Skeleton` describes what a method learned about a figure:

* ``labels`` (P,): the stick of each point, -1 for points on no stick;
* ``edges``: pairs of sticks joined at a joint, forming a forest;
* ``joints`` (J, F, D): per-frame joint positions over the training frames,
  with ``edge_joints`` (E,) giving the joint row of each edge;
* ``motions`` (S, F, D, 4): per-stick, per-frame affine camera motions
  ``[A | t]`` mapping homogeneous local coordinates to the data's space, and
  ``local`` (P, 3): each point's time-invariant coordinates in its stick's frame;
* ``log_likelihood``: the method's objective at the returned solution;
* ``state`` / ``info``: method-specific arrays and JSON diagnostics, enough for
  :meth:`Skeleton.impute` to refit the structure to new frames.

Files
-----
``save("model.json")`` writes two files: ``model.json`` (everything that is not a
large array, human-readable) and ``model.npz`` (the arrays, loaded without
pickle). Both are written atomically; the JSON records the NPZ's SHA-256 so a
mismatched pair is detected on load.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._atomic import atomic_path, atomic_write_text
from ._validation import check_edges, check_labels
from .trajectories import Trajectories, as_trajectories

__all__ = ["Skeleton", "FORMAT_VERSION", "orient_tree"]

FORMAT_VERSION = 1


@dataclass(eq=False)
class Skeleton:
    """A learned stick figure: segmentation, tree, joints and motions.

    Parameters
    ----------
    method : str
        Registered name of the method that produced it.
    labels : ndarray of int, shape (P,)
        Stick of each point, -1 = none.
    n_sticks : int
        Number of sticks S (labels lie in ``0 .. S-1``).
    edges : list of (int, int)
        Joined stick pairs; must form a forest.
    joints : ndarray, shape (J, F, D), optional
        Joint positions in every training frame.
    edge_joints : ndarray of int, shape (E,), optional
        Row of ``joints`` for each edge (defaults to ``arange(E)`` when J == E).
    motions : ndarray, shape (S, F, D, 4), optional
        Affine motion ``[A | t]`` of each stick in each frame.
    local : ndarray, shape (P, 3), optional
        Local 3D coordinates of each point in its stick's frame.
    log_likelihood : float, optional
        The method's objective (log-likelihood or log-joint) at this solution.
    params : dict
        The parameters the method was run with (JSON-serialisable).
    point_names : list of str, optional
    n_dims : int
        Dimension of the data it was fitted to.
    state : dict of str to ndarray
        Method-specific arrays used by :meth:`impute` and by the report.
    info : dict
        Method-specific JSON-serialisable diagnostics.
    """

    method: str
    labels: np.ndarray
    n_sticks: int
    edges: list[tuple[int, int]] = field(default_factory=list)
    joints: np.ndarray | None = None
    edge_joints: np.ndarray | None = None
    motions: np.ndarray | None = None
    local: np.ndarray | None = None
    log_likelihood: float | None = None
    params: dict[str, Any] = field(default_factory=dict)
    point_names: list[str] | None = None
    n_dims: int = 2
    state: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.labels = np.asarray(self.labels)
        P = self.labels.shape[0] if self.labels.ndim == 1 else -1
        self.labels = check_labels(self.labels, P, "labels")
        self.n_sticks = int(self.n_sticks)
        if self.labels.size and self.labels.max() >= self.n_sticks:
            raise ValueError(f"labels refer to stick {self.labels.max()}, but n_sticks = {self.n_sticks}")
        self.edges = check_edges(self.edges, self.n_sticks, "edges")
        if not _is_forest(self.n_sticks, self.edges):
            raise ValueError(f"edges must form a forest (no cycles, no repeated edge), got {self.edges}")
        if self.joints is not None:
            self.joints = np.asarray(self.joints, dtype=float)
            if self.joints.ndim != 3:
                raise ValueError(f"joints must have shape (J, F, D), got {self.joints.shape}")
            if self.edge_joints is None:
                if self.joints.shape[0] != len(self.edges):
                    raise ValueError("edge_joints is required when the number of joints differs from edges")
                self.edge_joints = np.arange(len(self.edges))
        if self.edge_joints is not None:
            self.edge_joints = np.asarray(self.edge_joints, dtype=np.int64)
            if self.edge_joints.shape != (len(self.edges),):
                raise ValueError(f"edge_joints must have shape ({len(self.edges)},), got {self.edge_joints.shape}")
        if self.motions is not None:
            self.motions = np.asarray(self.motions, dtype=float)
            want = (self.n_dims, 4)
            if self.motions.ndim != 4 or self.motions.shape[0] != self.n_sticks or self.motions.shape[2:] != want:
                raise ValueError(f"motions must have shape ({self.n_sticks}, F, {self.n_dims}, 4), "
                                 f"got {self.motions.shape}")
        if self.local is not None:
            self.local = np.asarray(self.local, dtype=float)
            if self.local.shape != (self.n_points, 3):
                raise ValueError(f"local must have shape ({self.n_points}, 3), got {self.local.shape}")
        if self.point_names is not None:
            self.point_names = [str(n) for n in self.point_names]
        if self.log_likelihood is not None:
            self.log_likelihood = float(self.log_likelihood)
        self.state = {k: np.asarray(v) for k, v in self.state.items()}

    # ---------------------------------------------------------------- queries
    @property
    def n_points(self) -> int:
        """Number of points P the skeleton was fitted to."""
        return int(self.labels.shape[0])

    @property
    def n_joints(self) -> int:
        """Number of joint rows J (0 when the method gives no joints)."""
        return 0 if self.joints is None else int(self.joints.shape[0])

    def stick_sizes(self) -> np.ndarray:
        """Number of points on each stick, shape (S,)."""
        return np.bincount(self.labels[self.labels >= 0], minlength=self.n_sticks)

    def parents(self) -> np.ndarray:
        """Parent of every stick in the forest rooted at each component's largest stick, shape (S,).

        Roots have parent -1.
        """
        import networkx as nx

        g = nx.Graph()
        g.add_nodes_from(range(self.n_sticks))
        g.add_edges_from(self.edges)
        sizes = self.stick_sizes()
        parent = -np.ones(self.n_sticks, np.int64)
        for comp in nx.connected_components(g):
            root = max(comp, key=lambda s: (sizes[s], -s))
            for child, par in nx.bfs_predecessors(g, root):
                parent[child] = par
        return parent

    def predict(self) -> np.ndarray:
        """Positions (P, F, D) the stick motions predict for the training frames (NaN for unassigned points)."""
        if self.motions is None or self.local is None:
            raise ValueError(f"the {self.method!r} skeleton has no stick motions to predict from")
        from .geometry import predict_points

        return predict_points(self.motions, self.local, self.labels)

    def impute(self, traj: Trajectories | np.ndarray) -> np.ndarray:
        """Fill every missing entry of ``traj`` using the learned structure.

        The structure (segmentation, local shapes, tree) stays fixed; the
        per-frame motions are re-estimated from the observed entries of
        ``traj``, which may be new frames of the same figure.

        Parameters
        ----------
        traj : Trajectories or ndarray, shape (P, F, D)
            The same P points as the skeleton was fitted to.

        Returns
        -------
        ndarray, shape (P, F, D)
            Observed entries unchanged, missing ones predicted.
        """
        traj = traj if isinstance(traj, Trajectories) else as_trajectories_unobserved(traj)
        if traj.n_points != self.n_points:
            raise ValueError(f"traj has {traj.n_points} points, but the skeleton was fitted to {self.n_points}")
        if traj.n_dims != self.n_dims:
            raise ValueError(f"traj is {traj.n_dims}D, but the skeleton was fitted to {self.n_dims}D data")
        from .models import get_method

        from ._threads import blas_threads

        with blas_threads():
            filled = np.asarray(get_method(self.method).impute_skeleton(self, traj), dtype=float)
        if filled.shape != traj.xy.shape:
            raise RuntimeError(f"{self.method} imputation returned shape {filled.shape}, expected {traj.xy.shape}")
        obs = traj.observed
        filled[obs] = traj.xy[obs]
        return filled

    def summary(self) -> str:
        """A few lines a person can read: sticks, sizes, tree."""
        sizes = self.stick_sizes()
        lines = [f"method: {self.method}", f"points: {self.n_points}, sticks: {self.n_sticks}"]
        names = self.point_names
        for s in range(self.n_sticks):
            members = np.flatnonzero(self.labels == s)
            shown = ", ".join(names[p] for p in members[:8]) if names else ", ".join(map(str, members[:8]))
            more = " ..." if members.size > 8 else ""
            lines.append(f"  stick {s}: {sizes[s]} points ({shown}{more})")
        if (self.labels < 0).any():
            lines.append(f"  unassigned: {int((self.labels < 0).sum())} points")
        if self.edges:
            lines.append("joints: " + ", ".join(f"{a}-{b}" for a, b in self.edges))
        else:
            lines.append("joints: none")
        if self.log_likelihood is not None:
            lines.append(f"objective: {self.log_likelihood:.6g}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"Skeleton(method={self.method!r}, n_points={self.n_points}, n_sticks={self.n_sticks}, "
                f"edges={self.edges})")

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> Path:
        """Write ``<stem>.json`` and ``<stem>.npz`` atomically; returns the JSON path."""
        path = Path(path)
        if path.suffix.lower() != ".json":
            path = path.with_suffix(path.suffix + ".json") if path.suffix else path.with_suffix(".json")
        npz_path = path.with_suffix(".npz")
        arrays: dict[str, np.ndarray] = {"labels": self.labels}
        for name in ("joints", "edge_joints", "motions", "local"):
            value = getattr(self, name)
            if value is not None:
                arrays[name] = value
        for k, v in self.state.items():
            if v.dtype == object:
                raise TypeError(f"state[{k!r}] is an object array; only numeric/string arrays can be saved")
            arrays[f"state/{k}"] = v
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        blob = buf.getvalue()
        with atomic_path(npz_path) as tmp:
            tmp.write_bytes(blob)
        doc = {
            "format": "stickfigure.skeleton",
            "version": FORMAT_VERSION,
            "method": self.method,
            "n_points": self.n_points,
            "n_sticks": self.n_sticks,
            "n_dims": self.n_dims,
            "edges": [list(e) for e in self.edges],
            "labels": self.labels.tolist(),
            "point_names": self.point_names,
            "log_likelihood": self.log_likelihood,
            "params": _jsonable(self.params),
            "info": _jsonable(self.info),
            "arrays": {"file": npz_path.name, "sha256": hashlib.sha256(blob).hexdigest()},
        }
        atomic_write_text(path, json.dumps(doc, indent=1, allow_nan=True) + "\n")
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Skeleton":
        """Read a skeleton written by :meth:`save` (no pickle is ever loaded)."""
        path = Path(path)
        if not path.exists() and path.with_suffix(".json").exists():
            path = path.with_suffix(".json")
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise FileNotFoundError(f"no such model file: {path}") from None
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path} is not a stickfigure model (invalid JSON: {exc})") from None
        if not isinstance(doc, dict) or doc.get("format") != "stickfigure.skeleton":
            raise ValueError(f"{path} is not a stickfigure model file")
        if int(doc.get("version", 0)) > FORMAT_VERSION:
            raise ValueError(f"{path} was written by a newer stickfigure (format {doc['version']})")
        npz_path = path.parent / doc["arrays"]["file"]
        try:
            blob = npz_path.read_bytes()
        except FileNotFoundError:
            raise FileNotFoundError(f"the model's array file is missing: {npz_path}") from None
        if hashlib.sha256(blob).hexdigest() != doc["arrays"]["sha256"]:
            raise ValueError(f"{npz_path} does not belong to {path} (checksum mismatch)")
        try:
            with np.load(io.BytesIO(blob), allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:  # zipfile/ValueError variants for corrupt files
            raise ValueError(f"{npz_path} is unreadable: {exc}") from None
        state = {k[len("state/"):]: v for k, v in arrays.items() if k.startswith("state/")}
        return cls(
            method=doc["method"],
            labels=arrays["labels"],
            n_sticks=doc["n_sticks"],
            edges=[tuple(e) for e in doc["edges"]],
            joints=arrays.get("joints"),
            edge_joints=arrays.get("edge_joints"),
            motions=arrays.get("motions"),
            local=arrays.get("local"),
            log_likelihood=doc.get("log_likelihood"),
            params=doc.get("params") or {},
            point_names=doc.get("point_names"),
            n_dims=int(doc.get("n_dims", 2)),
            state=state,
            info=doc.get("info") or {},
        )


def as_trajectories_unobserved(data: Any) -> Trajectories:
    """Like :func:`as_trajectories` but accepting never-observed points (for imputation)."""
    if isinstance(data, Trajectories):
        return data
    try:
        return Trajectories(np.asarray(data, dtype=float), allow_unobserved=True)
    except (TypeError, ValueError):
        return as_trajectories(data)


def orient_tree(edges: list[tuple[int, int]], root: int, n: int) -> list[tuple[int, int]]:
    """Direct an undirected forest as (parent, child) pairs, in breadth-first order.

    Parameters
    ----------
    edges : list of (int, int)
        Undirected edges between ``n`` nodes, forming a forest.
    root : int
        Root of its tree; every other tree is rooted at its smallest node.
    n : int
        Number of nodes.
    """
    import networkx as nx

    g = nx.Graph()
    g.add_nodes_from(range(n))
    g.add_edges_from(edges)
    out = []
    for comp in nx.connected_components(g):
        r = root if root in comp else min(comp)
        out += [(int(p), int(c)) for c, p in nx.bfs_predecessors(g, r)]
    return out


def _is_forest(n: int, edges: list[tuple[int, int]]) -> bool:
    parent = list(range(n))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        ra, rb = find(a), find(b)
        if ra == rb:
            return False
        parent[ra] = rb
    return True


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and tuples to plain JSON types."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, (str, int, float, bool)):
        return obj
    return repr(obj)
