"""Run the benchmark suite and write a Markdown table and a CSV.

Usage::

    python -m benchmarks.run                      # every case, quick sizes
    python -m benchmarks.run --only em --full     # cases whose name contains "em", paper sizes
    python -m benchmarks.run --list

Each ``benchmarks/bench_*.py`` module defines ``CASES``, a list of
:class:`Case`. A case's function receives a :class:`Context` and yields result
rows (dicts). The runner times every row's work and records its peak memory
(tracemalloc, which sees numpy's allocations in this process only: work a fit
forks into children, with ``n_jobs`` > 1, is not counted; the memory targets'
rows run with ``n_jobs=1``), and reports time as a ratio
against a fixed numpy reference workload timed in the same process, so figures
from noisy machines can be compared.

Columns: suite, dataset, method, ari, misclassification, edge_f1, exact,
rmse, time_s, time_ratio, peak_mb, plus any extra keys a case adds (notes).
"""

from __future__ import annotations

import argparse
import csv
import importlib
import math
import os
import pkgutil
import sys
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

COLUMNS = ["suite", "dataset", "method", "ari", "misclassification", "edge_f1", "exact", "rmse",
           "time_s", "time_ratio", "peak_mb", "notes"]


@dataclass
class Context:
    """What a case gets: the data directory (or None), the size mode and a seed."""

    data_dir: Path | None
    full: bool = False
    seed: int = 0
    reference_s: float = 1.0

    def measure(self, fn: Callable[[], Any]) -> tuple[Any, dict[str, float]]:
        """Run ``fn()`` under tracemalloc; return its value and {time_s, time_ratio, peak_mb}."""
        tracemalloc.start()
        tracemalloc.reset_peak()
        try:
            out, timing = self.time(fn)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        return out, {**timing, "peak_mb": peak / 2**20}

    def time(self, fn: Callable[[], Any]) -> tuple[Any, dict[str, float]]:
        """Run ``fn()`` and time it, starting no tracing of its own; return its value and {time_s, time_ratio}.

        tracemalloc (:meth:`measure`) slows code made of many small numpy operations
        by half or more; cases that report a time target time the work with this and
        trace its memory in a separate run.
        """
        t0 = time.perf_counter()
        out = fn()
        elapsed = time.perf_counter() - t0
        return out, {"time_s": elapsed, "time_ratio": elapsed / self.reference_s}


@dataclass
class Case:
    """A named group of benchmark rows."""

    name: str
    run: Callable[[Context], Iterator[dict[str, Any]]]
    needs_data: bool = False
    tags: list[str] = field(default_factory=list)


def reference_seconds(repeats: int = 3) -> float:
    """Time of a fixed numpy workload (SVDs and matrix products), best of ``repeats``."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(300, 300))
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(5):
            np.linalg.svd(A)
            A @ A.T
        best = min(best, time.perf_counter() - t0)
    return best


def discover() -> list[Case]:
    """All cases from ``benchmarks/bench_*.py``, in module order."""
    here = Path(__file__).resolve().parent
    cases: list[Case] = []
    for info in sorted(pkgutil.iter_modules([str(here)]), key=lambda m: m.name):
        if info.name.startswith("bench_"):
            mod = importlib.import_module(f"benchmarks.{info.name}")
            cases.extend(getattr(mod, "CASES", []))
    return cases


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def write_tables(rows: list[dict[str, Any]], out_dir: Path, reference_s: float) -> tuple[Path, Path]:
    """Write ``results.csv`` and ``results.md`` in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    extra = sorted({k for r in rows for k in r} - set(COLUMNS))
    cols = COLUMNS + extra
    csv_path, md_path = out_dir / "results.csv", out_dir / "results.md"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in cols})
    shown = [c for c in cols if any(r.get(c) not in (None, "") for r in rows)]
    lines = [f"Reference workload: {reference_s:.3f} s (time_ratio = time_s / reference).", "",
             "| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c)) for c in shown) + " |")
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", default=[], help="run cases whose name contains this (repeatable)")
    ap.add_argument("--full", action="store_true", help="paper-sized problems and more seeds (slow)")
    ap.add_argument("--data", default=os.environ.get("STICKFIGURE_DATA"), help="real-data directory")
    ap.add_argument("--out", default="bench-out", help="output folder for results.md / results.csv")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    args = ap.parse_args(argv)
    cases = discover()
    if args.only:
        cases = [c for c in cases if any(o in c.name for o in args.only)]
    if args.list:
        for c in cases:
            print(c.name + ("  [data]" if c.needs_data else ""))
        return 0
    data_dir = Path(args.data) if args.data and Path(args.data).is_dir() else None
    ref = reference_seconds()
    ctx = Context(data_dir=data_dir, full=args.full, seed=args.seed, reference_s=ref)
    rows: list[dict[str, Any]] = []
    for case in cases:
        if case.needs_data and data_dir is None:
            print(f"skip {case.name}: no data directory (--data or STICKFIGURE_DATA)", file=sys.stderr)
            continue
        print(f"== {case.name}", file=sys.stderr, flush=True)
        for row in case.run(ctx):
            row.setdefault("suite", case.name)
            rows.append(row)
            print("   " + ", ".join(f"{k}={_fmt(v)}" for k, v in row.items() if k != "suite"), file=sys.stderr,
                  flush=True)
    csv_path, md_path = write_tables(rows, Path(args.out), ref)
    print(md_path.read_text())
    print(f"wrote {md_path} and {csv_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
