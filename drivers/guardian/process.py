"""The guardian process itself (`python -m flightstack.drivers.guardian.process`); the design is in
drivers/guardian/launcher.py.

One thread runs everything (plus a log writer, so that a blocked stderr never delays a takeover): a
select() loop of ≤ 20 ms over the parent's pipe (stdin), the guardian's own Tello command sockets and the
Tello state ports it could bind; every GUARDIAN_BEAT_S it writes one byte on stdout (its heartbeat to the
parent). SIGTERM is the one way to stop it on purpose: it takes over (lands what it guards) and exits
when that is done. Every socket is non-blocking; every error is logged and counted, never fatal.
Times: time.monotonic() seconds; heights cm.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import queue
import select
import selectors
import signal
import site
import socket
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, TextIO

from flightstack.drivers.guardian.launcher import (
    ARM,
    BEAT,
    BYE,
    EXIT_BYE,
    EXIT_CONFIG,
    EXIT_DONE,
    EXIT_GAVE_UP,
    GUARDIAN_BEAT_S,
    GUARDIAN_NICE,
    OOM_SCORE_ADJ_GUARDIAN,
    READY,
    UNARM,
    GuardedTello,
    GuardianConfig,
    TakeoverFlag,
    remove_launch_dir,
    set_oom_score_adj,
)
from flightstack.drivers.netif import udp_socket
from flightstack.drivers.tello.phase import PhaseThresholds, PhaseTracker
from flightstack.drivers.tello.state import StateRejectedError, parse_state
from flightstack.scheduling import set_group_nice, set_nice

TICK_S = 0.02  # longest select() wait (s)
Local = tuple[str, str]
"""A command socket's (interface or "", local address): one per pair, shared by its drones."""
StatePort = tuple[str, str, int]
"""A state socket's (interface or "", local address, port)."""
BIND_RETRY_S = 0.2  # retry binding a held state port this often (s)
ROVER_HOLD_MODE = 4
FORCE_DISARM = 21196.0  # MAV_CMD_COMPONENT_ARM_DISARM param2: disarm regardless of checks


class Log:
    """Lines `<level>: <name> <pid> t=<monotonic s> <text>` to `stream` (None: stderr) and an optional file,
    from a writer thread (`flightstack guard` uses it with name "guard" and stdout). The level is the
    console's (`info`, `warning`, `error`: docs/logs.md, "What a run prints"): `warning` when the process
    acts on the drones or something failed that it works around, `error` when it gives up."""

    def __init__(self, path: str | None, name: str = "guardian", stream: TextIO | None = None) -> None:
        self._q: queue.Queue[str | None] = queue.Queue()
        self._file = None
        self._name = name
        self._stream = stream
        if path:
            try:
                self._file = open(path, "a", encoding="utf-8")  # noqa: SIM115 - closed by close()
            except OSError as exc:
                self(f"log file {path!r} not writable: {exc}")
        self._thread = threading.Thread(target=self._run, name="guardian-log", daemon=True)
        self._thread.start()

    def __call__(self, text: str, level: str = "info") -> None:
        self._q.put(f"{level}: {self._name} {os.getpid()} t={time.monotonic():.3f} {text}\n")

    def _run(self) -> None:
        while (line := self._q.get()) is not None:
            for out in (self._stream or sys.stderr, self._file):
                if out is None:
                    continue
                try:
                    out.write(line)
                    out.flush()
                except (OSError, ValueError):
                    pass  # a closed terminal must not stop the guardian

    def close(self, timeout_s: float = 1.0) -> None:
        self._q.put(None)
        self._thread.join(timeout_s)
        if self._file is not None:
            self._file.close()


