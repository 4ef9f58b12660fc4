"""Background takeoff and land of one wrapped drone (DESIGN §7): each runs on a worker thread (a Tello's
take seconds) and the control thread collects the outcome later, never waiting. Times: mission clock, s."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass


@dataclass
class DroneJob:
    """A takeoff or land of the wrapped drone running on a worker thread."""

    kind: str  # "takeoff" or "land"
    reason: str
    started: float  # mission clock (s)
    error: BaseException | None = None
    finished: bool = False
    collected: bool = False
    thread: threading.Thread | None = None


class DroneJobs:
    """The latest job of each kind of one drone (SafeDrone with `background` on)."""

    def __init__(self, drone_id: int) -> None:
        self._drone_id = drone_id
        self._jobs: dict[str, DroneJob] = {}

    def get(self, kind: str) -> DroneJob | None:
        return self._jobs.get(kind)

    def start(self, kind: str, fn: Callable[[], None], reason: str, now: float) -> None:
        """Run fn (the wrapped drone's takeoff or land) on a worker thread; `collect` reports its end."""
        job = DroneJob(kind, reason, now)

        def run() -> None:
            try:
                fn()
            except BaseException as exc:  # collected on the control thread
                job.error = exc
            finally:
                job.finished = True

        job.thread = threading.Thread(target=run, name=f"{kind}-drone{self._drone_id}", daemon=True)
        self._jobs[kind] = job
        job.thread.start()

    def collect(self) -> Iterator[DroneJob]:
        """Each finished job not collected before, marked collected as it is yielded (a caller may start or
        collect jobs while iterating)."""
        for job in list(self._jobs.values()):
            if not job.finished or job.collected:
                continue
            job.collected = True
            yield job

    def join(self, timeout_s: float) -> None:
        """Wait for every job's thread, at most `timeout_s` (wall clock) each."""
        for job in list(self._jobs.values()):
            if job.thread is not None:
                job.thread.join(timeout_s)
