"""The phases of one SafeDrone and the record of its background takeoff/land jobs (DESIGN §7).

flightstack/safety/drone.py (`SafeDrone`) moves through the `_Phase`s; flightstack/safety/landing.py runs the
wrapped drone's takeoff() and land() on worker threads, each tracked by a `_Job`. Times are mission-clock
seconds.
"""

from __future__ import annotations

import enum
import threading
from dataclasses import dataclass


class _Phase(enum.Enum):
    IDLE = "idle"  # built; nothing commanded yet (a sim drone may already be airborne)
    FLYING = "flying"  # after takeoff() or the first command: all rules enforced
    LAND_PENDING = "land_pending"  # land requested but not (yet) accepted: nothing but land retries sent
    LANDED = "landed"  # land accepted: nothing else is sent until a new takeoff()
    STOPPED = "stopped"  # emergency stop accepted: motors off


@dataclass
class _Job:
    """A takeoff or land of the wrapped drone running on a worker thread (a Tello's take seconds)."""

    kind: str  # "takeoff" or "land"
    reason: str
    started: float  # mission clock (s)
    error: BaseException | None = None
    finished: bool = False
    collected: bool = False
    thread: threading.Thread | None = None
