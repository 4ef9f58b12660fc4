"""Running a sweep's combinations: one in a worker (`run_combination`), all through one executor loop.

The executor is a `concurrent.futures.Executor`: a ProcessPoolExecutor by default, or the executor of a
dask.distributed Client (`--scheduler ADDRESS`); the same loop submits the combinations and handles the
results as they complete (`concurrent.futures.wait`, FIRST_COMPLETED). Each finished combination is
written at once to DIR/runs/<id>.json (atomically), so a sweep stopped in any way keeps what finished, and
a rerun skips it.

Finished means: the run returned (also with `error` set, e.g. too little GP training data; the summary
counts it as failed and a rerun does not repeat it). Not finished, so re-run by a rerun: an interrupted run
and a run whose worker raised or died (the error is printed, nothing is written).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from flightstack.recording.files import atomic_write_json, json_safe
from flightstack.sweep.plan import Combination, SweepError, canonical

RUNS_DIR = "runs"


def job_of(c: Combination, base_dir: Path, keep_dir: Path | None) -> dict[str, Any]:
    """What a worker receives for combination `c` (plain data: it crosses process and host boundaries)."""
    return {
        "id": c.id,
        "mission": c.mission,
        "base_dir": str(base_dir),
        "keep_dir": None if keep_dir is None else str(keep_dir / c.id),
    }


def run_combination(job: dict[str, Any]) -> dict[str, Any]:
    """In a worker: validate the job's mission, fly it (flightstack.runtime.flight), return its metrics
    (JSON-safe).

    The worker's thread pools follow the one rule (flightstack.threads: one BLAS and one numba thread a
    flight), applied here too, since a Dask worker inherits nothing from the sweep's process. SIGINT
    interrupts the run (workers of the local pool ignore it between runs); the result then says
    `interrupted` and is not kept. With
    `keep_dir` the run's full directory is written there (no plots).
    Safety events are not logged (40 runs' takeoffs and landings would bury the progress lines); they are
    in the metrics (`safety_events`, `safety_event_counts`)."""
    from flightstack import threads
    from flightstack.config.mission import parse_mission
    from flightstack.runtime.flight import Flight, write_run_dir

    logging.getLogger("flightstack.safety").setLevel(logging.ERROR)
    on_main = threading.current_thread() is threading.main_thread()  # Dask runs tasks in threads
    previous = signal.signal(signal.SIGINT, signal.default_int_handler) if on_main else None
    t0 = time.perf_counter()
    try:
        mission = parse_mission(job["mission"], f"sweep run {job['id']}")
        mission._base_dir = Path(job["base_dir"])
        threads.apply(threads.limits_for(1))
        with Flight(mission) as flight:
            res = flight.fly()
        if job.get("keep_dir") and not res.interrupted:
            write_run_dir(Path(job["keep_dir"]), mission, res)
    except KeyboardInterrupt:
        return {"id": job["id"], "interrupted": True}
    finally:
        if on_main:
            signal.signal(signal.SIGINT, previous)
    return {
        "id": job["id"],
        "interrupted": bool(res.interrupted),
        "error": res.error,
        "metrics": json_safe(res.metrics),
        "wall_seconds": time.perf_counter() - t0,
    }


def _ignore_sigint() -> None:
    """Initializer of the local pool's workers: Ctrl-C reaches only a running combination."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def result_path(out: Path, cid: str) -> Path:
    return out / RUNS_DIR / f"{cid}.json"


def write_result(out: Path, c: Combination, result: dict[str, Any]) -> dict[str, Any]:
    """DIR/runs/<id>.json (atomic): the seed, the set values, the metrics, the resolved mission; returned."""
    record = {
        "id": c.id,
        "seed": c.seed,
        "point": c.point,
        "values": c.values,
        "error": result.get("error"),
        "wall_seconds": result.get("wall_seconds"),
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "metrics": result.get("metrics"),
        "mission": c.mission,
    }
    atomic_write_json(result_path(out, c.id), record, strict=False)
    return record


def load_finished(out: Path, combinations: list[Combination]) -> dict[str, dict[str, Any]]:
    """The finished combinations' records: DIR/runs/<id>.json readable and of the same resolved mission."""
    done = {}
    for c in combinations:
        try:
            record = json.loads(result_path(out, c.id).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(record, dict) and canonical(record.get("mission")) == c.mission:
            done[c.id] = record
    return done


@contextmanager
def open_executor(jobs: int, scheduler: str | None) -> Iterator[tuple[Executor, str, int | None]]:
    """(executor, description, in_flight for `run_all`): `jobs` local worker processes, or the Dask cluster
    at `scheduler` (every combination submitted at once: its scheduler queues them, cancels what is left)."""
    if scheduler is None:
        pool = ProcessPoolExecutor(max_workers=jobs, initializer=_ignore_sigint)
        try:
            yield pool, f"{jobs} local worker process{'es' if jobs > 1 else ''}", jobs
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return
    try:
        from distributed import Client
    except ImportError:
        raise SweepError(
            "--scheduler needs Dask's distributed package: pip install 'flightstack[dask]'"
        ) from None
    client = Client(scheduler, timeout="20s")
    try:
        yield client.get_executor(), f"the Dask cluster at {scheduler}", None
    finally:
        client.close()


def run_all(
    executor: Executor,
    todo: list[Combination],
    job: Callable[[Combination], dict[str, Any]],
    on_result: Callable[[Combination, dict[str, Any]], None],
    on_failure: Callable[[Combination, BaseException], None],
    in_flight: int | None = None,
) -> bool:
    """Submit the combinations of `todo` (at most `in_flight` at a time; None: all at once), hand each
    result (or failure) over as it completes; True when interrupted (Ctrl-C or SIGTERM): what was not
    started is cancelled, running local workers get SIGINT, and results that complete meanwhile are still
    handed over. Interrupted runs are dropped.

    The local pool gets in_flight = its workers: a ProcessPoolExecutor starts queued work on its own (a
    submitted future soon cannot be cancelled), so after Ctrl-C only the runs already flying remain."""
    queue = list(reversed(todo))
    futures: dict[Future[dict[str, Any]], Combination] = {}
    handled: set[Future[dict[str, Any]]] = set()

    def handle(fut: Future[dict[str, Any]]) -> None:
        handled.add(fut)
        c = futures[fut]
        exc = fut.exception()
        if exc is not None:
            on_failure(c, exc)
            return
        result = fut.result()
        if not result.get("interrupted"):
            on_result(c, result)

    try:
        while queue or len(handled) < len(futures):
            while queue and (in_flight is None or len(futures) - len(handled) < in_flight):
                c = queue.pop()
                futures[executor.submit(run_combination, job(c))] = c
            done, _ = wait([f for f in futures if f not in handled], return_when=FIRST_COMPLETED)
            for fut in done:
                handle(fut)
        return False
    except KeyboardInterrupt:
        for fut in futures:
            fut.cancel()
        _interrupt_local_workers(executor)
        if isinstance(executor, ProcessPoolExecutor):
            executor.shutdown(wait=True, cancel_futures=True)  # the interrupted runs return quickly
        for fut in futures:
            if fut.done() and not fut.cancelled() and fut not in handled:
                handle(fut)
        return True


def _interrupt_local_workers(executor: Executor) -> None:
    """SIGINT to the local pool's worker processes (a terminal's Ctrl-C reached them already; a SIGTERM
    to this process did not). Nothing for a Dask executor: its cancelled tasks are dropped."""
    processes = getattr(executor, "_processes", None) or {}
    for proc in list(processes.values()):
        with suppress(OSError, AttributeError, TypeError):
            os.kill(proc.pid, signal.SIGINT)
