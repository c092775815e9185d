"""Small HTML builders: escaped text, tables, inline SVG sparklines, and a generic view of ``skeleton.info``."""

from __future__ import annotations

import html
import json
import math
from typing import Any, Iterable, Sequence

import numpy as np

__all__ = ["esc", "fmt", "table", "sparkline", "info_view", "kpis", "figure", "section"]


def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def fmt(v: Any, digits: int = 4) -> str:
    """A number as a person reads it: 4 significant digits, thousands separators for large integers."""
    if v is None:
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return f"{int(v):,}"
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return "–"
        if math.isinf(f):
            return "∞" if f > 0 else "−∞"
        if f != 0 and (abs(f) >= 1e6 or abs(f) < 1e-3):
            return f"{f:.{digits - 1}e}"
        return f"{f:.{digits}g}"
    return str(v)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def table(header: Sequence[str], rows: Iterable[Sequence[Any]], *, numeric: Sequence[bool] | None = None,
          raw: Sequence[bool] | None = None, cls: str = "") -> str:
    """An HTML table; cells are escaped unless their column is ``raw``."""
    n = len(header)
    numeric = list(numeric) if numeric is not None else [False] * n
    raw = list(raw) if raw is not None else [False] * n
    head = "".join(f'<th class="num">{esc(h)}</th>' if numeric[i] else f"<th>{esc(h)}</th>"
                   for i, h in enumerate(header))
    body = []
    for r in rows:
        cells = []
        for i, v in enumerate(r):
            text = v if raw[i] else esc(fmt(v) if _is_num(v) or v is None else v)
            cells.append(f'<td class="num">{text}</td>' if numeric[i] else f"<td>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    c = f' class="{esc(cls)}"' if cls else ""
    return f"<table{c}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def sparkline(values: Sequence[float], *, width: int = 220, height: int = 40, mark_best: str | None = None) -> str:
    """An inline SVG line chart of a series (NaN/None skipped)."""
    y = np.array([np.nan if v is None else float(v) for v in values], float)
    ok = np.isfinite(y)
    if ok.sum() < 2:
        return ""
    x = np.arange(len(y))
    lo, hi = float(np.min(y[ok])), float(np.max(y[ok]))
    span = hi - lo if hi > lo else 1.0
    px = 3 + (x / max(len(y) - 1, 1)) * (width - 6)
    py = height - 3 - (y - lo) / span * (height - 6)
    pts = " ".join(f"{a:.1f},{b:.1f}" for a, b, k in zip(px, py, ok) if k)
    best = ""
    if mark_best in ("max", "min"):
        i = int(np.nanargmax(np.where(ok, y, -np.inf)) if mark_best == "max" else np.nanargmin(np.where(ok, y, np.inf)))
        best = f'<circle cx="{px[i]:.1f}" cy="{py[i]:.1f}" r="3" fill="#dc2626"/>'
    return (f'<svg class="spark" width="{width}" height="{height}" viewBox="0 0 {width} {height}" role="img" '
            f'aria-label="series of {len(y)} values from {fmt(lo)} to {fmt(hi)}">'
            f'<polyline fill="none" stroke="#2563eb" stroke-width="1.5" points="{pts}"/>{best}</svg>')


def _heat_table(m: np.ndarray, labels: Sequence[str] | None = None) -> str:
    """A small matrix as a table with cells shaded by value."""
    finite = m[np.isfinite(m)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    span = hi - lo if hi > lo else 1.0
    labels = list(labels) if labels is not None else [str(i) for i in range(m.shape[0])]
    rows = []
    for i in range(m.shape[0]):
        cells = []
        for j in range(m.shape[1]):
            v = m[i, j]
            if not np.isfinite(v):
                cells.append('<td class="num">–</td>')
                continue
            a = (v - lo) / span
            cells.append(f'<td class="num" style="background: rgba(37,99,235,{0.08 + 0.6 * a:.2f})">{esc(fmt(v, 3))}</td>')
        rows.append(f"<tr><th>{esc(labels[i] if i < len(labels) else i)}</th>{''.join(cells)}</tr>")
    head = "".join(f'<th class="num">{esc(labels[j] if j < len(labels) else j)}</th>' for j in range(m.shape[1]))
    return f"<table><thead><tr><th></th>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


def _numeric_list(v: Any) -> bool:
    return isinstance(v, (list, tuple)) and len(v) >= 2 and all(_is_num(x) or x is None for x in v)


def _matrix(v: Any) -> np.ndarray | None:
    if isinstance(v, (list, tuple)) and len(v) >= 2 and all(_numeric_list(r) for r in v):
        lens = {len(r) for r in v}
        if len(lens) == 1:
            return np.array([[np.nan if x is None else float(x) for x in r] for r in v])
    return None


def _compact(v: Any, limit: int = 120) -> str:
    """A short text for a cell: small values as JSON, long or nested lists as their shape."""
    if isinstance(v, (list, tuple)):
        shape = np.shape(v) if _rectangular(v) else (len(v),)
        if len(v) > 8 or (v and isinstance(v[0], (list, tuple)) and len(shape) > 1 and np.prod(shape) > 8):
            return f"[{' × '.join(str(n) for n in shape)} values]"
    s = json.dumps(v, default=str) if not isinstance(v, str) else v
    return s if len(s) <= limit else s[: limit - 1] + "…"


def _rectangular(v: Any) -> bool:
    try:
        np.asarray(v, dtype=float)
        return True
    except (TypeError, ValueError):
        return False


def _records(key: str, v: list[dict[str, Any]], selected: Any = None) -> str:
    """A list of records (e.g. one per merge stage) as a table, numeric columns also as sparklines."""
    keys: list[str] = []
    for r in v:
        keys += [k for k in r if k not in keys]
    numeric = [all(_is_num(r.get(k)) or r.get(k) is None for r in v) for k in keys]
    rows = []
    for i, r in enumerate(v):
        cells = [fmt(r.get(k)) if numeric[j] else _compact(r.get(k)) for j, k in enumerate(keys)]
        rows.append([esc(f"{i} ◀ selected" if selected == i else str(i))] + [esc(c) for c in cells])
    out = f"<h3>{esc(key)}</h3>" + table(["#"] + keys, rows, numeric=[False] + numeric,
                                          raw=[True] * (len(keys) + 1))
    spark = []
    for j, k in enumerate(keys):
        vals = [r.get(k) for r in v]
        if numeric[j] and len(v) >= 2 and len({x for x in vals if x is not None}) > 1:
            mark = "max" if any(w in k.lower() for w in ("objective", "likelihood", "log_joint", "score")) else None
            spark.append(f"<span class=\"muted\">{esc(k)}</span> {sparkline(vals, width=160, height=34, mark_best=mark)}")
    if spark:
        out += f"<p>{' &nbsp; '.join(spark)}</p>"
    return out


def info_view(info: dict[str, Any], *, depth: int = 0) -> str:
    """A readable view of a method's JSON diagnostics.

    Scalars become a table, numeric series a sparkline with their range and
    last value, small matrices a shaded table, lists of records a table with
    one row per record; anything else is shown as JSON.
    """
    scalars, parts = [], []
    for key, v in info.items():
        if _is_num(v) or isinstance(v, (str, bool)) or v is None:
            scalars.append((key, v))
        elif isinstance(v, dict):
            inner = info_view(v, depth=depth + 1)
            parts.append(f"<h3>{esc(key)}</h3>{inner}" if depth < 2 else
                         f"<details><summary>{esc(key)}</summary>{inner}</details>")
        elif _numeric_list(v):
            arr = np.array([np.nan if x is None else float(x) for x in v])
            ok = np.isfinite(arr)
            stats = (f"{len(arr)} values, range {fmt(np.min(arr[ok]))} … {fmt(np.max(arr[ok]))}, last {fmt(arr[ok][-1])}"
                     if ok.any() else f"{len(arr)} values")
            mark = "max" if any(w in key.lower() for w in ("objective", "likelihood", "log_joint", "score")) else None
            parts.append(f"<p><b>{esc(key)}</b> {sparkline(v, mark_best=mark)} <span class=\"muted\">{esc(stats)}</span></p>")
        elif (m := _matrix(v)) is not None and max(m.shape) <= 30:
            parts.append(f"<h3>{esc(key)}</h3>{_heat_table(m)}")
        elif isinstance(v, (list, tuple)) and v and all(isinstance(r, dict) for r in v) and len(v) <= 200:
            sel = info.get("selected_stage") if key == "stages" else info.get(f"selected_{key.rstrip('s')}")
            parts.append(_records(key, list(v), sel))
        else:
            text = json.dumps(v, indent=1, default=str)
            if len(text) > 20000:
                text = text[:20000] + "\n… (cut)"
            parts.append(f"<details><summary>{esc(key)}</summary><pre class=\"json\">{esc(text)}</pre></details>")
    out = table(["value", ""], [(k, v if _is_num(v) or v is None else _compact(v)) for k, v in scalars],
                numeric=[False, True]) if scalars else ""
    return out + "".join(parts)


def kpis(items: Sequence[tuple[str, Any]]) -> str:
    cells = "".join(f'<div class="kpi"><div class="v">{esc(fmt(v) if _is_num(v) else v)}</div>'
                    f'<div class="k">{esc(k)}</div></div>' for k, v in items)
    return f'<div class="kpis">{cells}</div>'


def figure(uri: str, caption: str, alt: str | None = None) -> str:
    return (f'<figure><img src="{uri}" alt="{esc(alt or caption)}"><figcaption>{esc(caption)}</figcaption></figure>')


def section(anchor: str, title: str, body: str) -> str:
    return f'<section class="card" id="{esc(anchor)}"><h2>{esc(title)}</h2>{body}</section>'
