"""Safety supervisor (DESIGN §7): wraps every hal.Drone of a mission, on every backend.

`SafeDrone` is a hal.Drone that wraps another one and enforces the per-drone rules (saturation, geofence,
command watchdog, stale pose, battery, link loss, landing confirmation); `MissionSupervisor`
(flightstack/safety/supervisor.py) adds the mission-wide ones (target lost, land every drone, signals, the
exception guard). The rules, their reactions, the limits and every event kind are stated once, in
docs/safety.md. Limits, events and the pure rules are in flightstack/safety/rules.py. The landing sequence
is part of SafeDrone: a land puts the drone in LAND_PENDING (no velocity reaches the wrapped drone any more)
and is re-sent every `land_retry_s` until confirmed by the wrapped drone's land() returning, by its
telemetry (phase ground) or by motion capture (z ≤ `landed_height`), while the fence rule keeps logging on
the last known pose and a silent link gets zero velocity (hover). With `background` on (hardware), the
wrapped drone's takeoff() and land() run on worker threads (flightstack/safety/jobs.py), never waited for on
the control thread; tick() collects their outcome.

Every condition logs exactly one `SafetyEvent` per episode (the interval during which it holds), stamped
with the mission clock; its kind is one of the closed set `EVENT_KINDS`. Errors from the wrapped drone
inside `send_body_velocity`, `takeoff`, `connect`, `state` and `close` propagate unchanged (the caller's
`MissionSupervisor.guard()` lands everything); the safety rules themselves never raise into the control
loop.
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from flightstack.events import SafetyKind
from flightstack.hal import Clock, Drone, DroneState, FlightPhase, HoldsLastCommand, PoseSource, StampedPose
from flightstack.paper.delay_compensation import stamp_refusal
from flightstack.paper.geometry import Pose
from flightstack.safety.jobs import DroneJobs
from flightstack.safety.pose_check import FreezeWatch, HeightAgreement
from flightstack.safety.rules import (
    EventLog,
    SafetyError,
    SafetyLimits,
    climb_cap,
    fence_clip,
    outside_hard_fence,
    outside_soft_fence,
    sanitize,
    saturate,
    valid_pose,
)

_T = TypeVar("_T")

SUSPECT_LAND_AFTER_S = 1.0
"""A frozen or disagreeing pose lands the drone this long after the suspect began (s: the first sample that
should have moved, pose_check.FreezeWatch.frozen_since; the disagreement's detection), where a pose that
is only late waits `pose_land_after`: a late pose may come back, a lying one says the capture cannot be
trusted, and the fence cannot hold without it.
The hover starts at `pose_timeout`; with a Tello's 2.8 s landing the drone is down about 4 s after the
pose froze (fault row `mocap_frozen_tello`)."""


class _Phase(enum.Enum):
    IDLE = "idle"  # built; nothing commanded yet (a sim drone may already be airborne)
    FLYING = "flying"  # after takeoff() or the first command: all rules enforced
    LAND_PENDING = "land_pending"  # land requested but not (yet) accepted: nothing but land retries sent
    LANDED = "landed"  # land accepted: nothing else is sent until a new takeoff()
    STOPPED = "stopped"  # emergency stop accepted: motors off


# ---- one drone ---------------------------------------------------------------------------------------------
class SafeDrone:
    """A hal.Drone that enforces the safety rules on the hal.Drone it wraps (see the module docstring).

    Args:
        drone_id: the mission's id of this drone (used in events).
        drone: the wrapped drone (hardware driver or simulator).
        poses: the motion-capture source; `body` names this drone's rigid body in it.
        clock: the mission clock (s); every age is measured with it.
        limits: the safety limits.
        log: the event log shared with the mission.
        background: run the wrapped drone's takeoff() and land() on worker threads (real drones, whose
            takeoff and land block for seconds); tick() collects the outcome. Off: inline (simulated).

    `landed` is True once a land() or emergency_stop() of the wrapped drone was accepted and until the next
    takeoff(); it starts False because the wrapper cannot know (a simulated drone may start airborne).
    """

    def __init__(
        self,
        drone_id: int,
        drone: Drone,
        poses: PoseSource,
        body: str,
        clock: Clock,
        limits: SafetyLimits,
        log: EventLog,
        background: bool = False,
    ) -> None:
        self.drone_id = drone_id
        self.background = background
        self._jobs = DroneJobs(drone_id)
        self._next_land_try = -math.inf
        self._link_down_while_landing = False
        self.takeoff_error: str | None = None
        """Why the wrapped drone's takeoff() failed (background jobs), None otherwise."""
        self.inner = drone
        self.own_timeout_s: float | None = (
            float(drone.own_timeout_s) if isinstance(drone, HoldsLastCommand) else None
        )
        """How long the wrapped drone flies its last command by itself (s; hal.HoldsLastCommand), None:
        it does not (a simulated drone that stops with its simulation). Bounds the climb (climb_cap)."""
        self.poses = poses
        self.body = body
        self.clock = clock
        self.limits = limits
        self.log = log
        self._lock = threading.RLock()
        self._phase = _Phase.IDLE
        self._episodes: set[str] = set()
        now = clock.now()
        self._active_since = now
        self._last_command_t = now
        self._climbing_t = -math.inf  # the last tick its telemetry showed the takeoff climb (mission s)
        self._last_pose: StampedPose | None = None
        self._freeze = FreezeWatch()  # identical samples under fresh stamps (pose_check)
        self._heights = HeightAgreement()  # pose z against the drone's own height telemetry (pose_check)
        self._disagree: tuple[float, str] | None = None  # (mission s, detail): the pose disagreed, latched
        self._obeys = False  # its last telemetry said it flies velocity commands (AIRBORNE): a pose must move
        self._floor_armed = False
        self._link_seen = False  # the drone reported link_alive since its activation
        self._abort_reason: str | None = None
        self._land_reason = ""  # why the pending land was asked for (shown by its retries)
        self._inner_thread: int | None = None
        self.last_command: np.ndarray = np.zeros(4)
        """The last command received by send_body_velocity (float (4,), as given; zeros if not numeric)."""
        self.last_sent: np.ndarray | None = None
        """The last velocity actually sent to the wrapped drone (body frame), None before the first."""

    # ---- state -----------------------------------------------------------------------------------------
    @property
    def phase(self) -> str:
        """'idle', 'flying', 'land_pending', 'landed' or 'stopped'."""
        return self._phase.value

    @property
    def landed(self) -> bool:
        """True once land/emergency stop was accepted by the wrapped drone (until the next takeoff)."""
        return self._phase in (_Phase.LANDED, _Phase.STOPPED)

    def in_inner_call(self) -> bool:
        """True if the calling thread is currently inside a call to the wrapped drone."""
        return self._inner_thread == threading.get_ident()

    def request_abort(self, reason: str) -> None:
        """Ask for a landing on the next send_body_velocity/tick (safe to call from a signal handler)."""
        self._abort_reason = reason

    # ---- hal.Drone -------------------------------------------------------------------------------------
    def connect(self) -> None:
        with self._lock:
            self._call(self.inner.connect)

    def state(self) -> DroneState:
        with self._lock:
            return self._call(self.inner.state)

    def takeoff(self) -> None:
        """Take off after the checks: battery >= min_battery_takeoff, a fresh pose, x/y inside the hard fence.

        Raises SafetyError (and logs) when a check fails; the wrapped drone is then not asked to take off.
        """
        with self._lock:
            now = self.clock.now()
            battery = float(self._call(self.inner.state).battery_pct)
            if not battery >= self.limits.min_battery_takeoff:  # also refuses NaN
                self._event(
                    now,
                    "battery_refuse_takeoff",
                    f"battery {battery:.1f} % < {self.limits.min_battery_takeoff:.1f} %",
                )
                raise SafetyError(
                    f"drone {self.drone_id}: takeoff refused, battery {battery:.1f} % "
                    f"< {self.limits.min_battery_takeoff:.1f} %"
                )
            sp = self._read_pose(now)
            if sp is None or now - sp.stamp > self.limits.pose_timeout:
                age = "never seen" if sp is None else f"{now - sp.stamp:.3f} s old"
                self._event(now, "pose_refuse_takeoff", f"pose of {self.body!r} {age}")
                raise SafetyError(f"drone {self.drone_id}: takeoff refused, pose of {self.body!r} {age}")
            faces = [f for f in outside_hard_fence(sp.pose.p, self.limits, check_floor=False) if f[1] in "xy"]
            if faces:
                where = np.round(sp.pose.p, 3).tolist()
                self._event(now, "fence_refuse_takeoff", f"at {where}, beyond hard fence {faces}")
                raise SafetyError(
                    f"drone {self.drone_id}: takeoff refused, at {where} outside the hard fence"
                )
            self._activate(now)  # before the call: if takeoff raises half-way, land_all still lands it
            self.takeoff_error = None
            if self.background:  # tick() collects the outcome; state().flying says when it is up
                self._event(now, "takeoff", f"battery {battery:.1f} % (on a worker thread)")
                self._start_job("takeoff", self.inner.takeoff, "takeoff")
                return
            self._call(self.inner.takeoff)
            self._last_command_t = self.clock.now()  # takeoff may block while climbing
            self._event(self.clock.now(), "takeoff", f"battery {battery:.1f} %")

    def land(self, reason: str = "land()") -> None:
        """Land now (no-op if already landed); re-raises the wrapped drone's error after logging it.

        With background jobs this starts the land and returns at once; tick() confirms it (`landed`)."""
        with self._lock:
            if self.landed:
                return
            err = self._do_land(self.clock.now(), reason)
            if err is not None:
                raise err

    def emergency_stop(self, reason: str = "emergency_stop()") -> None:
        """Motors off. Nothing is sent afterwards; the wrapped drone's error propagates."""
        with self._lock:
            if self._phase is not _Phase.STOPPED:
                self._phase = _Phase.LAND_PENDING  # whatever happens, no more velocity commands
            self._call(self.inner.emergency_stop)
            self._phase = _Phase.STOPPED
            self._abort_reason = None
            self._event(self.clock.now(), "emergency_stop", reason)

    def close(self, land_wait_s: float = 40.0) -> None:
        """Land if not landed (errors logged, not raised), then close the wrapped drone.

        With background jobs, waits for a land under way (at most `land_wait_s`, wall clock) first: closing
        the driver would end it. This is the end of a run, never the control loop."""
        with self._lock:
            if not self.landed:
                self._do_land(self.clock.now(), "close()")
        self._jobs.join(land_wait_s)
        with self._lock:
            self._poll_jobs(self.clock.now())
            self._call(self.inner.close)

    def send_body_velocity(self, V: np.ndarray) -> None:
        """Send V = [v_x, v_y, v_z, ω_z] (m/s, rad/s, body frame of this drone) through the safety rules.

        In order: drop after land; NaN/inf/bad shape -> zeros; saturation; stale pose -> zeros (and land
        once it is older than pose_land_after); outside the hard fence -> land; an upward v_z beyond
        climb_cap (a drone that flies its last command on by itself) -> reduced; outside the soft fence ->
        outward world components removed. The rules log and never raise; an error of the wrapped drone's
        own send_body_velocity propagates.
        """
        with self._lock:
            now = self.clock.now()
            if self._abort_reason is not None and self._phase is _Phase.FLYING:
                self._do_land(now, self._abort_reason)
            if self._phase in (_Phase.LANDED, _Phase.STOPPED, _Phase.LAND_PENDING):
                self._event_once(now, "command_after_land", f"command dropped: drone is {self.phase}")
                return
            if self._phase is _Phase.IDLE:
                self._activate(now)
            self._last_command_t = now
            self._end("command_timeout")

            cmd, problem = sanitize(V)
            self.last_command = self._raw_copy(V)
            if problem is None:
                self._end("invalid_command")
            else:
                self._event_once(now, "invalid_command", f"{problem}; sending zero velocity")
            cmd, changed = saturate(cmd, self.limits)
            if changed:
                self._event_once(now, "saturated", f"command {self.last_command.tolist()} -> {cmd.tolist()}")
            else:
                self._end("saturated")

            pose = self._check_pose(now, hover_now=False)
            if self._phase is not _Phase.FLYING:  # landed on a stale pose
                return
            if pose is None:
                self._send(np.zeros(4))
                return
            if self._check_hard_fence(now, pose):
                return
            cmd = self._limit_climb(now, cmd, pose)
            faces = outside_soft_fence(pose.p, self.limits)
            if faces:
                cmd, clipped = fence_clip(cmd, pose, self.limits)
                where = np.round(pose.p, 3).tolist()
                self._event_once(
                    now, "fence_soft", f"at {where}, beyond soft fence {faces}; clipped {clipped}"
                )
            else:
                self._end("fence_soft")
            self._send(cmd)

    # ---- periodic checks -------------------------------------------------------------------------------
    def tick(self) -> None:
        """Once per control period, command or not: stale pose, hard fence, link, battery, command watchdog.

        Also retries a land that the wrapped drone refused. Never raises an Exception (logs instead).
        """
        with self._lock:
            now = self.clock.now()
            self._poll_jobs(now)
            if self._abort_reason is not None and self._phase is _Phase.FLYING:
                self._do_land(now, self._abort_reason)
            if self._phase is _Phase.LAND_PENDING:
                self._tick_landing(now)
                return
            if self._phase is not _Phase.FLYING:
                return
            pose = self._check_pose(now, hover_now=True)
            if self._phase is not _Phase.FLYING:
                return
            if pose is not None and self._check_hard_fence(now, pose):
                return
            try:
                st = self._call(self.inner.state)
                battery, link_alive = float(st.battery_pct), bool(st.link_alive)
            except Exception as exc:
                self._event_once(now, "drone_error", f"state() raised {type(exc).__name__}: {exc}")
            else:
                self._end("drone_error")
                takeoff = self._jobs.get("takeoff")
                climbing = takeoff is not None and not takeoff.finished  # a resent takeoff starts from there
                if link_alive and st.phase == FlightPhase.GROUND and self._link_seen and not climbing:
                    # its own telemetry shows it down (auto-land, a land by someone else): stop commanding
                    self._event(now, "landed_by_drone", "telemetry shows the drone on the ground")
                    self._phase = _Phase.LANDED
                    return
                if link_alive and st.phase == FlightPhase.LANDING and self._link_seen:
                    # landing by itself (its auto-land, a low battery, `error Auto land`): it ignores rc, and
                    # its land is under way; the land job waits for the touchdown and sends nothing
                    self._event(now, "landing_by_drone", "the drone's driver reports it landing by itself")
                    self._do_land(now, "landing_by_drone")
                    return
                if st.phase == FlightPhase.TAKING_OFF:  # climbing by itself: it ignores rc, none is due
                    self._climbing_t = now
                if link_alive:
                    self._link_seen = True
                elif self._link_seen:  # up since takeoff, now down (a link never up is not "lost")
                    # the uplink may still work: hover now, land now, keep hovering and re-sending land
                    self._event_once(now, "link_lost", "drone reports its link lost: hover and land")
                    self._send_quietly(now, np.zeros(4))
                    self._do_land(now, "link_lost")
                    return
                self._obeys = link_alive and st.phase == FlightPhase.AIRBORNE
                self._check_heights(now, st)
                if battery < self.limits.land_battery:
                    self._safety_land(
                        now, "battery_land", f"battery {battery:.1f} % < {self.limits.land_battery:.1f} %"
                    )
                    return
            if now - self._last_command_t > self.limits.command_timeout:  # every tick: a driver reads
                # silence as a dead loop. A fault only once the climb is over: the event counts from then
                silent = now - max(self._last_command_t, self._climbing_t)
                if silent > self.limits.command_timeout:
                    self._event_once(now, "command_timeout", f"no command for {silent:.3f} s: zero velocity")
                self._send_quietly(now, np.zeros(4))

    # ---- internals -------------------------------------------------------------------------------------
    @staticmethod
    def _raw_copy(V: object) -> np.ndarray:
        try:
            return np.array(V, dtype=float).reshape(-1).copy()
        except (TypeError, ValueError):
            return np.zeros(4)

    def _activate(self, now: float) -> None:
        self._phase = _Phase.FLYING
        self._episodes.clear()
        self._active_since = now
        self._last_command_t = now
        self._climbing_t = -math.inf
        self._floor_armed = False
        self._link_seen = False
        self._freeze.reset()
        self._heights.reset()
        self._disagree = None
        self._obeys = False

    def _check_pose(self, now: float, hover_now: bool) -> Pose | None:
        """The fresh pose, or None when stale (hover: zeros sent once if hover_now; land when too old).

        Never seen counts as stale at once (no fence without a pose), aged from the activation time.
        """
        sp = self._read_pose(now)
        if sp is None:
            age = now - self._active_since
            seen, stale = f"never seen ({age:.3f} s since takeoff/first command)", True
        else:
            age = now - sp.stamp
            seen, stale = f"{age:.3f} s old", age > self.limits.pose_timeout
        if stale:
            opened = self._event_once(now, "pose_stale_hover", f"pose of {self.body!r} {seen}: zero velocity")
            if age > self.limits.pose_land_after:
                self._safety_land(now, "pose_stale_land", f"pose of {self.body!r} {seen}")
            elif opened and hover_now:
                self._send_quietly(now, np.zeros(4))
            return None
        assert sp is not None  # not stale: seen
        self._end("pose_stale_hover")
        if self._suspect(now, hover_now):
            return None
        if sp.pose.p[2] >= self.limits.fence_lo[2]:
            self._floor_armed = True
        return sp.pose

    def _suspect(self, now: float, hover_now: bool) -> bool:
        """A fresh-looking pose that is frozen or disagrees with the drone's own height (pose_check): hover
        (zeros sent once if hover_now), land SUSPECT_LAND_AFTER_S after the suspect began. True if so."""
        since = self._freeze.frozen_since
        kind: SafetyKind
        if since is not None and now - since > self.limits.pose_timeout:
            onset, kind = since, "pose_frozen"
            detail = (
                f"pose of {self.body!r} identical for {now - since:.3f} s under fresh stamps while the drone "
                "was commanded to move: zero velocity"
            )
        elif self._disagree is not None:
            (onset, detail), kind = self._disagree, "pose_disagrees"
        else:
            self._end("pose_frozen")
            return False
        opened = self._event_once(now, kind, detail)
        if now - onset >= SUSPECT_LAND_AFTER_S:
            self._safety_land(now, "pose_stale_land", f"{kind}: {detail.removesuffix(': zero velocity')}")
        elif opened and hover_now:
            self._send_quietly(now, np.zeros(4))
        return True

    def _check_heights(self, now: float, st: DroneState) -> None:
        """Compare the fresh pose's z with the drone's own height over pose_check.HEIGHT_WINDOW_S while it is
        airborne and its telemetry alive; a disagreement latches (`_disagree`) until the next takeoff."""
        sp = self._last_pose
        fresh = sp is not None and now - sp.stamp <= self.limits.pose_timeout
        if not (fresh and st.link_alive and st.phase == FlightPhase.AIRBORNE) or self._disagree is not None:
            self._heights.reset()
            return
        assert sp is not None  # fresh
        d = self._heights.sample(now, float(sp.pose.p[2]), float(st.height_m))
        if d is not None:
            self._disagree = (
                now,
                f"pose of {self.body!r}: its z changed {d:+.2f} m more than the drone's own height over "
                f"{self._heights.window_s:g} s (bound ±{self._heights.bound_m:g} m): zero velocity",
            )

    def _check_hard_fence(self, now: float, pose: Pose) -> bool:
        """Land if outside the hard fence (its floor only once the drone has been above the soft floor)."""
        faces = outside_hard_fence(pose.p, self.limits, check_floor=self._floor_armed)
        if not faces:
            return False
        where = np.round(pose.p, 3).tolist()
        self._safety_land(now, "fence_hard_land", f"at {where}, beyond hard fence {faces}")
        return True

    # ---- plumbing --------------------------------------------------------------------------------------
    def _limit_climb(self, now: float, cmd: np.ndarray, pose: Pose) -> np.ndarray:
        """cmd with v_z at most climb_cap at the pose's height, for a drone that flies its last command on by
        itself (own_timeout_s); `climb_limited` once per episode."""
        if self.own_timeout_s is None:
            return cmd
        z = float(pose.p[2])
        cap = climb_cap(z, self.limits, self.own_timeout_s)
        if cmd[2] <= cap:
            self._end("climb_limited")
            return cmd
        detail = (
            f"v_z {cmd[2]:.3f} -> {cap:.3f} m/s at z {z:.2f} m (ceiling {self.limits.fence_hi[2]:g} m, "
            f"the drone's own timeout {self.own_timeout_s:g} s)"
        )
        self._event_once(now, "climb_limited", detail)
        out = cmd.copy()
        out[2] = cap
        return out

    def _call(self, fn: Callable[..., _T], *args: Any) -> _T:
        """Call the wrapped drone, remembering which thread is inside it (for signal handlers)."""
        prev = self._inner_thread
        self._inner_thread = threading.get_ident()
        try:
            return fn(*args)
        finally:
            self._inner_thread = prev

    def _event(self, now: float, kind: SafetyKind, detail: str) -> None:
        self.log.record(now, self.drone_id, kind, detail)

    def _event_once(self, now: float, kind: SafetyKind, detail: str) -> bool:
        """Log `kind` if its episode is not already open; True if this call opened it."""
        if kind in self._episodes:
            return False
        self._episodes.add(kind)
        self._event(now, kind, detail)
        return True

    def _end(self, kind: SafetyKind) -> None:
        self._episodes.discard(kind)

    def _send(self, V: np.ndarray) -> None:
        out = np.array(V, dtype=float)
        self._call(self.inner.send_body_velocity, out.copy())
        self.last_sent = out

    def _send_quietly(self, now: float, V: np.ndarray) -> None:
        try:
            self._send(V)
        except Exception as exc:
            self._event_once(now, "drone_error", f"send_body_velocity raised {type(exc).__name__}: {exc}")

    def _read_pose(self, now: float) -> StampedPose | None:
        """Latest valid pose from the source (remembered), or the last valid one; None if never seen.

        A pose stamped ahead of `now` (delay_compensation.stamp_refusal: another clock, or forged) is not
        taken: remembered, it would read as fresh for as long as its stamp is ahead, and the stale-pose
        rules would never hover or land the drone (`pose_error`, once per episode)."""
        try:
            sp = self.poses.latest(self.body)
        except Exception as exc:
            self._event_once(now, "pose_error", f"PoseSource.latest raised {type(exc).__name__}: {exc}")
            return self._last_pose
        if valid_pose(sp):
            assert sp is not None  # valid_pose: a StampedPose
            if stamp_refusal(sp.stamp, now, "pose") is not None:  # finite (valid_pose): ahead of now
                ahead = f"stamped {sp.stamp - now:.3g} s ahead of the clock ({sp.stamp!r} at {now:.3f})"
                self._event_once(now, "pose_error", f"pose of {self.body!r} {ahead}: not used")
                return self._last_pose
            self._last_pose = sp
            # a command is evidence of motion only while the drone obeys it: a Tello ignores rc in its
            # takeoff climb and the hover before its `ok` (8.7 s recorded), where a noise-free emulator's
            # pose stands still
            # (and only a command recent enough to be flown: after a stalled loop the driver hovers)
            flown = self._obeys and now - self._last_command_t <= self.limits.command_timeout
            self._freeze.sample(sp.stamp, sp.pose.as_vector(), self.last_sent if flown else None)
        self._end("pose_error")
        return self._last_pose

    # ---- landing sequence ------------------------------------------------------------------------------
    def _safety_land(self, now: float, kind: SafetyKind, detail: str) -> None:
        """Land because of a rule; a refusal of the wrapped drone is logged and retried by tick()."""
        self._event_once(now, kind, detail)
        if self.landed:
            return
        if self._do_land(now, kind) is not None:
            self._send_quietly(now, np.zeros(4))  # best effort: at least hover until land is accepted

    def _do_land(self, now: float, reason: str, retry: bool = False) -> Exception | None:
        """Send land to the wrapped drone; returns its Exception (logged once per episode) or None.

        Background jobs: starts the land on a worker thread unless one is under way, returns None."""
        self._phase = _Phase.LAND_PENDING  # from here on, no velocity reaches the wrapped drone
        if not retry:
            self._land_reason = reason
        if self.background:
            self._poll_jobs(now)
            job = self._jobs.get("land")
            if not self.landed and (job is None or job.finished):
                self._next_land_try = now + self.limits.land_retry_s
                self._start_job("land", self.inner.land, reason)
            return None
        try:
            self._call(self.inner.land)
        except Exception as exc:
            self._event_once(now, "land_failed", f"{reason}: land() raised {type(exc).__name__}: {exc}")
            self._next_land_try = now + self.limits.land_retry_s
            return exc
        self._confirm_landed(now, "", reason)
        return None

    def _confirm_landed(self, now: float, how: str, reason: str | None = None) -> None:
        """LANDED; the event names the land that worked (`reason`, default the first) and, if not
        land() itself, what confirmed it (`how`)."""
        self._phase = _Phase.LANDED
        self._abort_reason = None
        self._end("land_failed")
        why = self._land_reason if reason is None else reason
        self._event(now, "land", f"{why}: {how}" if how else why)

    def _tick_landing(self, now: float) -> None:
        """A land is pending: confirm it (telemetry, motion capture), hover while the link is silent (the
        uplink may still work), re-send land every land_retry_s. Never waits for the drone."""
        takeoff = self._jobs.get("takeoff")
        climbing = takeoff is not None and not takeoff.finished  # still on the floor: nothing to confirm
        link = False
        try:
            st = self._call(self.inner.state)
            link = bool(st.link_alive)
            if link and st.phase == FlightPhase.GROUND and not climbing:
                self._confirm_landed(now, "telemetry shows it on the ground")
                return
        except Exception as exc:
            self._event_once(now, "drone_error", f"state() raised {type(exc).__name__}: {exc}")
        sp = self._read_pose(now)
        if (
            sp is not None
            and not climbing
            and now - sp.stamp <= self.limits.pose_timeout
            and sp.pose.p[2] <= self.limits.landed_height
        ):
            self._confirm_landed(now, f"motion capture shows it down (z {sp.pose.p[2]:.3f} m)")
            return
        if sp is not None:  # the rules keep running on the last known pose (events only: it is landing)
            faces = outside_hard_fence(sp.pose.p, self.limits, check_floor=self._floor_armed)
            if faces:
                where = np.round(sp.pose.p, 3).tolist()
                self._event_once(now, "fence_hard_land", f"at {where}, beyond hard fence {faces} (landing)")
        if not link:
            self._send_quietly(now, np.zeros(4))
        elif self._link_down_while_landing:  # the link is back: a land sent now gets an answer
            self._next_land_try = now
        self._link_down_while_landing = not link
        job = self._jobs.get("land")
        if (job is None or job.finished) and not climbing and now >= self._next_land_try:
            self._do_land(now, f"retry ({self._land_reason})", retry=True)

    def _start_job(self, kind: str, fn: Callable[[], None], reason: str) -> None:
        """Run fn (the wrapped drone's takeoff or land) on a worker thread; _poll_jobs collects it."""
        self._jobs.start(kind, fn, reason, self.clock.now())

    def _poll_jobs(self, now: float) -> None:
        """Collect finished takeoff/land jobs: confirm a landing, log a failure (retried by tick)."""
        for job in self._jobs.collect():
            kind, err = job.kind, job.error
            why = "" if err is None else f"{type(err).__name__}: {err}"
            if kind == "takeoff":
                self._last_command_t = max(self._last_command_t, now)
                if err is not None:
                    self.takeoff_error = why
                    self._event(now, "takeoff_failed", why)
                    if self._phase is _Phase.FLYING:
                        self._do_land(now, "takeoff_failed")
            elif self._phase is _Phase.LAND_PENDING:
                takeoff = self._jobs.get("takeoff")
                if takeoff is not None and not takeoff.finished:  # returned before the drone was up:
                    self._next_land_try = now  # no proof of anything; sent again once the takeoff ends
                elif err is None:
                    self._confirm_landed(now, "", job.reason)
                else:
                    self._event_once(now, "land_failed", f"{job.reason}: land() raised {why}")
                    self._next_land_try = now + self.limits.land_retry_s
