"""The process's thread pools, sized once: BLAS (OpenBLAS, MKL; OpenMP with them) and numba.

One rule for `run`, `sweep` and every other command, decided before the work starts (`apply`, called by
the CLI before it imports a command's modules, and by each sweep worker): every flight gets ONE BLAS
thread and ONE numba thread, and the process runs as many flights at once as it has workers (1 for a
run, `--jobs` for a sweep, by default the CPUs it may use: `usable_cpus`).

Why one: a flight's own parallelism is already its loop, its recorder thread and, on the emulated lab, the
drivers' receiver threads; no numba kernel is parallel (`flightstack/paper/kernels.py`); and the GP
problems are small (a few hundred samples per expert), so a second BLAS thread saves little, while
OpenBLAS's spinning threads on cores that something else keeps busy made GP training of `paper_sim` take
12-16 s instead of about 0.5 s (docs/performance.md, "Thread pools"). The limits are set as environment
variables too, so that processes a command starts (sweep workers, the emulated lab's and agents'
processes) inherit them before they load BLAS.
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass
from typing import Any

BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
NUMBA_ENV = "NUMBA_NUM_THREADS"
PER_FLIGHT = 1
"""BLAS and numba threads of one flight (the module's docstring says why)."""


@dataclass(frozen=True)
class ThreadLimits:
    """The process's thread pools: `cpus` it may run on, `workers` flights at once, and each flight's
    `blas` and `numba` threads."""

    cpus: int
    workers: int
    blas: int
    numba: int

    def line(self) -> str:
        """One line for a command's output."""
        flights = "1 flight" if self.workers == 1 else f"{self.workers} flights at once"
        return (
            f"threads: BLAS {self.blas}, numba {self.numba} per flight; {flights} on "
            f"{self.cpus} usable CPU{'s' if self.cpus != 1 else ''}"
        )

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask; os.cpu_count where there is none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def limits_for(workers: int = 1) -> ThreadLimits:
    """The rule: `workers` flights at once (≥ 1), each with PER_FLIGHT BLAS and numba threads."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, not {workers}")
    return ThreadLimits(cpus=usable_cpus(), workers=int(workers), blas=PER_FLIGHT, numba=PER_FLIGHT)


_applied: ThreadLimits | None = None


def apply(limits: ThreadLimits) -> ThreadLimits:
    """Size this process's pools to `limits` (each flight's share) and export them to its children:
    environment variables for libraries not loaded yet, threadpoolctl for BLAS/OpenMP libraries loaded
    already, numba.set_num_threads if numba is loaded. Returns `limits`."""
    global _applied
    for name in BLAS_ENV:
        os.environ[name] = str(limits.blas)
    if "numpy" in sys.modules or "scipy" in sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=limits.blas)
    numba = sys.modules.get("numba")
    if numba is None:
        os.environ[NUMBA_ENV] = str(limits.numba)
    elif limits.numba <= numba.config.NUMBA_NUM_THREADS:  # numba refuses a changed variable once loaded
        numba.set_num_threads(limits.numba)
    _applied = limits
    return limits


def applied() -> ThreadLimits | None:
    """The limits `apply` set in this process (None if it was not called)."""
    return _applied


def in_effect() -> ThreadLimits:
    """The pools as they are now, read from the libraries: BLAS the largest pool of the BLAS libraries
    threadpoolctl sees loaded (0: none), numba its pool's limit; `workers` as applied (else 1)."""
    from threadpoolctl import threadpool_info

    pools = [int(i["num_threads"]) for i in threadpool_info() if i.get("user_api") == "blas"]
    numba = sys.modules.get("numba")
    if numba is None:
        n_numba = int(os.environ.get(NUMBA_ENV, usable_cpus()))
    elif getattr(sys.modules.get("numba.np.ufunc.parallel"), "_is_initialized", False):
        n_numba = int(numba.get_num_threads())  # its pool runs: the limit set_num_threads gave it
    else:
        n_numba = int(numba.config.NUMBA_NUM_THREADS)  # the pool it would start
    return ThreadLimits(
        cpus=usable_cpus(),
        workers=_applied.workers if _applied is not None else 1,
        blas=max(pools, default=0),
        numba=n_numba,
    )
