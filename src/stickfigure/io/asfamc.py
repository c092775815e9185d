"""Acclaim skeleton (``.asf``) and motion (``.amc``) files: bone positions by forward kinematics.

The ASF file defines bones (a ``direction`` in the global rest pose, a
``length``, an ``axis`` giving the bone's local frame and its ``dof``) and the
hierarchy; the AMC file gives the root translation/rotation and each bone's
degrees of freedom per frame. Forward kinematics (Acclaim ASF/AMC 1.10 as used
by Vicon BodyBuilder, CMU and HDM05), vectorised over frames::

    C_b  = rotation of the bone's axis (angles in the ASF's ``axis`` order)
    M_b  = rotation of its dof values (in the order of its ``dof`` line)
    R_b  = R_parent @ C_b @ M_b @ C_b^-1               (global rotation)
    start_b = end_parent      (the root's position for the root's children)
    end_b   = start_b + R_b @ (direction_b * length_b)

Rotations listed ``X Y Z`` are applied about fixed axes x, then y, then z, i.e.
``Rz @ Ry @ Rx`` (scipy ``from_euler("xyz")``). The root uses ``order`` for its
AMC values and ``axis``/``orientation``/``position`` for its preset pose. Angles
follow ``:units angle`` of the ASF (AMC values follow ``:DEGREES``/``:RADIANS``
in the AMC header when present).

Lengths: ``:units length L`` says the file's lengths are ``L`` times the
skeleton's own unit; dividing by ``L`` gives that unit. Vicon BodyBuilder
skeletons (CMU, HDM05) write ``length 0.45`` and their unit is the inch (CMU's
documentation converts to metres by ``(1 / 0.45) * 2.54 / 100``); we checked it
on the HDM05 take recorded both as C3D markers (mm) and AMC: the markers sit on
the forward-kinematics bones when AMC positions are divided by 0.45 and
multiplied by 25.4 (see ``docs/formats.md`` for the numbers). So ``L = 0.45``
gives ``meta["units"] = "in"``, and ``units="mm"`` (``"cm"``, ``"m"``, ``"in"``)
converts; for other skeletons the unit is unknown (``meta["units"]`` None) and
``units=`` only names it. ``scale=`` multiplies positions on top.

AMC files do not store a frame rate: ``frame_rate=`` sets it; otherwise a
trailing ``_<fps>`` in the file name (the HDM05 convention, ``..._120.amc``) is
used (a name of at least three ``_``-separated fields ending in a number from 24
to 2000; CMU's ``131_01`` ends in a trial number instead), else 120 Hz (the
CMU capture rate). ``meta["frame_rate_source"]`` says
which.

Points and ground truth (see :mod:`stickfigure.io._kinematics`): one point at the
root and one at the end of every bone, named after it, each labelled with the
part of the bone it ends (the root with the root part); ``markers_per_bone=k``
gives ``k`` virtual markers around every bone instead. ``up_axis`` is 1 (y up).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..trajectories import Trajectories
from ._common import OptionError, check_file, fail, positive_option
from ._kinematics import Rig, check_rig_options, rig_to_trajectories

__all__ = ["load_amc", "read_asf", "read_amc", "find_asf"]

_DOFS = ("rx", "ry", "rz", "tx", "ty", "tz", "l")


@dataclass
class Bone:
    """One ASF bone."""

    name: str
    direction: np.ndarray
    length: float
    axis: np.ndarray  # angles (radians) about x, y, z
    axis_order: str   # e.g. "xyz": the order the axis rotations are applied
    dof: list[str] = field(default_factory=list)


@dataclass
class ASF:
    """A parsed ASF skeleton (angles in radians, lengths as in the file)."""

    name: str
    length_unit: float
    angle_unit: str
    root_order: list[str]
    root_axis_order: str
    root_position: np.ndarray
    root_orientation: np.ndarray
    bones: dict[str, Bone]
    children: dict[str, list[str]]


def _angle_factor(unit: str) -> float:
    return np.pi / 180.0 if unit.startswith("deg") else 1.0


def read_asf(path: str | os.PathLike) -> ASF:
    """Parse an ASF skeleton file."""
    path = check_file(path)
    text = path.read_text(encoding="latin-1")
    # Split into keyword sections (":units", ":root", ...).
    sections: dict[str, list[list[str]]] = {}
    current = None
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].replace(",", " ").replace("(", " ").replace(")", " ").strip()
        if not line:
            continue
        if line.startswith(":"):
            key, _, rest = line.partition(" ")
            current = key[1:].lower()
            sections.setdefault(current, [])
            if rest.strip():
                sections[current].append(rest.split())
            continue
        if current is not None:
            sections[current].append(line.split())
    if "bonedata" not in sections and "root" not in sections:
        raise fail(path, "not an ASF skeleton file (no :root or :bonedata section)")
    for need in ("root", "bonedata", "hierarchy"):
        if need not in sections:
            raise fail(path, f"truncated or malformed ASF file: no :{need} section")

    units = {t[0].lower(): t[1] for t in sections.get("units", []) if len(t) >= 2}
    try:
        length_unit = float(units.get("length", 1.0))
    except ValueError:
        raise fail(path, f"bad length unit {units.get('length')!r}") from None
    if not np.isfinite(length_unit) or length_unit <= 0:
        raise fail(path, f"length unit must be > 0, got {length_unit}")
    angle_unit = units.get("angle", "deg").lower()
    if not angle_unit.startswith(("deg", "rad")):
        raise fail(path, f"unknown angle unit {angle_unit!r}")
    af = _angle_factor(angle_unit)

    def nums(tokens: list[str], n: int, what: str) -> np.ndarray:
        try:
            v = np.array([float(t) for t in tokens[:n]])
        except ValueError:
            raise fail(path, f"bad {what}: {' '.join(tokens)!r}") from None
        if v.size != n:
            raise fail(path, f"bad {what}: {' '.join(tokens)!r}")
        return v

    root = {t[0].lower(): t[1:] for t in sections["root"] if t}
    order = [o.lower() for o in root.get("order", ["tx", "ty", "tz", "rx", "ry", "rz"])]
    if any(o not in _DOFS[:6] for o in order):
        raise fail(path, f"bad root order {' '.join(order)!r}")
    root_axis = "".join(root.get("axis", ["xyz"])).lower()
    if sorted(root_axis) != ["x", "y", "z"]:
        raise fail(path, f"bad root axis order {root_axis!r}")
    position = nums(root.get("position", ["0", "0", "0"]), 3, "root position")
    orientation = nums(root.get("orientation", ["0", "0", "0"]), 3, "root orientation") * af

    bones: dict[str, Bone] = {}
    block: dict[str, list[str]] | None = None
    last_key = None
    for t in sections["bonedata"]:
        key = t[0].lower()
        if key == "begin":
            block, last_key = {}, None
        elif key == "end":
            if block is None:
                raise fail(path, "'end' without 'begin' in :bonedata")
            bones_add(path, block, bones, af, nums)
            block = None
        elif block is not None:
            if key in ("id", "name", "direction", "length", "axis", "dof", "limits", "bodymass", "cofmass"):
                block[key] = t[1:]
                last_key = key
            elif last_key == "limits":
                pass  # continuation lines of "limits"
            else:
                block[key] = t[1:]
    if block is not None:
        raise fail(path, "truncated ASF file: a bone block is not closed")
    if not bones:
        raise fail(path, "the ASF file defines no bones")

    hier_keys = [t[0].lower() for t in sections["hierarchy"]]
    if "begin" in hier_keys and "end" not in hier_keys[hier_keys.index("begin"):]:
        raise fail(path, "truncated ASF file: the :hierarchy block is not closed")
    children: dict[str, list[str]] = {}
    seen = set()
    in_block = False
    for t in sections["hierarchy"]:
        key = t[0].lower()
        if key == "begin":
            in_block = True
            continue
        if key == "end":
            in_block = False
            continue
        if not in_block:
            continue
        parent = t[0].lower()
        if parent != "root" and parent not in bones:
            raise fail(path, f"hierarchy names unknown bone {t[0]!r}")
        for c in t[1:]:
            c = c.lower()
            if c not in bones:
                raise fail(path, f"hierarchy names unknown bone {c!r}")
            if c in seen:
                raise fail(path, f"bone {c!r} has two parents in the hierarchy")
            seen.add(c)
            children.setdefault(parent, []).append(c)
    if in_block:
        raise fail(path, "truncated ASF file: the :hierarchy block is not closed")
    if not children.get("root"):
        raise fail(path, "the hierarchy attaches no bone to the root")
    return ASF(
        name=" ".join(sections.get("name", [["?"]])[0]),
        length_unit=length_unit,
        angle_unit=angle_unit,
        root_order=order,
        root_axis_order=root_axis,
        root_position=position,
        root_orientation=orientation,
        bones=bones,
        children=children,
    )


def bones_add(path: Path, block: dict[str, list[str]], bones: dict[str, Bone], af: float, nums: Any) -> None:
    """Check one ``begin ... end`` bone block and add it to ``bones``."""
    if "name" not in block or not block["name"]:
        raise fail(path, "a bone block has no name")
    name = block["name"][0].lower()
    for need in ("direction", "length"):
        if need not in block:
            raise fail(path, f"bone {name!r} has no {need}")
    direction = nums(block["direction"], 3, f"direction of bone {name!r}")
    length = float(nums(block["length"], 1, f"length of bone {name!r}")[0])
    axis_tokens = block.get("axis", ["0", "0", "0", "XYZ"])
    axis = nums(axis_tokens, 3, f"axis of bone {name!r}") * af
    order = axis_tokens[3].lower() if len(axis_tokens) > 3 else "xyz"
    if sorted(order) != ["x", "y", "z"]:
        raise fail(path, f"bad axis order {order!r} for bone {name!r}")
    dof = [d.lower() for d in block.get("dof", [])]
    if any(d not in _DOFS for d in dof):
        raise fail(path, f"bad dof {' '.join(dof)!r} for bone {name!r}")
    if any(d[0] != "r" for d in dof):
        # Stretching ("l") and sliding ("tx"...) bones are allowed by the spec but
        # not used by Vicon, CMU or HDM05 skeletons; they would not be rigid parts.
        raise fail(path, f"bone {name!r} has translation/length dof ({' '.join(dof)}), which is not supported")
    norm = np.linalg.norm(direction)
    if norm > 0:
        direction = direction / norm
    bones[name] = Bone(name=name, direction=direction, length=length, axis=axis, axis_order=order, dof=dof)


@dataclass
class AMC:
    """Parsed AMC motion: per bone (and ``"root"``) an array (F, n_values)."""

    values: dict[str, np.ndarray]
    frame_numbers: np.ndarray
    angle_unit: str | None


def read_amc(path: str | os.PathLike, asf: ASF) -> AMC:
    """Parse an AMC file against its skeleton."""
    path = check_file(path)
    text = path.read_text(encoding="latin-1")
    lines = []
    angle_unit = None
    for raw in text.splitlines():
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith(":"):
            key = s[1:].lower()
            if key.startswith("deg"):
                angle_unit = "deg"
            elif key.startswith("rad"):
                angle_unit = "rad"
            continue
        lines.append(s.split())
    if not lines:
        raise fail(path, "the AMC file holds no frames")
    starts = [i for i, t in enumerate(lines) if len(t) == 1 and t[0].isdigit()]
    if not starts or starts[0] != 0:
        raise fail(path, "not an AMC motion file: expected a frame number before the bone lines")
    n_per = np.diff(starts + [len(lines)]) - 1
    k = int(n_per[0])
    if k == 0:
        raise fail(path, "an AMC frame holds no bone lines")
    dof_count = {"root": len(asf.root_order)}
    dof_count.update({b: len(bone.dof) for b, bone in asf.bones.items()})
    F = len(starts)
    regular = bool(np.all(n_per == k))
    if regular:
        names = [t[0].lower() for t in lines]
        first = names[1:k + 1]
        regular = all(names[j + 1::k + 1] == [first[j]] * F for j in range(k))
    values: dict[str, np.ndarray] = {}
    if regular:
        # Every frame lists the same bones in the same order: one slice per bone.
        for j, b in enumerate(first):
            if b not in dof_count:
                raise fail(path, f"bone {b!r} is not in the skeleton")
            rows = [t[1:] for t in lines[j + 1::k + 1]]
            if any(len(r) != dof_count[b] for r in rows):
                bad = next(f for f, r in enumerate(rows) if len(r) != dof_count[b])
                raise fail(path, f"frame {lines[starts[bad]][0]}: bone {b!r} has {len(rows[bad])} values, "
                                 f"the skeleton gives it {dof_count[b]} dof")
            try:
                values[b] = np.array(rows, dtype=float).reshape(F, dof_count[b])
            except ValueError:
                raise fail(path, f"non-numeric value for bone {b!r}") from None
    else:
        collected: dict[str, list[np.ndarray]] = {}
        for f, s in enumerate(starts):
            end = starts[f + 1] if f + 1 < F else len(lines)
            for t in lines[s + 1:end]:
                b = t[0].lower()
                if b not in dof_count:
                    raise fail(path, f"frame {lines[s][0]}: bone {b!r} is not in the skeleton")
                if len(t) - 1 != dof_count[b]:
                    raise fail(path, f"frame {lines[s][0]}: bone {b!r} has {len(t) - 1} values, "
                                     f"the skeleton gives it {dof_count[b]} dof")
                try:
                    v = np.array(t[1:], dtype=float)
                except ValueError:
                    raise fail(path, f"frame {lines[s][0]}: non-numeric value for bone {b!r}") from None
                collected.setdefault(b, [np.full(dof_count[b], np.nan)] * F)[f] = v
        values = {b: np.stack(v) for b, v in collected.items()}
        for b, v in values.items():
            if np.isnan(v).any():
                missing = int(np.isnan(v).any(axis=1).sum())
                raise fail(path, f"bone {b!r} is missing from {missing} frame(s) (truncated file?)")
    if "root" not in values:
        raise fail(path, "the AMC file has no root line")
    for b, v in values.items():
        if not np.isfinite(v).all():
            raise fail(path, f"non-finite value for bone {b!r}")
    frame_numbers = np.array([int(lines[s][0]) for s in starts])
    return AMC(values=values, frame_numbers=frame_numbers, angle_unit=angle_unit)


def _rot(order: str, angles: np.ndarray) -> np.ndarray:
    """Rotations about fixed axes applied in ``order`` (lowercase), angles (F, len(order)) in radians."""
    return Rotation.from_euler(order, angles).as_matrix()


def asf_amc_rig(asf: ASF, amc: AMC) -> Rig:
    """Forward kinematics: the posed :class:`Rig` (frames: the root and every bone)."""
    F = amc.frame_numbers.size
    amc_af = _angle_factor(amc.angle_unit or asf.angle_unit)
    L = asf.length_unit
    # Frames in parent-first order.
    names = ["root"]
    parent = [-1]
    queue = list(asf.children.get("root", []))
    parent_of = {c: 0 for c in queue}
    while queue:
        b = queue.pop(0)
        names.append(b)
        parent.append(parent_of[b])
        for c in asf.children.get(b, []):
            parent_of[c] = len(names) - 1
            queue.append(c)
    J = len(names)
    R = np.empty((J, F, 3, 3))
    start = np.empty((J, F, 3))
    end = np.empty((J, F, 3))

    rv = amc.values["root"]
    rot_idx = [i for i, o in enumerate(asf.root_order) if o[0] == "r"]
    trans = np.tile(asf.root_position, (F, 1)).astype(float)
    for i, o in enumerate(asf.root_order):
        if o[0] == "t":
            trans[:, "xyz".index(o[1])] += rv[:, i]
    C = _rot(asf.root_axis_order, asf.root_orientation[["xyz".index(a) for a in asf.root_axis_order]][None])[0]
    if rot_idx:
        M = _rot("".join(asf.root_order[i][1] for i in rot_idx), rv[:, rot_idx] * amc_af)
    else:
        M = np.broadcast_to(np.eye(3), (F, 3, 3))
    R[0] = C @ M @ C.T
    start[0] = end[0] = trans / L

    bone_local = np.zeros((J, 3))
    for j in range(1, J):
        bone = asf.bones[names[j]]
        p = parent[j]
        C = _rot(bone.axis_order, bone.axis[["xyz".index(a) for a in bone.axis_order]][None])[0]
        vals = amc.values.get(bone.name)
        rdofs = [i for i, d in enumerate(bone.dof) if d[0] == "r"]
        if vals is not None and rdofs:
            M = _rot("".join(bone.dof[i][1] for i in rdofs), vals[:, rdofs] * amc_af)
            Rl = C @ M @ C.T
        else:
            Rl = np.broadcast_to(np.eye(3), (F, 3, 3))
        R[j] = R[p] @ Rl
        seg = bone.direction * bone.length / L
        bone_local[j] = seg
        start[j] = end[p]
        end[j] = start[j] + np.einsum("fij,j->fi", R[j], seg)
    return Rig(
        names=names,
        parent=np.asarray(parent, np.int64),
        rotation=R,
        origin=start,
        point_names=names,
        point_frame=np.arange(J),
        point_local=bone_local,
        bone_names=names[1:],
        bone_frame=np.arange(1, J),
        bone_start=np.zeros((J - 1, 3)),
        bone_end=bone_local[1:],
    )


def find_asf(amc_path: Path) -> Path:
    """The skeleton file beside an AMC file.

    Tries ``<stem>.asf``, then the subject prefix conventions (HDM05:
    ``HDM_dg_06-03_03_120.amc`` → ``HDM_dg.asf``; CMU: ``131_01.amc`` →
    ``131.asf``), then the only ``.asf`` in the folder.
    """
    folder = amc_path.parent
    asfs = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".asf") if folder.is_dir() else []
    by_stem = {p.stem.lower(): p for p in asfs}
    stem = amc_path.stem.lower()
    # Longest ASF stem that prefixes the AMC stem at a "_" boundary (or equals it).
    best = None
    for s, p in by_stem.items():
        if stem == s or stem.startswith(s + "_"):
            if best is None or len(s) > len(best[0]):
                best = (s, p)
    if best is not None:
        return best[1]
    if len(asfs) == 1:
        return asfs[0]
    if not asfs:
        raise FileNotFoundError(f"no .asf skeleton beside {amc_path}; pass asf='path/to/skeleton.asf'")
    raise OptionError(f"several .asf files beside {amc_path} and none matches its name "
                     f"({', '.join(p.name for p in asfs)}); pass asf='...'")


# HDM05 names end in the capture rate ("HDM_dg_06-03_03_120"); CMU names
# ("131_01") end in a trial number, so at least three fields are required.
_RATE_IN_NAME = re.compile(r"^[^_]+_[^_]+_.*_([1-9]\d{1,3})$")
_MM_PER = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


def load_amc(
    path: str | os.PathLike,
    *,
    asf: str | os.PathLike | None = None,
    frame_rate: float | None = None,
    markers_per_bone: int = 0,
    random_state: Any = None,
    marker_spread: float = 0.25,
    merge_rigid: bool = True,
    scale: float = 1.0,
    units: str | None = None,
) -> Trajectories:
    """Load an AMC motion (with its ASF skeleton) as 3D trajectories.

    Parameters
    ----------
    path : path-like
        The ``.amc`` file.
    asf : path-like, optional
        The skeleton; found beside the AMC file when omitted (see :func:`find_asf`).
    frame_rate : float, optional
        Frames per second (AMC files do not store it).
    markers_per_bone, random_state, marker_spread, merge_rigid
        See :func:`stickfigure.io.bvh.load_bvh`.
    scale : float
        Factor applied to every position (after any unit conversion).
    units : {"mm", "cm", "m", "in"}, optional
        Unit of the result: converted to when the skeleton's unit is known
        (Vicon-style ``length 0.45``: inches), else just recorded.

    Returns
    -------
    Trajectories
        Positions (P, F, 3), y up, with ground truth from the bone hierarchy.
    """
    path = check_file(path)
    check_rig_options(markers_per_bone, marker_spread, scale)
    if frame_rate is not None:
        frame_rate = positive_option(frame_rate, "frame_rate")
    if units is not None and units not in _MM_PER:
        raise OptionError(f"units must be one of {', '.join(_MM_PER)}, got {units!r}")
    asf_path = check_file(asf) if asf is not None else find_asf(path)
    skeleton = read_asf(asf_path)
    native = "in" if abs(skeleton.length_unit - 0.45) < 1e-9 else None
    factor = _MM_PER[native] / _MM_PER[units] if (native and units) else 1.0
    motion = read_amc(path, skeleton)
    if motion.frame_numbers.size < 2:
        raise fail(path, f"the AMC file holds {motion.frame_numbers.size} frame(s); at least 2 are needed")
    rate_source = "argument"
    if frame_rate is None:
        m = _RATE_IN_NAME.search(path.stem)
        if m and 24 <= int(m.group(1)) <= 2000:
            frame_rate, rate_source = float(m.group(1)), "file name"
        else:
            frame_rate, rate_source = 120.0, "default (CMU capture rate)"
    rig = asf_amc_rig(skeleton, motion)
    return rig_to_trajectories(
        rig,
        markers_per_bone=markers_per_bone,
        random_state=random_state,
        marker_spread=marker_spread,
        merge_rigid=merge_rigid,
        scale=scale * factor,
        up_axis=1,
        frame_rate=frame_rate,
        meta={
            "source": str(path),
            "format": "asf/amc",
            "skeleton": str(asf_path),
            "units": units or native,
            "asf_length_unit": skeleton.length_unit,
            "angle_unit": motion.angle_unit or skeleton.angle_unit,
            "frame_rate_source": rate_source,
            "first_frame": int(motion.frame_numbers[0]),
            "n_figures": 1,  # an ASF skeleton is one tree (EMSkeleton(max_trees="auto") reads it)
        },
    )
