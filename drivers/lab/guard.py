"""`flightstack guard MISSION`: land the Tello of an agent process that vanishes in flight.

Optional, on the operator's computer (station topology only; refused in access-point mode,
`guard_refusal`). It joins the mission's Zenoh bus as the operator tool "guard" (publishes nothing),
follows every agent's liveliness token and its status reports (validated `control.StatusReport`s; a
malformed one counts as none) and, when an agent vanishes in flight, lands its Tello with the guardian's
code (drivers/guardian/process.py `GuardianProcess`, one per drone, sockets opened at start so a takeover
sends at once): `rc 0 0 0 0` then `land`, re-sent every `land_resend_s` until telemetry shows it down or
`give_up_s`. What it decides and why (in flight = last status `flying` and at most `status_fresh_s` old
when the token went; silence alone never triggers; an agent that comes back ends the takeover), and what
it measured: docs/bus.md ("Guard").

Telemetry: during a takeover guard binds the mission's `state_port` if free (SO_REUSEADDR; a live agent's
driver on this computer holds it exclusively), so it sees the drone down only on the dead agent's
computer; elsewhere it re-sends until `give_up_s` (a grounded Tello ignores both). A partition hiding a
live agent for longer than the lease makes guard land its drone: safety first.

Every event is one line `guard <pid> t=<time.monotonic() s> <text>` on stdout (`Log`, a writer thread: a
blocked terminal never delays a takeover). One thread runs the watch, a loop of ≤ POLL_S over the bus's
presence and status events and the landers' sockets. Units: times in s (time.monotonic()).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from flightstack.comms.control import ControlEvent, StatusReport, status_report
from flightstack.config.mission import Mission
from flightstack.drivers.guardian.launcher import EXIT_DONE, GuardianConfig
from flightstack.drivers.guardian.process import GuardianProcess, Log
from flightstack.drivers.lab.hardware import tello_config
from flightstack.events import Event

POLL_S = 0.01  # longest wait between two looks at the bus and the landers (s)
STATUS_FRESH_MIN_S = 2.0  # lower bound of status_fresh_s (s)


class GuardBus(Protocol):
    """What guard reads of a flightstack.comms.zenoh_bus.ZenohBus."""

    @property
    def presence_events(self) -> list[Event]: ...
    def control_events(self) -> list[ControlEvent]: ...


def guard_refusal(mission: Mission) -> str | None:
    """Why `flightstack guard` cannot protect this mission's drones from this computer, or None."""
    hw = mission.hardware
    if hw is None:
        return (
            f"mission {mission.name}: guard lands real Tellos; this mission has no hardware section "
            "(simulated agents are landed by `flightstack world`)"
        )
    if hw.topology != "station":
        return (
            f"mission {mission.name}: hardware.topology is {hw.topology!r}: each Tello is its own Wi-Fi "
            "access point (192.168.10.1), reachable only from its agent's computer, so guard on this "
            "computer cannot reach it. guard needs `topology: station` (every Tello on the lab network); "
            "in access-point mode each agent's own guardian process lands its drone when the agent dies"
        )
    if mission.bus.kind != "zenoh" or mission.bus.zenoh is None:
        return f"mission {mission.name}: guard watches agents on the Zenoh bus (bus.kind: zenoh)"
    return None


@dataclass
class AgentWatch:
    """What guard knows of one agent (times: time.monotonic() s as received here)."""

    present: bool = False
    flying: bool | None = None  # its last status said flying (None: no status since it appeared)
    status_t: float = -math.inf
    silent_reported: bool = False


@dataclass
class Takeover:
    """One landing by guard: the drone, when its agent vanished and how it ended."""

    drone: int
    t_left: float  # its token vanished (s)
    why: str
    result: str = "landing"  # "landing" | "down" | "gave up" | "agent back" | "interrupted"
    t_end: float | None = None
    sends: int = 0


@dataclass
class GuardSummary:
    """What happened while guard watched."""

    takeovers: list[Takeover] = field(default_factory=list)
    ignored: list[tuple[int, str]] = field(default_factory=list)  # (drone, why nothing was sent)
    errors: int = 0