@dataclass
class Drone:
    """One guarded Tello during a takeover."""

    spec: GuardedTello
    tracker: PhaseTracker
    last_send_t: float = -math.inf
    sends: int = 0
    down_t: float | None = None
    low_since: float | None = (
        None  # fresh telemetry has shown it near the ground since then (PhaseTracker.low)
    )

    def is_down(self, now: float) -> bool:
        """On the ground: the motor-on time frozen over motor_quiet_s of fresh telemetry (PhaseTracker.down:
        whatever tof and h read, a drone on a raised surface too)."""
        s = self.tracker.latest
        return s is not None and now - s.t <= 0.5 and self.tracker.down(now)


@dataclass
class Robot:
    """Stops and disarms the robot over MAVLink from the guardian's own connection."""

    cfg: GuardianConfig
    log: Log
    conn: Any = None
    target: tuple[int, int] = (1, 1)
    sends: int = 0
    last_send_t: float = -math.inf
    first_send_t: float | None = None
    done: bool = False
    mavlink: Any = None  # pymavlink's mavutil.mavlink
    is_vehicle_heartbeat: Any = None  # drivers.scamper.link.is_vehicle_heartbeat

    def __post_init__(self) -> None:
        from pymavlink import mavutil  # imported now (~0.3 s), not during a takeover

        from flightstack.drivers.scamper.link import is_vehicle_heartbeat

        self.mavlink = mavutil.mavlink
        self.is_vehicle_heartbeat = is_vehicle_heartbeat

    def step(self, now: float) -> None:
        if self.done:
            return
        self._receive(now)
        if self.done or now - self.last_send_t < self.cfg.robot_resend_s:
            return
        if self.sends >= self.cfg.robot_sends:
            self.done = True
            self.log(f"robot: no HEARTBEAT showed it disarmed after {self.sends} sends: giving up", "error")
            return
        self.last_send_t = now
        if self.conn is None and not self._open():
            self.sends += 1  # a connection that cannot open counts as a try
            return
        m = self.mavlink
        sysid, comp = self.target
        n = self.sends
        try:
            self.conn.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)
            self.conn.mav.set_position_target_local_ned_send(
                0, sysid, comp, m.MAV_FRAME_BODY_NED, 1511, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
            )
            self.conn.mav.command_long_send(
                sysid, comp, m.MAV_CMD_COMPONENT_ARM_DISARM, n, 0, FORCE_DISARM, 0, 0, 0, 0, 0
            )
            self.conn.mav.command_long_send(
                sysid, comp, m.MAV_CMD_DO_SET_MODE, n, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ROVER_HOLD_MODE,
                0, 0, 0, 0, 0,
            )  # fmt: skip
        except Exception as exc:
            self.log(f"robot: send failed: {type(exc).__name__}: {exc}", "warning")
        self.sends += 1
        self.first_send_t = self.first_send_t if self.first_send_t is not None else now
        self.log(
            f"robot: zero velocity, forced disarm, HOLD sent to {sysid}/{comp} (send {self.sends})", "warning"
        )

    def _open(self) -> bool:
        try:
            from pymavlink import mavutil

            sysid, comp = self.cfg.robot_source
            self.conn = mavutil.mavlink_connection(
                self.cfg.robot_url, source_system=sysid, source_component=comp
            )
            self.log(f"robot: connection {self.cfg.robot_url!r} open")
            return True
        except Exception as exc:
            self.log(f"robot: cannot open {self.cfg.robot_url!r}: {type(exc).__name__}: {exc}", "error")
            self.conn = None
            return False

    def _receive(self, now: float) -> None:
        if self.conn is None:
            return
        for _ in range(100):
            try:
                msg = self.conn.recv_match(type="HEARTBEAT", blocking=False)
            except Exception as exc:
                self.log(f"robot: receive error {type(exc).__name__}: {exc}", "warning")
                return
            if msg is None:
                return
            if not self.is_vehicle_heartbeat(msg):
                continue
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if src != self.target:
                self.log(f"robot: HEARTBEAT from {src[0]}/{src[1]}: commands go there now")
                self.target, self.last_send_t = src, -math.inf
            armed = bool(msg.base_mode & 128)  # MAV_MODE_FLAG_SAFETY_ARMED
            if self.first_send_t is not None and not armed:
                self.done = True
                self.log(f"robot: HEARTBEAT shows it disarmed (mode {msg.custom_mode}); robot done")
                return

    def close(self) -> None:
        if self.conn is not None:
            with contextlib.suppress(OSError):
                self.conn.close()


