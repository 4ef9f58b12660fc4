"""A guardian process for every process that commands hardware (`fly`, `agent`, `target`; issue 15).

When the process flying the drones dies (SIGKILL, out-of-memory kill, a crash in native code) or stops
ticking (SIGSTOP, Ctrl-Z on a process that ignores it, a hang), nothing in it can land them: a Tello keeps
its last `rc` for up to 15 s (its own auto-land). The guardian is a second, small OS process that does it.

Design (decided):
- **Launch**: `Guardian.start(cfg)` runs `python -m flightstack.drivers.guardian` with
`start_new_session=True`, so that
  Ctrl-C / SIGHUP / SIGTSTP sent to the terminal's process group never reach it, BEFORE takeoff. The parent
  writes one JSON line of `GuardianConfig` on the guardian's stdin and waits (≤ `ready_timeout_s`) for its
  `ready` line on stdout (the guardian has then mapped the flag and opened its own sockets).
- **Heartbeat**: one byte per control tick on the same pipe (`heartbeat()`: non-blocking, never raises;
  a full or broken pipe is counted in `counts`). `arm()` arms the stall detection (call it when the control
  loop starts ticking, before the first takeoff); `arm(False)` disarms it around a known blocking phase.
  `finish()` writes "bye" (the drones landed normally) and waits briefly for the guardian to exit.
- **Takeover** (final): on EOF of the pipe or a change of the guardian's parent pid (the parent is gone:
  SIGKILL, OOM, crash; the pid check also covers a forked child that inherited the pipe), ALWAYS, armed or
  not (the robot is armed during connect; an `rc`/`land` to a Tello on the ground is ignored by it); on
  no heartbeat for `stall_s` (0.5 s) ONLY while armed (connect and preflight may block for seconds).
  EOF after "bye" is no takeover.
- **What it does** (drivers/guardian_process.py): first it sets the takeover flag, then, from its OWN UDP
  socket, sends `rc 0 0 0 0` and `land` to every Tello, re-sent every `land_resend_s` (1 s) until that
  drone's telemetry shows it down (h ≤ 20 cm with its motor-on time frozen for `motor_quiet_s`, as
  drivers/tello_phase), or until `give_up_s` (20 s, beyond the Tello's 15 s auto-land). It does not send
  `command`: the drone is in SDK mode already and executes commands from any source port (DJITelloPy
  PR #163: EDU drones answer only the first client's port, yet execute a second client's commands;
  sim_backend/emulators/tello.py `reply_port_latch`); no reply is awaited. Telemetry: it binds each Tello
  state
  port (SO_REUSEADDR) as soon as it is free; a stopped parent still holds it, a dead one does not. The
  robot: from its own pymavlink connection (`robot_url`, by default the parent's), a GCS heartbeat, a zero
  velocity set-point, a forced disarm (MAV_CMD_COMPONENT_ARM_DISARM, param2 21196) and HOLD mode, every
  `robot_resend_s` until a robot HEARTBEAT shows it disarmed, at most `robot_sends` times. Every action is
  logged with time.monotonic() stamps to stderr and `log_path`. It exits when its drones are down and the
  robot stopped, after `give_up_s`, or at once after "bye".
- **Takeover flag**: a 1-byte file mapped (mmap, MAP_SHARED) by both processes. The guardian sets it
  before its first datagram; `TakeoverFlag.is_set()` / `Guardian.taken_over()` is one memory read, which
  the parent's drivers call right before every send (`TelloDriver.set_muted(guardian.taken_over)`,
  `ScamperDriver.set_muted(...)`). A parent resumed after a takeover (SIGCONT) therefore sends nothing more,
  except, at most, one datagram per thread that had passed the check when it was stopped (superseded by
  the guardian's next `rc 0 0 0 0` + `land`).

Not covered by any process on the laptop: sleep, power or Wi-Fi loss of the laptop itself; the Tello's own
15 s auto-land (no datagram for 15 s) is the last backstop. For a robot reached through `udpin:` or a
serial device the stopped parent holds, give the guardian its own endpoint (`robot_url`, e.g. a second
mavlink-router UDP endpoint: a router's UDP server endpoint answers one client only).

Units: times in seconds (time.monotonic()), heights in cm, ports UDP.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import mmap
import os
import select
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Protocol

BEAT, ARM, UNARM, BYE = b".", b"A", b"a", b"B"  # parent -> guardian pipe bytes
READY = b"ready"
EXIT_BYE, EXIT_CONFIG, EXIT_DONE, EXIT_GAVE_UP = 0, 2, 10, 11  # guardian exit codes


class GuardianError(RuntimeError):
    """The guardian could not be started (it did not report ready in time, or rejected its config)."""


class TelloLike(Protocol):
    """What the guardian needs of a flightstack.drivers.tello_config.TelloConfig (read-only)."""

    @property
    def host(self) -> str: ...
    @property
    def control_port(self) -> int: ...
    @property
    def state_port(self) -> int: ...
    @property
    def bind_ip(self) -> str: ...


@dataclass(frozen=True)
class GuardedTello:
    """One Tello: IP, command port (8889 on a real drone), local state port (8890) and local bind IP."""

    host: str
    control_port: int = 8889
    state_port: int = 8890
    bind_ip: str = ""

    @classmethod
    def of(cls, cfg: TelloLike) -> GuardedTello:
        """From a TelloConfig (or anything with host, control_port, state_port, bind_ip)."""
        return cls(cfg.host, int(cfg.control_port), int(cfg.state_port), cfg.bind_ip)


@dataclass(frozen=True)
class GuardianConfig:
    """What the guardian watches and how (times in s, heights in cm); sent to it as one JSON line.

    robot_url: pymavlink connection string of the robot (None: no robot); robot_target: its (system,
    component), learned from its HEARTBEAT when one arrives; robot_source: the guardian's own MAVLink ids.
    flag_path: the takeover flag file ("" = a new temporary file, made by Guardian.start); parent_pid: 0 =
    the pid of the process calling Guardian.start.
    """

    tellos: tuple[GuardedTello, ...] = ()
    robot_url: str | None = None
    robot_target: tuple[int, int] = (1, 1)
    robot_source: tuple[int, int] = (255, 25)  # GCS system id, MAV_COMP_ID_USER1
    stall_s: float = 0.5
    land_resend_s: float = 1.0
    give_up_s: float = 20.0
    robot_resend_s: float = 0.5
    robot_sends: int = 6
    ground_h_cm: float = 20.0
    motor_quiet_s: float = 1.5
    flag_path: str = ""
    log_path: str | None = None
    parent_pid: int = 0
    extra: dict[str, Any] = field(default_factory=dict)  # free-form, logged (e.g. mission name)

    def __post_init__(self) -> None:
        for name in ("stall_s", "land_resend_s", "give_up_s", "robot_resend_s", "motor_quiet_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"GuardianConfig.{name} must be > 0")
        if self.robot_sends < 1:
            raise ValueError("GuardianConfig.robot_sends must be >= 1")

    @classmethod
    def for_devices(
        cls, tellos: list[TelloLike] | tuple[TelloLike, ...], robot_url: str | None = None, **kw: Any
    ) -> GuardianConfig:
        """The config for these Tellos (TelloConfig) and robot (ScamperConfig.url or None)."""
        return cls(tellos=tuple(GuardedTello.of(t) for t in tellos), robot_url=robot_url, **kw)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, text: str) -> GuardianConfig:
        d = json.loads(text)
        d["tellos"] = tuple(GuardedTello(**t) for t in d.get("tellos", ()))
        for key in ("robot_target", "robot_source"):
            if key in d:
                d[key] = tuple(d[key])
        return cls(**d)


class TakeoverFlag:
    """A 1-byte file mapped shared by the parent and the guardian; non-zero = taken over (final)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        """Map an existing flag file (see `create`)."""
        self.path = str(path)
        with open(self.path, "r+b") as f:
            self._mm = mmap.mmap(f.fileno(), 1, access=mmap.ACCESS_WRITE)

    @classmethod
    def create(cls, path: str | os.PathLike[str]) -> TakeoverFlag:
        """Write a cleared flag file at `path` (replacing any) and map it."""
        with open(path, "wb") as f:
            f.write(b"\0")
        return cls(path)

    def is_set(self) -> bool:
        """One read of the shared byte (safe from any thread; False once the mapping is closed)."""
        try:
            return self._mm[0] != 0
        except ValueError:  # closed
            return False

    def set(self) -> None:
        self._mm[0] = 1

    def close(self) -> None:
        with contextlib.suppress(BufferError, ValueError):
            self._mm.close()


