"""How many threads the linear-algebra library may use inside the methods, and how many CPUs
the process may use (the default worker count of the methods that run jobs in parallel).

The methods' work is many small matrix problems (per-cluster eigenproblems,
per-frame 2x3 Procrustes fits, batched 3x3 solves). Multithreaded BLAS only
adds synchronisation to these: on 2 cores, one BLAS thread made
``multibody-sfm`` 1.5-2x faster on a 3-body scene, and ``mcmc`` runs its chains
in separate processes anyway. So fitting and imputing run with one BLAS thread
unless ``STICKFIGURE_BLAS_THREADS`` says otherwise (an integer, or ``"auto"`` to
leave the library's own setting).
"""

from __future__ import annotations

import contextlib
import os
from typing import Iterator

from threadpoolctl import threadpool_limits

__all__ = ["available_cpus", "blas_threads"]


def available_cpus() -> int:
    """CPUs this process may run on: its affinity mask where the platform has one (a container or
    ``taskset`` may allow fewer than ``os.cpu_count()`` reports), else ``os.cpu_count()``."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def blas_threads() -> Iterator[None]:
    """Limit BLAS threads for the duration of a fit (see the module docstring)."""
    setting = os.environ.get("STICKFIGURE_BLAS_THREADS", "1").strip().lower()
    if setting == "auto":
        yield
        return
    try:
        n = int(setting)
    except ValueError:
        raise ValueError(f"STICKFIGURE_BLAS_THREADS must be a positive integer or 'auto', got {setting!r}") from None
    if n < 1:
        raise ValueError(f"STICKFIGURE_BLAS_THREADS must be a positive integer or 'auto', got {setting!r}")
    with threadpool_limits(limits=n, user_api="blas"):
        yield