class GuardianProcess:
    """The watch and the takeover (module docstring of drivers/guardian/launcher.py).

    `flightstack guard` (drivers/lab/guard.py) reuses the takeover alone: watch_stdin=False (no parent pipe),
    flag None (no parent to mute), then `take_over`, and `poll` + `step_takeover` until it returns."""

    def __init__(
        self,
        cfg: GuardianConfig,
        flag: TakeoverFlag | None,
        log: Log,
        watch_stdin: bool = True,
        beat_fd: int | None = None,
    ) -> None:
        """beat_fd: where to write the guardian's heartbeat to its parent (None: nowhere)."""
        self.cfg, self.flag, self.log = cfg, flag, log
        self.beat_fd = beat_fd
        self.last_beat_out = -math.inf
        self.beats_dropped = 0
        self.terminate = False  # SIGTERM: stop on purpose = take over, then exit
        th = PhaseThresholds(ground_h_cm=cfg.ground_h_cm, motor_quiet_s=cfg.motor_quiet_s)
        self.drones = [Drone(t, PhaseTracker(th)) for t in cfg.tellos]
        self.sel = selectors.DefaultSelector()
        self.cmd_socks: dict[Local, socket.socket] = {}
        for local in sorted({(t.interface or "", t.bind_ip) for t in cfg.tellos}):
            s = udp_socket(local[0] or None)  # one per interface: a land leaves through its drone's adapter
            try:
                s.bind((local[1], 0))
            except OSError:
                s.close()
                raise
            s.setblocking(False)
            self.cmd_socks[local] = s
            self.sel.register(s, selectors.EVENT_READ, ("reply", local))
        self.state_socks: dict[StatePort, socket.socket | None] = {
            (t.interface or "", t.bind_ip, t.state_port): None for t in cfg.tellos
        }
        self.held_logged: set[StatePort] = set()
        self.last_bind_try = -math.inf
        self.robot = Robot(cfg, log, target=cfg.robot_target) if cfg.robot_url else None
        self.armed = False
        self.last_beat = time.monotonic()
        self.bye = False
        self.takeover_t: float | None = None
        self.watch_ppid = os.getppid() == cfg.parent_pid
        if watch_stdin:
            os.set_blocking(0, False)
            self.sel.register(0, selectors.EVENT_READ, ("stdin", ""))

    # ---- watching the parent -------------------------------------------------------------------------
    def parent_gone(self) -> bool:
        if self.watch_ppid:
            return os.getppid() != self.cfg.parent_pid
        try:
            os.kill(self.cfg.parent_pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            return False
        return False

    def read_stdin(self, now: float) -> None:
        try:
            data = os.read(0, 65536)
        except BlockingIOError:
            return
        except OSError as exc:
            data = b""
            self.log(f"pipe read error: {exc}", "warning")
        if not data:
            self.sel.unregister(0)
            if not self.bye and self.takeover_t is None:
                self.take_over(now, "the parent's pipe closed: the parent ended without 'bye'")
            return
        if self.takeover_t is not None:
            return  # a resumed parent: takeover is final
        if BYE in data:
            self.bye = True
            self.log("bye from the parent: its drones landed normally; exiting, nothing sent")
            return
        self.last_beat = now  # any byte: the parent is ticking
        armed = self.armed
        for byte in data:  # the last ARM / UNARM wins
            armed = True if byte == ARM[0] else False if byte == UNARM[0] else armed
        if armed != self.armed:
            self.armed = armed
            self.log(f"stall detection {'armed' if armed else 'disarmed'} (stall_s {self.cfg.stall_s:g})")

    # ---- the takeover ----------------------------------------------------------------------------------
    def take_over(self, now: float, why: str) -> None:
        self.takeover_t = now
        try:
            if self.flag is not None:
                self.flag.set()
        except Exception as exc:  # the drones come first
            self.log(f"cannot set the takeover flag: {exc}", "error")
        self.mark_down(now)
        self.send_all(now, first=True)
        flag = "flag set, " if self.flag is not None else ""
        self.log(f"TAKEOVER: {why}; {flag}rc 0 0 0 0 and land sent to {len(self.drones)} Tello(s)", "warning")
        if self.robot is not None:
            self.robot.step(now)

    def mark_down(self, now: float) -> None:
        """Note every drone fresh telemetry shows on the ground: nothing is sent to it any more (a land to a
        drone whose motors are off is refused at best)."""
        for d in self.drones:
            if d.down_t is None and d.is_down(now):
                d.down_t = now
                self.log(f"{d.spec.name}: down ({self.telemetry(d)}); no more sends to it")

    def send_all(self, now: float, first: bool = False) -> None:
        for d in self.drones:
            s = d.tracker.latest
            low = s is not None and now - s.t <= 0.5 and d.tracker.low(s)  # tof first: h drifts in flight
            d.low_since = (d.low_since or now) if low else None
            if d.low_since is not None and now - d.low_since < self.cfg.motor_quiet_s + 1.0:
                continue  # fresh telemetry shows it at the ground: give its motors time to stop
            if d.down_t is None and (first or now - d.last_send_t >= self.cfg.land_resend_s):
                self.send(d, "rc 0 0 0 0")
                self.send(d, "land")
                d.last_send_t, d.sends = now, d.sends + 1
                if not first:
                    self.log(
                        f"{d.spec.name}: rc 0 0 0 0 + land re-sent ({d.sends}, {self.telemetry(d)})",
                        "warning",
                    )

    def send(self, d: Drone, text: str) -> None:
        try:
            sock = self.cmd_socks[(d.spec.interface or "", d.spec.bind_ip)]
            sock.sendto(text.encode("ascii"), (d.spec.host, d.spec.control_port))
        except OSError as exc:
            self.log(f"{d.spec.name}: sending {text!r} failed: {exc}", "warning")

    def telemetry(self, d: Drone) -> str:
        s = d.tracker.latest
        return "no telemetry" if s is None else f"h {s.h_cm:.0f} cm, motor time {s.motor_s:.0f} s"

    def bind_state_ports(self, now: float) -> None:
        if now - self.last_bind_try < BIND_RETRY_S:
            return
        self.last_bind_try = now
        for key, sock in self.state_socks.items():
            if sock is not None:
                continue
            where = f"{key[1] or '*'}:{key[2]}" + (f" on {key[0]}" if key[0] else "")
            try:
                s = udp_socket(key[0] or None)
            except OSError as exc:
                self._bind_failed(key, f"state port {where}: {exc}")
                continue
            try:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind(key[1:])
            except OSError as exc:
                s.close()
                held = "held (by the stopped parent?)" if exc.errno == errno.EADDRINUSE else str(exc)
                self._bind_failed(key, f"state port {where} {held}")
                continue
            s.setblocking(False)
            self.state_socks[key] = s
            self.sel.register(s, selectors.EVENT_READ, ("state", key))
            self.log(f"state port {where} bound: telemetry")

    def _bind_failed(self, key: StatePort, why: str) -> None:
        """Log once per state port that it cannot be bound (retried every BIND_RETRY_S)."""
        if key not in self.held_logged:
            self.held_logged.add(key)
            self.log(f"{why}; re-sending without telemetry", "warning")

    def read_state(self, key: StatePort, now: float) -> None:
        sock = self.state_socks[key]
        assert sock is not None
        for _ in range(64):
            try:
                data, addr = sock.recvfrom(2048)
            except BlockingIOError:
                return
            except OSError as exc:
                self.log(f"state port {key[2]}: {exc}", "warning")
                return
            for d in self.drones:  # told apart by interface, then by source address
                spec = d.spec
                if spec.host == addr[0] and (spec.interface or "", spec.bind_ip, spec.state_port) == key:
                    try:
                        d.tracker.observe(parse_state(data, now))
                    except StateRejectedError:
                        continue

    def drain_replies(self, local: Local) -> None:
        via = f" via {local[0]}" if local[0] else ""
        for _ in range(64):
            try:
                data, addr = self.cmd_socks[local].recvfrom(2048)
            except OSError:
                return
            self.log(f"{addr[0]}{via}: reply {data[:40].decode('ascii', 'replace').strip()!r}")

    def step_takeover(self, now: float) -> int | None:
        """One takeover tick; the exit code once finished, else None."""
        assert self.takeover_t is not None
        self.bind_state_ports(now)
        self.mark_down(now)
        self.send_all(now)
        if self.robot is not None:
            self.robot.step(now)
        if all(d.down_t is not None for d in self.drones) and (self.robot is None or self.robot.done):
            self.log(f"takeover complete after {now - self.takeover_t:.2f} s: every drone down, robot done")
            return EXIT_DONE
        if now - self.takeover_t > self.cfg.give_up_s:
            up = [d.spec.name for d in self.drones if d.down_t is None]
            self.log(
                f"giving up after {self.cfg.give_up_s:g} s; not seen down: {up} (the Tello auto-lands)",
                "error",
            )
            return EXIT_GAVE_UP
        return None

    def run(self) -> int:
        c = self.cfg
        hosts = [t.name for t in c.tellos]
        self.log(
            f"watching parent {c.parent_pid}: Tellos {hosts}, robot {c.robot_url!r}, {c.extra}; "
            f"site-packages {site_packages()}; flightstack {package_dir()}; "
            f"stop on purpose: kill -TERM {os.getpid()}"
        )
        errors = 0
        while True:
            try:
                code = self.tick()
            except Exception as exc:  # the watch must outlive any bug (logged at the 1st, then every 100th)
                errors += 1
                if errors == 1 or errors % 100 == 0:
                    self.log(f"error #{errors} in the loop: {type(exc).__name__}: {exc}", "error")
                time.sleep(TICK_S)
                continue
            if code is not None:
                return code

    def poll(self, timeout_s: float = TICK_S) -> None:
        """Wait ≤ timeout_s (s) for the pipe, the Tellos' replies and telemetry; read what arrived."""
        for key, _ in self.sel.select(timeout_s):
            kind, arg = key.data
            now = time.monotonic()
            if kind == "stdin":
                self.read_stdin(now)
            elif kind == "state":
                self.read_state(arg, now)
            else:
                self.drain_replies(arg)

    def beat_parent(self, now: float) -> None:
        """One byte to the parent every GUARDIAN_BEAT_S (non-blocking; a full or closed pipe is counted)."""
        if self.beat_fd is None or now - self.last_beat_out < GUARDIAN_BEAT_S:
            return
        self.last_beat_out = now
        try:
            os.write(self.beat_fd, BEAT)
        except BlockingIOError:
            self.beats_dropped += 1  # the parent is not reading (blocked or stopped): it reads them later
        except OSError:
            self.beat_fd = None  # the parent is gone: the pipe's EOF on stdin says so too

    def tick(self) -> int | None:
        """One pass of the loop (≤ TICK_S of waiting); the exit code once the guardian is done."""
        self.poll(TICK_S)
        now = time.monotonic()
        self.beat_parent(now)
        if self.bye and self.takeover_t is None:
            return EXIT_BYE
        if self.takeover_t is None:
            silent = now - self.last_beat
            if self.terminate:
                self.take_over(now, "SIGTERM: stopped on purpose")
            elif self.parent_gone():
                self.take_over(now, f"parent {self.cfg.parent_pid} is gone")
            elif self.armed and silent > self.cfg.stall_s:
                self.take_over(now, f"no heartbeat for {silent:.2f} s (stall_s {self.cfg.stall_s:g})")
        return self.step_takeover(now) if self.takeover_t is not None else None

    def close(self) -> None:
        for s in [*self.cmd_socks.values(), *self.state_socks.values()]:
            if s is not None:
                s.close()
        if self.robot is not None:
            self.robot.close()


def site_packages() -> list[str]:
    """The resolved site-packages directories of this interpreter: the environment the guardian runs in
    (its own prefix is the neutral launch directory, drivers/guardian.guardian_argv)."""
    return [os.path.realpath(p) for p in site.getsitepackages()]


def package_dir() -> str:
    """Where this process imported its code from (this module's folder, resolved): the checkout's
    drivers/ (an editable install) or site-packages' flightstack/drivers."""
    return os.path.dirname(os.path.realpath(__file__))


def read_config(timeout_s: float = 10.0) -> str:
    """The config line from stdin, read byte by byte so that the heartbeats after it stay in the pipe."""
    buf = b""
    deadline = time.monotonic() + timeout_s
    while b"\n" not in buf:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([0], [], [], left)[0]:
            raise TimeoutError(f"no config line within {timeout_s:g} s")
        chunk = os.read(0, 1)
        if not chunk:
            raise EOFError("stdin closed before the config line")
        buf += chunk
    return buf.decode()


def main() -> int:
    """Entry point of the guardian process (`Guardian.start` runs it through BOOTSTRAP)."""
    for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGTSTP, signal.SIGTTOU, signal.SIGTTIN):
        signal.signal(sig, signal.SIG_IGN)
    try:
        cfg = GuardianConfig.from_json(read_config())
        flag = TakeoverFlag(cfg.flag_path)
    except Exception as exc:
        sys.stdout.write(f"error: {type(exc).__name__}: {exc}\n")
        sys.stdout.flush()
        return EXIT_CONFIG
    log = Log(cfg.log_path)
    oom = next((v for v in OOM_SCORE_ADJ_GUARDIAN if set_oom_score_adj(v) is not None), None)
    log(f"oom_score_adj {'set to ' + str(oom) if oom is not None else 'kept (it may not be lowered here)'}")
    nice_set, group_set = set_nice(GUARDIAN_NICE), set_group_nice(GUARDIAN_NICE)
    log(
        f"CPU priority: nice {os.getpriority(os.PRIO_PROCESS, 0)}, its session's group "
        f"{GUARDIAN_NICE if group_set else 'unchanged'}"
        + ("" if nice_set and group_set else " (raising them needs CAP_SYS_NICE; some kernels have no group)")
    )
    g = None
    try:
        g = GuardianProcess(cfg, flag, log, beat_fd=1)
        guardian = g

        def on_term(signum: int, frame: Any) -> None:
            guardian.terminate = True  # acted on by the next tick (≤ TICK_S): take over, then exit

        signal.signal(signal.SIGTERM, on_term)
        os.write(1, READY + b"\n")
        os.set_blocking(1, False)  # from now on stdout carries only the heartbeat
        code = g.run()
    except Exception as exc:
        log(f"{type(exc).__name__}: {exc}", "error")
        code = EXIT_CONFIG if g is None else EXIT_GAVE_UP
        if g is None:  # never ready (e.g. a socket it cannot bind to its interface): the parent says why
            with contextlib.suppress(OSError):
                os.write(1, f"error: {type(exc).__name__}: {exc}\n".encode(errors="replace"))
    finally:
        if g is not None:
            g.close()
        remove_launch_dir(cfg.launch_dir)
    log(f"exit {code}", "info" if code == 0 else "warning")
    log.close()
    return code


if __name__ == "__main__":  # `python -m flightstack.drivers.guardian.process`, by hand
    sys.exit(main())
