"""Keep the computer awake while it flies (a laptop that sleeps leaves its drones alone).

No process on the laptop can land a drone while the laptop sleeps, so `flightstack fly` and a hardware
`flightstack agent` ask the operating system not to sleep for as long as they fly:

- Linux: `systemd-inhibit --what=sleep:idle:handle-lid-switch --mode=block ... cat` (systemd-logind); the
  inhibitor holds while `cat` reads our pipe, so it also ends when this process dies;
- macOS: `caffeinate -i -s -w PID` (ends with this process).

Where neither exists or the request is refused (a container without logind, Windows), the run goes on and
says so: the Tello's own 15 s auto-land stays the last backstop (docs/safety.md).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator

LOG = logging.getLogger("flightstack.keep_awake")
START_CHECK_S = 0.3
"""How long (s) the helper must survive to count as holding the inhibitor."""


def inhibit_command(why: str) -> list[str] | None:
    """The command that keeps this computer awake while it runs, or None when there is none."""
    if sys.platform == "darwin" and shutil.which("caffeinate"):
        return ["caffeinate", "-i", "-s", "-w", str(os.getpid())]
    if shutil.which("systemd-inhibit"):
        return [
            "systemd-inhibit",
            "--what=sleep:idle:handle-lid-switch",
            "--who=flightstack",
            f"--why={why}",
            "--mode=block",
            "cat",
        ]
    return None


@contextlib.contextmanager
def keep_awake(why: str = "drones in flight") -> Iterator[str]:
    """Inside the block the OS is asked not to sleep; yields a sentence saying whether it worked."""
    cmd = inhibit_command(why)
    if cmd is None:
        yield "sleep not inhibited: no systemd-inhibit or caffeinate on this computer"
        return
    try:
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
    except OSError as exc:
        yield f"sleep not inhibited: {cmd[0]} did not start ({exc})"
        return
    t_end = time.monotonic() + START_CHECK_S
    while time.monotonic() < t_end and proc.poll() is None:
        time.sleep(0.02)
    if proc.poll() is not None:
        err = (proc.stderr.read() if proc.stderr else b"").decode(errors="replace").strip()
        yield f"sleep not inhibited: {cmd[0]} refused ({err or f'exit {proc.returncode}'})"
        return
    try:
        yield f"sleep inhibited ({cmd[0]}, pid {proc.pid})"
    finally:
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()
        proc.terminate()
        try:
            proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=2.0)
