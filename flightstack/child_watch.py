"""Waiting for a child process for as long as it makes progress, not for a fixed time: a child that is
slow because the machine is loaded keeps being waited for, one that is stopped (SIGSTOP), hung on a lock or
a dead disk is killed once it has made no progress for a while.

Progress is any change of a value sampled every WATCH_PERIOD_S: by default the child's CPU time (the sum
over its threads of /proc/PID/task/*/schedstat's first field, ns; Linux), to which a caller adds what it
can see of the child's work (the live MCAP's writer: its file's size). A child on a busy machine still gets
slices of a core, so its CPU time advances; a stopped child's does not. A child waiting for a core (a
thread in state R, runnable: /proc/PID/task/*/stat) counts as progressing too: at nice 19 beside a loaded
flight it got no slice for over 2.5 s and was killed though healthy (a CI run beside CPU-bound processes),
while a stopped child is in state T and a hung one in S or D. Where /proc is missing the CPU time cannot be
read, it counts as progress at every sample, and only the overall cap applies."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Callable, Hashable
from pathlib import Path

WATCH_PERIOD_S = 0.1
"""How often (s) the child's progress is sampled."""


def cpu_ns(pid: int) -> int | None:
    """CPU time (ns) of process `pid`, all its threads; None where it cannot be read (no /proc, gone)."""
    total = 0
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                total += int((task / "schedstat").read_text().split()[0])
            except (OSError, ValueError, IndexError):
                continue  # a thread that just ended
    except OSError:
        return None
    return total


def runnable(pid: int) -> bool:
    """Whether a thread of process `pid` is runnable (state R: running or waiting for a core); False where
    it cannot be read."""
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                stat = (task / "stat").read_text()
            except OSError:
                continue  # a thread that just ended
            if stat[stat.rfind(")") + 2 : stat.rfind(")") + 3] == "R":  # the state follows "(comm) "
                return True
    except OSError:
        return False
    return False


def communicate_while_progressing(
    proc: subprocess.Popen[bytes],
    stall_s: float,
    cap_s: float,
    progress: Callable[[], Hashable] | None = None,
) -> tuple[bytes, bytes, str | None]:
    """Close the child's stdin and read its stdout and stderr until it exits (Popen.communicate), as long
    as it makes progress (module docstring): killed (SIGKILL) and reaped once it has made none for
    `stall_s` (s), or `cap_s` (s) after the call. `progress`: more of its work, sampled with its CPU time.
    Returns (stdout, stderr, why it was killed or None)."""
    pid = proc.pid

    def sample() -> Hashable:
        ns = cpu_ns(pid)
        if ns is None or runnable(pid):  # unreadable, or waiting for a core: progress
            return (time.monotonic(), None)
        return (ns, progress() if progress is not None else None)

    t0 = time.monotonic()
    last, last_change = sample(), t0
    first = True
    while True:
        try:
            out, err = proc.communicate(input=b"" if first else None, timeout=WATCH_PERIOD_S)
            return out, err, None
        except subprocess.TimeoutExpired:
            first = False
        now = time.monotonic()
        value = sample()
        if value != last:
            last, last_change = value, now
        if now - last_change >= stall_s:
            why = f"no progress (CPU time, output) for {now - last_change:.1f} s"
        elif now - t0 >= cap_s:
            why = f"still working after {now - t0:.0f} s"
        else:
            continue
        proc.send_signal(signal.SIGKILL)  # a stopped process dies of it too
        out, err = proc.communicate()
        return out, err, why
