"""One event type for everything that happens in a run, with its kind from one declared set.

An `Event` is what a safety rule, a device driver, the bus, the simulated world or the runner reports:
its time, the drone it concerns, a kind (declared in KINDS with its severity and meaning), a detail, the
component it comes from and the clock its time is on. Device drivers and the bus stamp with
`time.monotonic()` of their process (`clock="monotonic"`); the safety layer and the runner with the
mission clock (`clock="mission"`, s since the mission's start; virtual on simulated rigs).

A recording stores `Event.record(mode)`: a JSON object whose "event" names it (docs/logs.md, "events.jsonl").
`kind_of` reads the kind back from that form, `severity` how a viewer shows it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

Clock = Literal["mission", "monotonic"]
Severity = Literal["ERROR", "WARNING", "INFO"]
Source = Literal["safety", "bus", "tello", "mocap", "scamper", "lab", "world", "run"]

SafetyKind = Literal[
    "saturated", "invalid_command", "fence_soft", "fence_hard_land", "command_timeout", "pose_stale_hover",
    "pose_stale_land", "pose_error", "battery_refuse_takeoff", "pose_refuse_takeoff", "fence_refuse_takeoff",
    "battery_land", "target_lost_land", "link_lost", "drone_error", "command_after_land", "land_failed",
    "landed_by_drone", "landing_by_drone", "emergency_stop", "emergency_stop_failed", "target_lost_hover",
    "land_all", "signal", "takeoff", "takeoff_failed", "land", "climb_limited", "robot_moved",
    "robot_refuse_takeoff", "robot_law_start", "pose_frozen", "pose_disagrees", "robot_pose_suspect",
]  # fmt: skip
RunKind = Literal[
    "end", "end_early", "end_exception", "compiled loop", "lock-step wait timed out", "safety tick", "landed",
    "NOT LANDED", "neighbours", "recording_stopped",
]  # fmt: skip
BusKind = Literal["joined", "left", "second session", "restart", "offset learning",
                  "offset re-learning after silence", "offset frozen"]  # fmt: skip
TelloKind = Literal[
    "phase", "link_lost", "link_restored", "loop_lost_land", "loop_silent_hover", "resend",
    "reply_not_trusted", "takeoff_confirmed", "land_confirmed", "reply_lost_confirmed",
    "error_reply_but_effect", "emergency", "rc_suppressed", "replies_discarded", "stray_reply", "rejoin",
    "video_setting", "video_setting_refused", "error_unanswered", "state_implausible", "state_rejected_run",
]  # fmt: skip
MocapKind = Literal["reader_join_timeout", "reader_error", "reader_recovered", "bad_sample", "body_found",
                    "body_regained", "tilt_refused", "tilt_ok", "body_lost"]  # fmt: skip
ScamperKind = Literal[
    "connected", "disarm_skipped_muted", "disarm_failed", "no_command_needed",
    "ack_lost_confirmed_by_heartbeat", "ack_contradicted_by_heartbeat", "command_resent", "link_lost",
    "link_restored", "mode_changed", "disarmed_by_robot", "armed_by_robot", "origin_confirmed",
    "origin_forgotten",
]  # fmt: skip
LabKind = Literal["auto_land_no_command", "battery_empty"]
WorldKind = Literal["lockstep_timeout", "second session", "agent_left"]
EventKind = Literal[SafetyKind, RunKind, BusKind, TelloKind, MocapKind, ScamperKind, LabKind, WorldKind]
"""Every kind an Event may have (KINDS says what each means)."""


class KindInfo(NamedTuple):
    severity: Severity  # how a viewer shows it (the MCAP export's Log level, the Rerun text log's)
    meaning: str


def _i(meaning: str) -> KindInfo:
    return KindInfo("INFO", meaning)


def _w(meaning: str) -> KindInfo:
    return KindInfo("WARNING", meaning)


def _e(meaning: str) -> KindInfo:
    return KindInfo("ERROR", meaning)


KINDS: Mapping[str, KindInfo] = {
    # the safety layer (flightstack.safety; source "safety", mission clock)
    "saturated": _w("a command beyond the velocity limits, clipped"),
    "invalid_command": _w("a command not finite or of the wrong shape: zero velocity sent"),
    "fence_soft": _w("beyond the soft fence: the outward velocity clipped"),
    "climb_limited": _w(
        "an upward velocity that, held for the drone's own command timeout, would cross the fence's ceiling:"
        " reduced to the distance left over that timeout"
    ),
    "fence_hard_land": _w("beyond the hard fence: the drone lands"),
    "command_timeout": _w("no command within the timeout: zero velocity"),
    "pose_stale_hover": _w("the drone's pose is stale: it hovers"),
    "pose_stale_land": _w("the pose stayed stale (or frozen, or disagreeing) too long: the drone lands"),
    "pose_frozen": _w(
        "the drone's pose repeats identically under fresh stamps while it is commanded to move: it hovers "
        "(flightstack.safety.pose_check)"
    ),
    "pose_disagrees": _w(
        "the drone's pose moved in z unlike the drone's own height telemetry: it hovers "
        "(flightstack.safety.pose_check)"
    ),
    "robot_pose_suspect": _e(
        "the ground robot's pose is not finite, or frozen while it is commanded to move: the robot stops, "
        "the run fails (flightstack.runtime.phases)"
    ),
    "pose_error": _e("the pose source raised"),
    "battery_refuse_takeoff": _w("takeoff refused: battery too low"),
    "pose_refuse_takeoff": _w("takeoff refused: no fresh pose"),
    "fence_refuse_takeoff": _w("takeoff refused: the drone stands beyond the hard fence"),
    "robot_moved": _i(
        "the ground robot, nudged before takeoff, moved as commanded (flightstack.runtime.motion_check)"
    ),
    "robot_refuse_takeoff": _w(
        "takeoff refused: the ground robot did not move as commanded when nudged, or stands off its path"
    ),
    "robot_law_start": _i(
        "the ground robot's law starts at the lap time where the robot stands (a device stays where the last "
        "mode left it; flightstack.paper.target_law.start_phase)"
    ),
    "battery_land": _w("battery below the landing level: the drone lands"),
    "target_lost_land": _w("the target unseen too long: every drone lands"),
    "link_lost": _w("the link to the device is lost (the safety layer: hover and land)"),
    "drone_error": _e("a call into the drone raised"),
    "command_after_land": _w("a command after landing, dropped"),
    "land_failed": _e("land() raised or did not bring the drone down"),
    "landed_by_drone": _w("telemetry shows the drone on the ground without a land from us"),
    "landing_by_drone": _w(
        "the drone lands of its own accord (its `error Auto land`, or a descent its driver calls its own "
        "landing): no more commands; landed_by_drone follows at touchdown unless the landing was confirmed"
    ),
    "emergency_stop": _w("motors stopped on request"),
    "emergency_stop_failed": _e("the emergency stop raised"),
    "target_lost_hover": _w("the target unseen: every drone hovers"),
    "land_all": _i("the supervisor lands every drone (detail: why; a fault that caused it is its own event)"),
    "signal": _w("a signal (Ctrl-C, SIGTERM) and what the supervisor does with it"),
    "takeoff": _i("takeoff accepted and sent"),
    "takeoff_failed": _e("takeoff raised or did not lift the drone"),
    "land": _i("land sent (detail: why; a fault that caused it is its own event)"),
    # the runner (flightstack.runtime; source "run", mission clock; facts: the record's other fields)
    "end": _i('the mode ended as planned ("mission complete")'),
    "end_early": _w("the mode ended early: every drone landed by safety, interrupted, aborted or diverged"),
    "end_exception": _e("the mode ended by an exception in the loop"),
    "compiled loop": _i("ticks flown by the compiled loop and in Python"),
    "lock-step wait timed out": _w("phase 2 went on without some neighbours' messages of the tick"),
    "safety tick": _i("the safety tick's timing over the mode"),
    "landed": _i("the drone says it is down after the run"),
    "NOT LANDED": _e("the drone says it is still flying after the run"),
    "neighbours": _i("the neighbours a drone fuses changed"),
    "recording_stopped": _e("the run directory stopped taking data (disk full, I/O error)"),
    # the bus (flightstack.comms; source "bus", monotonic clock; drone: the sender)
    "joined": _i("an agent appeared on the bus"),
    "left": _i("an agent left the bus"),
    "second session": _w("a second process speaks for a drone; its messages are dropped"),
    "restart": _w(
        "a sender's messages taken again by the restart rule (flightstack/comms/acceptance.py): it counted "
        "again, this receiver joined it late, or another stream took its id (detail: the sender, the seqs)"
    ),
    "offset learning": _i("first messages of a sender: its clock offset is being learned (value: s)"),
    "offset re-learning after silence": _i("a sender back after silence: its offset is learned again"),
    "offset frozen": _i("a sender's clock offset is fixed (value: s)"),
    # the Tello driver (drivers/tello*; source "tello", monotonic clock)
    "phase": _i("the flight phase changed (detail: from -> to)"),
    "link_restored": _i("state packets again after a lost link"),
    "loop_lost_land": _w("no velocity from the control loop too long: the driver lands"),
    "loop_silent_hover": _w("no velocity from the control loop: sticks centred"),
    "resend": _w("a takeoff or land sent again (no effect in telemetry, silent telemetry, the link back)"),
    "reply_not_trusted": _w("an 'ok' the telemetry contradicts"),
    "takeoff_confirmed": _i("telemetry shows the takeoff done"),
    "land_confirmed": _i("telemetry shows the landing done"),
    "reply_lost_confirmed": _w("a command without reply that telemetry shows done"),
    "error_reply_but_effect": _w("an error reply, yet telemetry shows the command done"),
    "emergency": _w("emergency: motors off"),
    "rc_suppressed": _i("stick commands not sent (detail: why)"),
    "replies_discarded": _i("stale replies dropped before a command"),
    "stray_reply": _w(
        "a reply that answers no command waiting for it: a keep-alive's `ok`, a late one (the first of each"
        " kind ok/error/value; then counted: stray_reply_<kind>)"
    ),
    "rejoin": _w("state stream silent: 'command' sent again at a bounded rate (a rebooted drone needs it)"),
    "video_setting": _i("an SDK 3.0 video setting of the lab file confirmed at connect (detail: command)"),
    "video_setting_refused": _w("an SDK 3.0 video setting the drone refused or never answered (no video)"),
    "error_unanswered": _w(
        "an `error …` from the drone that answers no command (its text); `error Auto land`: it lands itself"
    ),
    "state_implausible": _w(
        "a state value outside its physical bounds, used as sent (detail: field=value and the bounds; once"
        " per field until a line carries it within them again)"
    ),
    "state_rejected_run": _w(
        "the drone's state datagrams all rejected for the link timeout (detail: how many, over how long, the"
        " reasons); the link is lost, not silent"
    ),
    # the motion-capture source (drivers/mocap.py; source "mocap", monotonic clock; detail: the body)
    "reader_join_timeout": _w("the reader thread did not stop in time"),
    "reader_error": _e("the reader thread raised"),
    "reader_recovered": _i("frames again after reader errors"),
    "bad_sample": _w("a body's sample is not a valid pose"),
    "body_found": _i("a body seen for the first time"),
    "body_regained": _i("a lost body seen again"),
    "tilt_refused": _w("a body tilted beyond the limit: its pose refused"),
    "tilt_ok": _i("a body's tilt within the limit again"),
    "body_lost": _w("a body no longer in the frames"),
    # the Scamper rover driver (drivers/scamper/driver.py; source "scamper", monotonic clock)
    "connected": _i("heartbeat seen, GUIDED and armed: streaming set-points"),
    "disarm_skipped_muted": _i("no disarm: another process has taken over the robot"),
    "disarm_failed": _e("the disarm on close failed"),
    "no_command_needed": _i("the robot already shows the wanted state"),
    "ack_lost_confirmed_by_heartbeat": _w("no COMMAND_ACK, yet the heartbeat shows the command done"),
    "ack_contradicted_by_heartbeat": _w("a refusing COMMAND_ACK, yet the heartbeat shows the command done"),
    "command_resent": _w("a command sent again (no ACK, no heartbeat change)"),
    "mode_changed": _w("the robot changed mode without this driver"),
    "disarmed_by_robot": _w("the robot disarmed itself"),
    "armed_by_robot": _w("the robot armed again by itself"),
    "origin_confirmed": _i("the robot reported its EKF origin (GPS_GLOBAL_ORIGIN) after the driver set it"),
    "origin_forgotten": _w("the robot rebooted or came back after a gap: its EKF origin is set again"),
    # the simulated lab's drone model (sim_backend/lab.py; source "lab", mission clock)
    "auto_land_no_command": _w("no command too long: the modelled drone lands by itself"),
    "battery_empty": _w("the modelled battery is empty: the drone lands"),
    # the served world (sim_backend/served; source "world", mission clock)
    "lockstep_timeout": _w("a tick went on without some agents' commands"),
    "agent_left": _w("an agent left: its drone lands"),
}
"""Severity and meaning of every kind of EventKind."""

END_KINDS: tuple[RunKind, RunKind, RunKind] = ("end", "end_early", "end_exception")
"""The kinds of a mode's last runner event, all recorded as "event": "end" with its "reason"."""


