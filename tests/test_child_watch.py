"""Waiting for a child while it makes progress (flightstack.child_watch): a stopped child is killed once
it has made no progress for the stall time; a child kept slow (stopped most of the time, as a loaded
machine would starve it, though never for the stall time) is waited for past the stall time and not
killed."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time

from flightstack.child_watch import communicate_while_progressing, cpu_ns, runnable
from tests.conftest import Bound, process_running

STALL_S = 1.5
"""The stall time these tests use (s)."""
WORK = (
    "import time\nt = time.process_time()\nwhile time.process_time() - t < {cpu_s}:\n    pass\nprint('done')"
)
"""A child that needs `cpu_s` seconds of CPU, then prints `done`."""


def _child(cpu_s: float) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-c", WORK.format(cpu_s=cpu_s)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip


def _reap(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
        proc.wait(timeout=10)


def test_cpu_time_advances_while_a_process_runs() -> None:
    before = cpu_ns(os.getpid())
    t = time.process_time()
    while time.process_time() - t < 0.05:
        pass
    after = cpu_ns(os.getpid())
    assert before is not None and after is not None and after > before
    assert cpu_ns(2**22 + 1) is None  # above pid_max's default: no such process


def test_a_stopped_child_is_killed_after_the_stall_time(safety_bound: Bound) -> None:
    proc = _child(60.0)
    try:
        os.kill(proc.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        out, _, killed = communicate_while_progressing(proc, STALL_S, 300.0)
        waited = time.monotonic() - t0
    finally:
        _reap(proc)
    assert killed is not None and "no progress" in killed, killed
    assert out == b"" and proc.returncode == -signal.SIGKILL and not process_running(proc.pid)
    assert waited >= STALL_S
    safety_bound("a stopped child killed (stall time 1.5 s)", waited, STALL_S + 1.5, "s")


def test_a_slow_child_that_progresses_is_not_killed() -> None:
    """Stopped 1.0 s of every 1.2 s (below the stall time of 1.5 s): it needs 0.3 s of CPU, so it takes
    several stall times to finish, and is waited for."""
    proc = _child(0.3)
    done = threading.Event()

    def throttle() -> None:
        with contextlib.suppress(ProcessLookupError):  # it ended (and was reaped) between two signals
            while not done.is_set() and proc.returncode is None:
                os.kill(proc.pid, signal.SIGSTOP)
                done.wait(1.0)
                os.kill(proc.pid, signal.SIGCONT)
                done.wait(0.2)

    thread = threading.Thread(target=throttle, daemon=True)
    try:
        thread.start()
        t0 = time.monotonic()
        out, err, killed = communicate_while_progressing(proc, STALL_S, 300.0)
        waited = time.monotonic() - t0
    finally:
        done.set()
        thread.join(timeout=5)
        _reap(proc)
    print(f"a throttled child finished after {waited:.1f} s (stall time {STALL_S} s)")
    assert killed is None and out.strip() == b"done" and proc.returncode == 0, (killed, err)
    assert waited > STALL_S


def test_runnable_tells_a_child_waiting_for_a_core_from_a_stopped_or_sleeping_one() -> None:
    """A busy child is runnable (state R: at nice 19 on a loaded machine it may wait seconds for a core and
    is not stalled); a stopped one (SIGSTOP, state T) and a sleeping one (state S) are not."""
    busy = subprocess.Popen([sys.executable, "-c", "while 1: pass"])
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        time.sleep(0.5)
        assert runnable(busy.pid)
        time.sleep(0.2)
        assert not runnable(sleeper.pid)
        busy.send_signal(signal.SIGSTOP)
        time.sleep(0.2)
        assert not runnable(busy.pid)
    finally:
        for p in (busy, sleeper):
            p.kill()
            p.wait(timeout=10)
