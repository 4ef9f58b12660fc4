"""This process's CPU priority on Linux: its nice value and its session's autogroup's.

Where Linux schedules by session (`/proc/sys/kernel/sched_autogroup_enabled`, on by default on many
distributions), a process's nice orders it only against the processes of its own session; between sessions
the autogroup's nice counts. A process that must run after the rest (the live MCAP's follower,
flightstack/recording/mcap_live.py) or before it (the flight's guardian, drivers/guardian/process.py) leads
its own session and sets both. Raising a priority (a negative nice) needs root or CAP_SYS_NICE; lowering it
needs nothing."""

from __future__ import annotations

import os
import time
from pathlib import Path

AUTOGROUP = Path("/proc/self/autogroup")
"""Linux's scheduling group of this process's session (absent without CONFIG_SCHED_AUTOGROUP)."""


def set_nice(nice: int) -> bool:
    """Set this process's nice value to `nice` (absolute, −20 … 19); False where not permitted."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (OSError, AttributeError):
        return False
    return True


def set_group_nice(nice: int, autogroup: Path = AUTOGROUP) -> bool:
    """Set the nice value of this process's session's autogroup, only when this process leads its session
    (run by hand from a shell it would renice the shell's whole session). The kernel takes one change per
    0.1 s from unprivileged processes (EAGAIN): retried a few times. False where there is no autogroup, or it
    was not changed (a negative value without the privilege)."""
    if os.getsid(0) != os.getpid():
        return False
    for _ in range(5):
        try:
            autogroup.write_text(f"{nice}\n")
            return True
        except BlockingIOError:
            time.sleep(0.11)
        except OSError:
            return False
    return False


__all__ = ["AUTOGROUP", "set_group_nice", "set_nice"]