class Guardian:
    """The parent's handle on its guardian process (see the module docstring)."""

    def __init__(self, proc: subprocess.Popen[bytes], flag: TakeoverFlag, cfg: GuardianConfig) -> None:
        self.proc = proc
        self.flag = flag
        self.cfg = cfg
        self.counts: Counter[str] = Counter()  # "beats", "pipe_full", "pipe_broken"
        self._lock = threading.Lock()
        self._fd = proc.stdin.fileno() if proc.stdin is not None else -1
        self._own_flag = False

    @property
    def pid(self) -> int:
        return self.proc.pid

    @classmethod
    def start(cls, cfg: GuardianConfig, ready_timeout_s: float = 10.0) -> Guardian:
        """Launch the guardian, send it `cfg`, wait ≤ ready_timeout_s for its `ready`; GuardianError else."""
        own = not cfg.flag_path
        if own:
            fd, path = tempfile.mkstemp(prefix="flightstack-guardian-", suffix=".flag")
            os.close(fd)
            cfg = dataclasses.replace(cfg, flag_path=path)
        flag = TakeoverFlag.create(cfg.flag_path)
        cfg = dataclasses.replace(cfg, parent_pid=cfg.parent_pid or os.getpid())
        env = dict(os.environ)  # the child imports the installed flightstack package
        proc = subprocess.Popen(
            [sys.executable, "-m", "flightstack.drivers.guardian"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
            env=env,
        )
        g = cls(proc, flag, cfg)
        g._own_flag = own
        try:
            os.write(g._fd, cfg.to_json().encode() + b"\n")  # blocking: far below the pipe's capacity
            os.set_blocking(g._fd, False)
            answer = g._read_ready(ready_timeout_s)
        except OSError as exc:
            answer = f"pipe error: {exc}"
        if answer != "":
            g._abort()
            raise GuardianError(f"guardian (pid {proc.pid}) did not start: {answer}")
        return g

    def _read_ready(self, timeout_s: float) -> str:
        """'' once the guardian wrote `ready`; else why not."""
        assert self.proc.stdout is not None
        out = self.proc.stdout.fileno()
        buf, deadline = b"", time.monotonic() + timeout_s
        while b"\n" not in buf:
            left = deadline - time.monotonic()
            if left <= 0.0:
                return f"no 'ready' within {timeout_s:g} s"
            if select.select([out], [], [], min(left, 0.1))[0]:
                chunk = os.read(out, 4096)
                if not chunk:
                    return f"exited with {self.proc.poll()} ({buf.decode(errors='replace').strip()!r})"
                buf += chunk
        line = buf.split(b"\n", 1)[0]
        self.proc.stdout.close()
        return "" if line.startswith(READY) else line.decode(errors="replace")

    def _abort(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=2.0)
        self._close_pipe()
        if self._own_flag:
            with contextlib.suppress(OSError):
                os.unlink(self.flag.path)

    def _write(self, data: bytes) -> bool:
        """Write to the pipe without blocking; never raises (a full or broken pipe is counted)."""
        with self._lock:
            if self._fd < 0:
                self.counts["pipe_broken"] += 1
                return False
            try:
                os.write(self._fd, data)
            except BlockingIOError:
                self.counts["pipe_full"] += 1
                return False
            except (OSError, ValueError):
                self.counts["pipe_broken"] += 1
                return False
        return True

    def heartbeat(self) -> None:
        """One control tick (call it every tick of the control loop, never from another thread)."""
        if self._write(BEAT):
            self.counts["beats"] += 1

    def arm(self, on: bool = True) -> None:
        """Arm (on=True) or disarm the stall detection; parent death is always a takeover."""
        self._write(ARM if on else UNARM)

    def taken_over(self) -> bool:
        """True once the guardian took over (final): the drivers' `muted` check; one memory read."""
        return self.flag.is_set()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def finish(self, timeout_s: float = 2.0) -> int | None:
        """Drones landed normally: "bye", close the pipe, wait ≤ timeout_s; the guardian's exit code (None
        while it still runs, e.g. finishing a takeover: it is then left to complete it)."""
        self._write(BYE)
        self._close_pipe()
        try:
            code: int | None = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            code = None
        if self._own_flag and code is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.flag.path)  # both mappings stay valid
        return code

    def _close_pipe(self) -> None:
        with self._lock:
            fd, self._fd = self._fd, -1
        if fd >= 0 and self.proc.stdin is not None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()


if __name__ == "__main__":
    from flightstack.drivers.guardian_process import main

    sys.exit(main())