def end_kind(reason: str) -> RunKind:
    """The kind of the "end" event of a mode that ended for `reason` (the runner's words)."""
    if reason == "mission complete":
        return "end"
    return "end_exception" if reason.startswith("exception") else "end_early"


@dataclass(frozen=True)
class Event:
    """t: time (s) on `clock` (NaN: none known); drone: the drone's id (None: mission-wide or not about
    one drone); kind: one of KINDS (ValueError otherwise); detail: free text (a body name, a reason);
    source: the component that reports it; value: a number that belongs to the event (e.g. a clock
    offset in s), None if none; facts: the kind's own JSON fields (runner events: e.g. height_m)."""

    t: float
    drone: int | None
    kind: EventKind
    detail: str = ""
    source: Source = "run"
    clock: Clock = "mission"
    value: float | None = None
    facts: Mapping[str, Any] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"undeclared event kind {self.kind!r} (flightstack.events.KINDS)")

    def to_dict(self) -> dict[str, Any]:
        """Every field as JSON (the facts merged in)."""
        return {
            "t": self.t,
            "drone": self.drone,
            "kind": self.kind,
            "detail": self.detail,
            "source": self.source,
            "clock": self.clock,
            "value": self.value,
            **self.facts,
        }

    def record(self, mode: str | None) -> dict[str, Any]:
        """The recorded form (a line of events.jsonl; docs/logs.md) in mode `mode` (None: not in one):
        - source "run": {"t", "event": the kind ("end" for END_KINDS), "drone" if any, **facts, "mode"};
        - source "bus": {"event": "bus presence", "mode", "sender", "what": the kind, "monotonic": t,
          "detail" if any};
        - any other: {"event": the source, "mode", **to_dict()} (e.g. "event": "safety")."""
        at_mode = {} if mode is None else {"mode": mode}
        if self.source == "run":
            name = "end" if self.kind in END_KINDS else self.kind
            who = {} if self.drone is None else {"drone": self.drone}
            t = self.t if math.isfinite(self.t) else None
            return {"t": t, "event": name, **who, **self.facts, **at_mode}
        if self.source == "bus":
            out = {
                "event": "bus presence",
                **at_mode,
                "sender": self.drone,
                "what": self.kind,
                "monotonic": self.t,
            }
            return out | ({"detail": self.detail} if self.detail else {})
        return {"event": self.source, **at_mode, **self.to_dict()}

    def __str__(self) -> str:
        who = "" if self.drone is None else f" drone {self.drone}"
        tail = f": {self.detail}" if self.detail else ""
        facts = "".join(f" {k}={v}" for k, v in self.facts.items())
        return f"t = {self.t:.3f} s ({self.source}{who}) {self.kind}{tail}{facts}"


