"""The landing sequence of a SafeDrone and the plumbing it shares with the rules (DESIGN §7).

`_LandingSequence` is the base class of `SafeDrone` (flightstack/safety/drone.py, whose docstring has the
rules and the event kinds); SafeDrone's __init__ sets every attribute declared here. It holds:
    - the plumbing: calls to the wrapped drone (remembering which thread is inside one, for signal
      handlers), sending a body velocity V = [v_x, v_y, v_z, ω_z] (m/s, rad/s, body frame), one
      `SafetyEvent` per episode, reading the latest valid pose (world frame Σw, metres) from the PoseSource;
    - the landing sequence: a land puts the drone in LAND_PENDING (no velocity reaches the wrapped drone any
      more); it is re-sent every `land_retry_s` until confirmed by the wrapped drone's land() returning, by
      its telemetry (phase ground) or by motion capture (z ≤ `landed_height`), while the fence rule keeps
      logging on the last known pose and a silent link gets zero velocity (hover);
    - the background workers (hardware, `background` on): the wrapped drone's takeoff() and land() run on a
      worker thread each (`_Job`, flightstack/safety/phases.py); tick() collects their outcome.
Times are mission-clock seconds.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from flightstack.events import SafetyKind
from flightstack.hal import Clock, Drone, FlightPhase, PoseSource, StampedPose
from flightstack.safety.phases import _Job, _Phase
from flightstack.safety.rules import EventLog, SafetyLimits, _valid_pose, outside_hard_fence

_T = TypeVar("_T")


class _LandingSequence:
    """Base of SafeDrone: calls to the wrapped drone, events, pose reading and the landing sequence.

    Every attribute below is set by SafeDrone.__init__ (flightstack/safety/drone.py).
    """

    drone_id: int
    background: bool
    inner: Drone
    poses: PoseSource
    body: str
    clock: Clock
    limits: SafetyLimits
    log: EventLog
    takeoff_error: str | None
    last_sent: np.ndarray | None
    _jobs: dict[str, _Job]
    _next_land_try: float
    _link_down_while_landing: bool
    _phase: _Phase
    _episodes: set[str]
    _last_command_t: float
    _last_pose: StampedPose | None
    _floor_armed: bool
    _abort_reason: str | None
    _land_reason: str
    _inner_thread: int | None

    @property
    def landed(self) -> bool:
        """True once land/emergency stop was accepted by the wrapped drone (until the next takeoff)."""
        return self._phase in (_Phase.LANDED, _Phase.STOPPED)

    # ---- plumbing --------------------------------------------------------------------------------------
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

    def _end(self, kind: str) -> None:
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
        """Latest valid pose from the source (remembered), or the last valid one; None if never seen."""
        try:
            sp = self.poses.latest(self.body)
        except Exception as exc:
            self._event_once(now, "pose_error", f"PoseSource.latest raised {type(exc).__name__}: {exc}")
            return self._last_pose
        self._end("pose_error")
        if _valid_pose(sp):
            self._last_pose = sp
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
        job = _Job(kind, reason, self.clock.now())

        def run() -> None:
            try:
                fn()
            except BaseException as exc:  # collected by _poll_jobs on the control thread
                job.error = exc
            finally:
                job.finished = True

        job.thread = threading.Thread(target=run, name=f"{kind}-drone{self.drone_id}", daemon=True)
        self._jobs[kind] = job
        job.thread.start()

    def _poll_jobs(self, now: float) -> None:
        """Collect finished takeoff/land jobs: confirm a landing, log a failure (retried by tick)."""
        for kind, job in list(self._jobs.items()):
            if not job.finished or job.collected:
                continue
            job.collected = True
            err = job.error
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