class Guard:
    """The watch (module docstring). `run()` returns when `duration_s` is over and no landing runs."""

    def __init__(
        self,
        mission: Mission,
        bus: GuardBus,
        log: Log,
        *,
        status_fresh_s: float | None = None,
        land_resend_s: float = 1.0,
        give_up_s: float = 20.0,
    ) -> None:
        """status_fresh_s: a last `flying` status at most this old (s) when the token vanishes means in
        flight (None: max(STATUS_FRESH_MIN_S, lease + 1 s)); land_resend_s, give_up_s: as the guardian's
        (s). ValueError when the mission cannot be guarded from here (`guard_refusal`)."""
        why = guard_refusal(mission)
        if why is not None:
            raise ValueError(why)
        assert mission.bus.zenoh is not None
        self.mission = mission
        self.bus = bus
        self.log = log
        lease_s = mission.bus.zenoh.lease_ms / 1000.0
        self.status_fresh_s = (
            max(STATUS_FRESH_MIN_S, lease_s + 1.0) if status_fresh_s is None else float(status_fresh_s)
        )
        if not (self.status_fresh_s > 0 and math.isfinite(self.status_fresh_s)):
            raise ValueError(f"status_fresh_s {status_fresh_s}: must be a finite number of seconds > 0")
        self.ids = [d.id for d in mission.drones]
        self.cfgs = {
            i: GuardianConfig.for_devices(
                [tello_config(mission, i)],
                None,
                land_resend_s=land_resend_s,
                give_up_s=give_up_s,
                extra={"mission": mission.name, "drone": i},
            )
            for i in self.ids
        }
        self.agents = {i: AgentWatch() for i in self.ids}
        self.landers: dict[int, GuardianProcess] = {}
        self.active: dict[int, Takeover] = {}
        self.summary = GuardSummary()
        self._n_presence = 0
        try:
            for i in self.ids:
                self.landers[i] = self._new_lander(i)
        except BaseException:
            self.close()
            raise

    # ---- the landers -------------------------------------------------------------------------------
    def _new_lander(self, i: int) -> GuardianProcess:
        """Drone i's lander: its own command socket, open now, nothing sent until `take_over`."""
        return GuardianProcess(self.cfgs[i], None, self.log, watch_stdin=False)

    def local_port(self, i: int) -> int:
        """The UDP port guard sends drone i's commands from (its current lander's socket)."""
        lander = self.landers[i]
        return int(next(iter(lander.cmd_socks.values())).getsockname()[1])

    def _describe(self, i: int) -> str:
        t = self.cfgs[i].tellos[0]
        return f"drone {i} at {t.host}:{t.control_port} (from local port {self.local_port(i)})"

    def _end(self, i: int, result: str, now: float, reopen: bool = True) -> None:
        """End drone i's takeover (result as Takeover.result); reopen: a fresh lander for its next flight."""
        tk = self.active.pop(i)
        lander = self.landers.pop(i)
        tk.result, tk.t_end, tk.sends = result, now, lander.drones[0].sends
        self._close_lander(lander)
        again = ""
        if reopen:
            self.landers[i] = self._new_lander(i)
            again = f"; guarding it again from local port {self.local_port(i)}"
        self.log(
            f"drone {i}: takeover ended ({result}) {now - tk.t_left:.2f} s after agent {i} vanished, "
            f"{tk.sends} send(s) of rc 0 0 0 0 + land{again}"
        )

    @staticmethod
    def _close_lander(lander: GuardianProcess) -> None:
        with contextlib.suppress(Exception):
            lander.close()
        with contextlib.suppress(Exception):
            lander.sel.close()

    # ---- the watch ---------------------------------------------------------------------------------
    def start_line(self) -> None:
        """Log what is guarded and from where."""
        drones = "; ".join(self._describe(i) for i in self.ids)
        self.log(
            f"watching mission {self.mission.name}: {drones}; in flight = last status flying and "
            f"≤ {self.status_fresh_s:g} s old when the token vanishes"
        )

    def run(self, duration_s: float = math.inf) -> GuardSummary:
        """Watch until `duration_s` (s) has passed and no takeover is running (a takeover in progress is
        completed, ≤ give_up_s); KeyboardInterrupt propagates (call `interrupted()`, then `close()`)."""
        t_end = time.monotonic() + duration_s
        said_over = False
        while True:
            now = time.monotonic()
            try:
                self.step(now)
            except Exception as exc:  # the watch must outlive any bug (logged at the 1st, every 100th)
                self.summary.errors += 1
                if self.summary.errors == 1 or self.summary.errors % 100 == 0:
                    self.log(
                        f"error #{self.summary.errors} in the watch: {type(exc).__name__}: {exc}", "error"
                    )
            if now >= t_end:
                if not self.active:
                    break
                if not said_over:
                    said_over = True
                    self.log(f"duration over; finishing the landing of drones {sorted(self.active)}")
            time.sleep(POLL_S)
        return self.summary

    def step(self, now: float) -> None:
        """One look: statuses and presence changes in order of receipt, silences, running takeovers."""
        events: list[tuple[float, int, str, StatusReport | None]] = []
        presence = self.bus.presence_events
        for p in presence[self._n_presence :]:
            if p.drone is not None:
                events.append((p.t, p.drone, p.kind, None))
        self._n_presence = len(presence)
        for ev in self.bus.control_events():
            report = status_report(ev)  # None: not a status, or a malformed one (the bus counted it)
            if report is not None and report.drone in self.agents and report.drone in ev.origin:
                events.append((ev.time, report.drone, "status", report))
        for t, i, what, report in sorted(events, key=lambda e: e[0]):
            if report is not None:
                self._on_status(i, report, t)
            elif what == "joined":
                self._on_joined(i)
            elif what == "left":
                self._on_left(i, t)
        self._check_silence(now)
        for i in list(self.active):
            lander = self.landers[i]
            lander.poll(0.0)
            code = lander.step_takeover(time.monotonic())
            if code is not None:
                self._end(i, "down" if code == EXIT_DONE else "gave up", time.monotonic())

    def _on_status(self, i: int, report: StatusReport, t: float) -> None:
        """Agent i's validated status, received at t (time.monotonic() s)."""
        a = self.agents[i]
        flying = report.flying
        if flying != a.flying:
            self.log(f"agent {i}: status {'flying' if flying else 'not flying'}")
        a.flying, a.status_t, a.silent_reported = flying, t, False

    def _on_joined(self, i: int) -> None:
        a = self.agents[i]
        if a.present:
            return
        a.present = True
        if i in self.active:
            self.log(f"agent {i} is back: nothing more is sent to drone {i}")
            self._end(i, "agent back", time.monotonic())
        self.log(f"agent {i} present")

    def _on_left(self, i: int, t: float) -> None:
        a = self.agents[i]
        if not a.present:
            return
        age = t - a.status_t
        flying, a.present, a.flying, a.status_t = a.flying, False, None, -math.inf
        if flying and age <= self.status_fresh_s:
            why = f"agent {i}'s token vanished in flight (last status flying, {age:.2f} s old)"
            self.active[i] = Takeover(i, t, why)
            self.landers[i].take_over(time.monotonic(), why)
            self.log(f"LANDING {self._describe(i)}: rc 0 0 0 0 + land sent, re-sent until down", "warning")
            self.summary.takeovers.append(self.active[i])
            return
        if flying is None:
            why = "no status since it appeared (taking off? its own guardian covers that)"
        elif not flying:
            why = f"last status not flying ({age:.2f} s old)"
        else:
            why = (
                f"last status flying but {age:.2f} s old (> {self.status_fresh_s:g} s: it was landing at the "
                "end of its run, or stalled, which its own guardian covers)"
            )
        self.summary.ignored.append((i, why))
        self.log(f"agent {i} left: {why}; nothing sent to drone {i}")

    def _check_silence(self, now: float) -> None:
        for i, a in self.agents.items():
            if a.present and a.flying and not a.silent_reported and now - a.status_t > self.status_fresh_s:
                a.silent_reported = True
                self.log(
                    f"agent {i}: present but no status for {now - a.status_t:.1f} s (landing at the end of "
                    "its run, or stalled): guard does not act while its token is present"
                )

    def interrupted(self) -> None:
        """Log the takeovers cut short by Ctrl-C (what was sent stands: a Tello executes `land` at once)."""
        now = time.monotonic()
        for i in list(self.active):
            self.log(f"drone {i}: interrupted while landing it; land was sent, not seen down", "warning")
            self._end(i, "interrupted", now, reopen=False)

    def close(self) -> None:
        """Close every lander's sockets (idempotent)."""
        for lander in self.landers.values():
            self._close_lander(lander)
        self.landers.clear()

    def __enter__(self) -> Guard:
        return self

    def __exit__(self, *_exc: Any) -> None:
        self.close()


__all__ = ["AgentWatch", "Guard", "GuardBus", "GuardSummary", "Takeover", "guard_refusal"]
