"""A guardian process for every process that commands hardware (`fly`, `agent`, `target`).

A process that dies or stops ticking cannot land its drones (a Tello keeps its last `rc` for up to 15 s);
the guardian, a second small OS process, does. What it covers and what it cannot, measured:
docs/safety.md ("The guardian").

- **Launch** (`Guardian.start`, before takeoff): own session (`start_new_session=True`), and a process name
  and command line that match none of an operator's patterns for the flight or for Python
  (`name_patterns`: "python", "python3", "flightstack", the environment's path), from the exec on
  (`guardian_argv`: `<tmp>/tello-guardian-XXXX/bin/tello-guardian -c BOOTSTRAP`, the module from the
  environment, `GUARDIAN_ENTRY`), so neither the terminal's signals nor `pkill [-f]` by those names reach
  it. The parent writes one JSON line of `GuardianConfig` on its stdin and waits ≤ `ready_timeout_s` for
  its `ready` line. Once the guardian is forked, the parent makes itself the out-of-memory killer's first
  choice (`OOM_SCORE_ADJ_FLIGHT`); the guardian lowers its own as far as it may
  (`OOM_SCORE_ADJ_GUARDIAN`) and raises its CPU priority where permitted (`GUARDIAN_NICE`).
- **Both directions beat.** `heartbeat()` writes one byte per control tick (non-blocking, never raises;
  failures counted); `arm()` starts the stall detection, `arm(False)` pauses it around a known blocking
  phase; `finish()` writes "bye". The guardian beats back every `GUARDIAN_BEAT_S`; `Guardian.lost()` says
  why it is gone (exited, pipe closed, silent for `GUARDIAN_SILENT_S`) and the flight then lands.
- **Takeover** (final): on EOF or a changed parent pid always (armed or not); on no heartbeat for
  `stall_s` only while armed; never after "bye". SIGTERM also makes it take over, then exit.
- **What it does** (drivers/guardian/process.py): sets the takeover flag (a 1-byte file mmap'd by both
  processes; the parent's drivers read it before every send, `set_muted(guardian.taken_over)`), then from
  its own socket sends `rc 0 0 0 0` + `land` to every Tello every `land_resend_s` until its telemetry shows
  it down or `give_up_s`. A Tello reached through a named interface gets them from a socket bound to that
  interface, and its telemetry is read from a state socket bound to it (drivers/netif.py): its own
  adapter, never another drone's at the same address. No `command`: a Tello in SDK mode executes
  commands from any source port (DJITelloPy PR #163). The robot gets a GCS heartbeat, a zero set-point,
  a forced disarm (MAV_CMD_COMPONENT_ARM_DISARM, param2 21196) and HOLD until a HEARTBEAT shows it
  disarmed.

Units: times in seconds (time.monotonic()), heights in cm, ports UDP.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import mmap
import os
import re
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
GUARDIAN_BEAT_S = 0.1
"""The guardian writes one byte on its stdout this often (s): its heartbeat to the parent."""
GUARDIAN_SILENT_S = 1.0
"""The parent counts its guardian as lost after this long without a byte from it (s): 10 beats, so that
a guardian descheduled on a loaded computer is not mistaken for a dead one (a dead one closes the pipe,
which is seen at once)."""
GUARDIAN_READY_S = 30.0
"""How long (s) the flight waits for a new guardian's `ready` before it refuses to fly. Nothing has taken
off yet, so waiting costs only time; 10 s was too short beside a CPU-bound process on a 2-core machine
(load 8: the guardian's interpreter and imports did not finish)."""
ENTRY_ENV = "GUARDIAN_ENTRY"
"""The environment variable naming the module the guardian runs (`main()`), read by BOOTSTRAP."""
ENTRY_MODULE = "flightstack.drivers.guardian.process"
BOOTSTRAP = "import os,sys,importlib;sys.exit(importlib.import_module(os.environ['GUARDIAN_ENTRY']).main())"
"""The guardian's `-c` code: names no module itself, so that its command line matches no NAME_WORDS."""
GUARDIAN_NAME = "tello-guardian"
"""The guardian's process name (/proc/PID/comm, ≤ 15 characters) and the name of its interpreter link."""
NAME_WORDS = ("flightstack", "python")
"""What an operator's `pkill [-f]` matches for the flight or for Python ("python3" contains "python"):
never in the guardian's process name or command line (`name_patterns` adds the environment's path)."""


OOM_SCORE_ADJ_FLIGHT = 1000
"""The flight's /proc/self/oom_score_adj once its guardian runs: the out-of-memory killer's first choice
(raising it needs no privilege), so that it takes the flight, which its guardian then lands."""
OOM_SCORE_ADJ_GUARDIAN = (-1000, 0)
"""What the guardian asks for itself, in order: never the OOM killer's choice (needs CAP_SYS_RESOURCE),
else the neutral 0 (allowed without privilege down to the value the session started with, usually 0),
so that a flight started with 1000 already does not hand its guardian that."""
GUARDIAN_NICE = -10
"""The guardian's nice and its session's autogroup nice, where permitted (root or CAP_SYS_NICE): the safety
net runs before the work it guards, so that a loaded computer does not silence its beat past
GUARDIAN_SILENT_S (which lands the flight). Without the privilege both stay as they were (0)."""


def set_oom_score_adj(value: int, path: str = "/proc/self/oom_score_adj") -> int | None:
    """Write `value` to this process's oom_score_adj; the value read back, None where it cannot be set
    (not Linux, or lowering it without the privilege). Never raises."""
    try:
        with open(path, "w", encoding="ascii") as f:
            f.write(f"{int(value)}\n")
    except OSError:
        pass
    try:
        with open(path, encoding="ascii") as f:
            got = int(f.read().strip())
    except (OSError, ValueError):
        return None
    return got if got == int(value) else None


class GuardianError(RuntimeError):
    """The guardian could not be started (it did not report ready in time, or rejected its config)."""


class TelloLike(Protocol):
    """What the guardian needs of a flightstack.drivers.tello.config.TelloConfig (read-only)."""

    @property
    def host(self) -> str: ...
    @property
    def control_port(self) -> int: ...
    @property
    def state_port(self) -> int: ...
    @property
    def bind_ip(self) -> str: ...
    @property
    def interface(self) -> str | None: ...


@dataclass(frozen=True)
class GuardedTello:
    """One Tello: IP, command port (8889 on a real drone), local state port (8890), local bind IP and the
    network interface it is reached through (None: any; drivers/netif.py)."""

    host: str
    control_port: int = 8889
    state_port: int = 8890
    bind_ip: str = ""
    interface: str | None = None

    @property
    def name(self) -> str:
        """How the log names it: its address, and the interface when one is named (two access-point
        Tellos share 192.168.10.1)."""
        return self.host if self.interface is None else f"{self.host} via {self.interface}"

    @classmethod
    def of(cls, cfg: TelloLike) -> GuardedTello:
        """From a TelloConfig (or anything with host, control_port, state_port, bind_ip, interface)."""
        return cls(cfg.host, int(cfg.control_port), int(cfg.state_port), cfg.bind_ip, cfg.interface)


@dataclass(frozen=True)
class GuardianConfig:
    """What the guardian watches and how (times in s, heights in cm); sent to it as one JSON line.

    robot_url: pymavlink connection string of the robot (None: no robot); robot_target: its (system,
    component), learned from its HEARTBEAT when one arrives; robot_source: the guardian's own MAVLink ids.
    flag_path: the takeover flag file ("" = a new temporary file, made by Guardian.start); parent_pid: 0 =
    the pid of the process calling Guardian.start; launch_dir: set by Guardian.start (guardian_argv).
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
    launch_dir: str = ""  # the neutral directory of the guardian's interpreter link; removed at its exit
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


def _neutral_dirs() -> list[str]:
    """Where a neutral launch directory may go, in order of preference."""
    home = os.path.expanduser("~")
    return [d for d in (tempfile.gettempdir(), "/tmp", "/dev/shm", "/var/tmp", home) if os.path.isdir(d)]


def name_patterns(prefix: str = sys.prefix) -> list[str]:
    """What the guardian's name and command line must never match: NAME_WORDS and the environment's
    path (`prefix` as given and resolved), the patterns an operator gives `pkill [-f]` for the flight."""
    out = list(NAME_WORDS)
    for p in (prefix, os.path.realpath(prefix)):
        if p and p not in out:
            out.append(p)
    return out


def matching(text: str, patterns: list[str]) -> list[str]:
    """The patterns that select `text` as pgrep/pkill would (an extended regex searched anywhere, here also
    ignoring case), or that `text` contains literally (a path is also tried as plain text)."""
    hits = []
    for p in patterns:
        try:
            found = re.search(p, text, re.IGNORECASE) is not None
        except re.error:
            found = False
        if found or p.lower() in text.lower():
            hits.append(p)
    return hits


def _venv_config(executable: str, prefix: str) -> str:
    """The pyvenv.cfg of the neutral environment: the running environment's own (a virtual environment:
    same base interpreter, same system-site-packages choice), else one over the interpreter's installation
    with its site-packages (run outside a virtual environment)."""
    try:
        with open(os.path.join(prefix, "pyvenv.cfg"), encoding="utf-8") as f:
            return f.read()
    except OSError:
        home = os.path.dirname(os.path.realpath(executable))
        return f"home = {home}\ninclude-system-site-packages = true\n"


def _make_environment(launch: str, executable: str, prefix: str) -> None:
    """In `launch`: bin/GUARDIAN_NAME → the real interpreter, pyvenv.cfg, and lib (and sys.platlibdir) →
    the running environment's, so that the interpreter started through the link finds the same standard
    library and site-packages (.pth files and editable installs included) as this process."""
    os.mkdir(os.path.join(launch, "bin"))
    os.symlink(os.path.realpath(executable), os.path.join(launch, "bin", GUARDIAN_NAME))
    with open(os.path.join(launch, "pyvenv.cfg"), "w", encoding="utf-8") as f:
        f.write(_venv_config(executable, prefix))
    if os.path.isfile(os.path.join(prefix, "pyvenv.cfg")):  # a venv: its own site-packages
        for lib in sorted({"lib", sys.platlibdir}):
            if os.path.isdir(os.path.join(prefix, lib)):
                os.symlink(os.path.join(prefix, lib), os.path.join(launch, lib), target_is_directory=True)


def guardian_argv(
    executable: str = sys.executable, prefix: str = sys.prefix, roots: list[str] | None = None
) -> tuple[list[str], str]:
    """The guardian's command line and the directory made for it: (argv, launch_dir).

    argv is `<root>/tello-guardian-XXXX/bin/tello-guardian -c BOOTSTRAP`: a link to the real interpreter
    with a neutral name (the kernel takes the process name, /proc/PID/comm, from the path given to execve,
    not from what the link points to) inside a small virtual environment (`_make_environment`) that keeps
    this process's standard library and site-packages. Neither matches `name_patterns(prefix)` from the
    exec on, before any device is commanded. GuardianError when no root gives such a command line."""
    patterns = name_patterns(prefix)
    tried = []
    for root in _neutral_dirs() if roots is None else roots:
        argv = [os.path.join(root, f"{GUARDIAN_NAME}-XXXXXXXX", "bin", GUARDIAN_NAME), "-c", BOOTSTRAP]
        if matching(" ".join(argv), patterns):
            tried.append(root)
            continue
        try:
            launch = tempfile.mkdtemp(prefix=f"{GUARDIAN_NAME}-", dir=root)
        except OSError:
            tried.append(root)
            continue
        argv[0] = os.path.join(launch, "bin", GUARDIAN_NAME)
        try:
            if matching(" ".join(argv), patterns):
                raise OSError("the random part matched")
            _make_environment(launch, executable, prefix)
        except OSError:
            remove_launch_dir(launch)
            tried.append(root)
            continue
        return argv, launch
    raise GuardianError(
        f"no neutral command line for the guardian: every temporary directory ({', '.join(tried) or 'none'}) "
        f"has a path matching one of {patterns} (set TMPDIR to a neutral directory)"
    )


def remove_launch_dir(path: str) -> None:
    """Remove a directory made by guardian_argv (its links only, never what they point to)."""
    if not path or not os.path.basename(path).startswith(f"{GUARDIAN_NAME}-"):
        return
    for entry in (os.path.join("bin", GUARDIAN_NAME), "pyvenv.cfg", "lib", sys.platlibdir):
        with contextlib.suppress(OSError):
            os.unlink(os.path.join(path, entry))
    for d in ("bin", ""):
        with contextlib.suppress(OSError):
            os.rmdir(os.path.join(path, d))


class Guardian:
    """The parent's handle on its guardian process (see the module docstring)."""

    def __init__(self, proc: subprocess.Popen[bytes], flag: TakeoverFlag, cfg: GuardianConfig) -> None:
        self.proc = proc
        self.flag = flag
        self.cfg = cfg
        self.counts: Counter[str] = Counter()  # "beats", "pipe_full", "pipe_broken"
        self._lock = threading.Lock()
        self._fd = proc.stdin.fileno() if proc.stdin is not None else -1
        self._beat_fd = -1  # the guardian's stdout after `ready`: its heartbeat
        self._last_guardian_beat = time.monotonic()
        self._lost: str | None = None
        self._own_flag = False
        self.oom_score_adj: int | None = None
        """The parent's oom_score_adj as set by `start` (OOM_SCORE_ADJ_FLIGHT), None if it could not be."""

    @property
    def pid(self) -> int:
        return self.proc.pid

    @classmethod
    def start(cls, cfg: GuardianConfig, ready_timeout_s: float = GUARDIAN_READY_S) -> Guardian:
        """Launch the guardian, send it `cfg`, wait ≤ ready_timeout_s for its `ready`; GuardianError else."""
        own = not cfg.flag_path
        if own:
            fd, path = tempfile.mkstemp(prefix="flightstack-guardian-", suffix=".flag")
            os.close(fd)
            cfg = dataclasses.replace(cfg, flag_path=path)
        flag = TakeoverFlag.create(cfg.flag_path)
        try:
            argv, launch = guardian_argv()
        except GuardianError:
            if own:
                with contextlib.suppress(OSError):
                    os.unlink(cfg.flag_path)
            raise
        cfg = dataclasses.replace(cfg, parent_pid=cfg.parent_pid or os.getpid(), launch_dir=launch)
        env = dict(os.environ)  # the child imports the installed flightstack package
        env[ENTRY_ENV] = ENTRY_MODULE
        proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
            env=env,
        )
        g = cls(proc, flag, cfg)
        g._own_flag = own
        g.oom_score_adj = set_oom_score_adj(OOM_SCORE_ADJ_FLIGHT)  # forked: the guardian kept its own
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
        if not line.startswith(READY):
            self.proc.stdout.close()
            return line.decode(errors="replace")
        os.set_blocking(out, False)
        self._beat_fd, self._last_guardian_beat = out, time.monotonic()
        return ""

    def _abort(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=2.0)
        self._close_pipe()
        remove_launch_dir(self.cfg.launch_dir)
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

    def lost(self) -> str | None:
        """Why this process's guardian can no longer cover it (it exited, its heartbeat pipe closed, or it
        was silent for GUARDIAN_SILENT_S), else None. Non-blocking, never raises; once lost, always lost.
        Call it every control tick: the flight must land when it is not None."""
        if self._lost is not None:
            return self._lost
        now = time.monotonic()
        fd = self._beat_fd
        if fd >= 0:
            try:
                while data := os.read(fd, 4096):
                    self._last_guardian_beat = now
                    if len(data) < 4096:
                        break
                else:
                    self._lost = f"the guardian (pid {self.pid}) closed its heartbeat pipe"
            except BlockingIOError:
                pass
            except (OSError, ValueError) as exc:
                self._lost = f"the guardian's heartbeat pipe failed: {exc}"
        code = self.proc.poll()
        if code is not None:
            self._lost = f"the guardian (pid {self.pid}) exited with {code}"
            remove_launch_dir(self.cfg.launch_dir)  # a killed guardian could not remove it itself
        elif self._lost is None and now - self._last_guardian_beat > GUARDIAN_SILENT_S:
            silent = now - self._last_guardian_beat
            self._lost = f"the guardian (pid {self.pid}) is silent for {silent:.2f} s"
        return self._lost

    def finish(self, timeout_s: float = 2.0) -> int | None:
        """Drones landed normally: "bye", close the pipe, wait ≤ timeout_s; the guardian's exit code (None
        while it still runs, e.g. finishing a takeover: it is then left to complete it)."""
        self._write(BYE)
        self._close_pipe()
        try:
            code: int | None = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            code = None
        if code is not None:
            remove_launch_dir(self.cfg.launch_dir)  # the guardian removes it too; whoever is last
            if self._own_flag:
                with contextlib.suppress(OSError):
                    os.unlink(self.flag.path)  # both mappings stay valid
        return code

    def _close_pipe(self) -> None:
        with self._lock:
            fd, self._fd = self._fd, -1
            beat_fd, self._beat_fd = self._beat_fd, -1
        if fd >= 0 and self.proc.stdin is not None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
        if beat_fd >= 0 and self.proc.stdout is not None:
            with contextlib.suppress(OSError):
                self.proc.stdout.close()