def kind_of(ev: Mapping[str, Any]) -> str | None:
    """The kind of a recorded event (`Event.record`'s form), None when it is not one of KINDS (a
    recording from another version)."""
    name = ev.get("event")
    if name == "bus presence":
        kind = ev.get("what")
    elif name == "end":
        kind = end_kind(str(ev.get("reason", "")))
    elif "kind" in ev:
        kind = ev.get("kind")
    else:
        kind = name
    return kind if isinstance(kind, str) and kind in KINDS else None


def mission_time(ev: Mapping[str, Any]) -> float | None:
    """The recorded event's time on the mission clock (s), or None when it has none: no finite `t`, or
    a `t` on another clock (a device's or the bus's monotonic stamp)."""
    t = ev.get("t")
    if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
        return float(t) if ev.get("clock", "mission") == "mission" else None
    return None


def severity(ev: Mapping[str, Any]) -> Severity:
    """How a viewer shows a recorded event: the severity of its kind (KINDS); WARNING for a kind not
    declared here (a recording from another version)."""
    kind = kind_of(ev)
    return "WARNING" if kind is None else KINDS[kind].severity


LOG_LEVELS: Mapping[Severity, int] = {"INFO": 20, "WARNING": 30, "ERROR": 40}
"""A severity as a `logging` level (logging.INFO, WARNING, ERROR): how a component that logs its events
as they happen (the safety layer, the Tello driver) logs each kind; the console shows the level
(docs/logs.md, "What a run prints")."""


def log_level(kind: str) -> int:
    """The `logging` level of an event of `kind` (its KINDS severity; WARNING for an undeclared one)."""
    info = KINDS.get(kind)
    return LOG_LEVELS["WARNING" if info is None else info.severity]
