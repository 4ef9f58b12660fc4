"""Flies one mode of an assembled fleet: take off, tick, record, land (DESIGN §1–2, §7).

`run_mode` flies an assembled fleet (flightstack.runtime.fleet; the flight, flightstack.runtime.flight,
assembles and closes it) and is cut into its parts: `take_off`, `pursuit_tick` (one control period),
`record_tick` (flightstack.runtime.tick_record, from a declared field list), `_land_everything` and
`finish_recording`. It flies in lock-step: each
tick the target driver (sim_lab) commands the ground robot, the safety supervisor checks every drone,
all agents run phase 1, then all run phase 2, then the backend's clock advances by dt. Before the loop
every drone takes off (bounded wait); after it, whatever ended it (end of mission, a signal, an operator
abort, an exception in any agent), every drone is landed and the recording is returned with what was
flown. A state that diverges (flightstack.runtime.divergence, checked once per tick or compiled chunk)
ends the run the same way, with the error "diverged at t = … s (drone N, quantity …)".

On real drones nothing waits for a drone on the control thread: takeoffs and landings run on
worker threads (flightstack.safety, `background`), and the safety tick, the operator's abort and the
backend's heartbeat (the guardian process) keep running while they do, also during takeoff and landing.
Signals (SIGINT, SIGTERM, SIGHUP, SIGQUIT, SIGTSTP) land every drone; a repeated one is ignored.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol, TypeVar

from flightstack.comms.bus import OperatorChannel
from flightstack.events import Event, RunKind, end_kind
from flightstack.hal import StreamCounting
from flightstack.paper.geometry import compose
from flightstack.recording.timeseries import Recording
from flightstack.runtime.divergence import DivergedError, check_rows
from flightstack.runtime.fleet import (
    Fleet,
    OperatorAbortError,
    SafetyTickTimer,
    StatusPublisher,
    check_operator,
    make_agents,
    safety_limits,
    signal_guard,
)
from flightstack.runtime.phases import (
    LAND_TIMEOUT_S,
    POSE_WAIT_S,
    TAKEOFF_TIMEOUT_S,
    advance_until,
    settle_virtual_landing,
)
from flightstack.runtime.taps import TapSet, TickTap
from flightstack.runtime.tick_record import TickBook, record_tick
from flightstack.safety import SafeDrone

__all__ = [  # run_mode and its parts here; the fleet's parts re-exported from flightstack.runtime.fleet
    "OperatorAbortError",
    "SafetyTickTimer",
    "StatusPublisher",
    "check_operator",
    "finish_recording",
    "make_agents",
    "pursuit_tick",
    "run_mode",
    "run_procedure",
    "safety_limits",
    "take_off",
]

_log = logging.getLogger(__name__)


class ChunkLoop(Protocol):
    """A rig's faster way to fly runs of ticks (the ideal rig's compiled loop,
    flightstack.sim_backend.compiled_loop): `run` flies ticks k0..k1-1 into `rec` and returns the first
    tick it did not fly; `ready` says whether the next tick may be flown by it."""

    chunk: int
    chunks: int
    compiled_ticks: int

    def ready(self, book: TickBook) -> bool: ...

    def run(self, rec: Recording, k0: int, k1: int) -> int: ...


def run_mode(
    f: Fleet,
    progress: Callable[[int], None] | None = None,
    *,
    writer: Any = None,
    taps: Sequence[TickTap] = (),
    plan_loop: Callable[[Fleet], ChunkLoop | None] | None = None,
) -> Recording:
    """Fly the fleet's mode for its n_ticks of pursuit (f.loop); never leaves a drone flying.

    writer: a flightstack.recording.run_dir mode writer that appends the recording to disk as the run goes.
    On a simulated clock with a network bus, phase 2 waits for the neighbours' messages of the same tick
    (`bus.zenoh.lockstep_timeout_s`), so the result equals the in-process bus's.
    plan_loop: the rig's chunked loop for this fleet, if it has one (None: every tick through the Agents,
    the reference path; the compiled loop's recordings are bit-identical).
    taps: observers told after each recorded tick or chunk (live viewer, live export;
    flightstack.runtime.taps); one that raises is switched off, the flight goes on."""
    mode, dt, n_ticks = f.mode, f.loop.dt_s, f.loop.n_ticks
    rec = Recording.empty(mode, f.ids, n_ticks)
    book = TickBook.of(mode, f.ids)
    book.video_at_start = stream_counts(f)
    observers = TapSet(taps)
    observers.start(f, rec)
    wall0 = time.perf_counter()
    reason = "mission complete"
    signals = signal_guard(f.supervisor)
    signals.__enter__()
    try:
        take_off(f)
        t0 = f.clock.now()
        loop = plan_loop(f) if plan_loop is not None else None
        k = 0
        w_prev = math.nan  # wall time (perf_counter, s) of the last Python tick's start: loop health
        while k < n_ticks:
            if loop is not None and k > 0 and loop.ready(book):  # tick 0 in Python: its events
                k_new = loop.run(rec, k, min(n_ticks, k + loop.chunk))
                w_prev = math.nan  # the next Python tick's period would span the chunk
                if k_new > k:
                    if writer is not None:
                        writer.append(rec, k_new)
                    check_rows(rec, k, k_new, f.backend.simulated)  # DivergedError ends the run
                    if observers:
                        observers.on_tick(f, rec, k_new)
                    f.status.maybe_publish(f.clock.now(), k_new - 1, f.agents)
                    if progress is not None:
                        progress(k_new - k)
                    k = k_new
                    continue
            t = f.clock.now()
            w_start = time.perf_counter()
            ended = pursuit_tick(f, t, t - t0, rec)
            if ended is not None:
                reason = ended
                break
            record_tick(rec, k, t, f.agents, f.backend.truth(), book)
            rec.loop_compute[k] = time.perf_counter() - w_start
            rec.loop_period[k] = w_start - w_prev
            w_prev = w_start
            if writer is not None:
                writer.append(rec, k + 1)
            check_rows(rec, k, k + 1, f.backend.simulated)  # DivergedError ends the run
            if observers:
                observers.on_tick(f, rec, k + 1)
            f.status.maybe_publish(t, k, f.agents)
            if progress is not None:
                progress(1)
            f.clock.sleep_until(t + dt)
            k += 1
        if loop is not None and loop.chunks:
            facts = {
                "ticks": loop.compiled_ticks,
                "chunks": loop.chunks,
                "python_ticks": k - loop.compiled_ticks,
            }
            rec.events.append(Event(f.clock.now(), None, "compiled loop", facts=facts).record(mode))
    except KeyboardInterrupt:
        rec.interrupted = True
        reason = "interrupted"
    except OperatorAbortError as exc:
        rec.error = f"operator abort: {exc}"
        reason = "operator abort"
    except DivergedError as exc:  # the state left every bound: land, keep what was recorded
        rec.error = str(exc)
        reason = "diverged"
    except Exception as exc:  # an exception in any agent: land everyone, keep the data, report
        rec.error = f"{type(exc).__name__}: {exc}"
        reason = f"exception: {rec.error}"
    finally:
        # the recording is closed with every flown tick even if landing or its facts fail (or a second
        # Ctrl-C comes where no supervisor guards the signals): the error still propagates
        try:
            if f.supervisor is not None:  # a signal from here on must not interrupt landing or closing
                f.supervisor.ignore_signals(f"the run's end ({reason})")
            end = Event(f.clock.now(), None, end_kind(reason), facts={"reason": reason})
            rec.events.append(end.record(mode))
            if writer is not None:
                writer.event(rec.events[-1])
            _land_everything(f, reason, dt)
            with contextlib.suppress(Exception):  # `status` and `guard` see the drones down before we leave
                f.status.maybe_publish(f.clock.now(), rec.ticks_done, f.agents, force=True)
        finally:
            signals.__exit__(None, None, None)
            try:
                finish_recording(f, rec, book, time.perf_counter() - wall0)
            finally:
                if writer is not None:
                    writer.close(rec)
                observers.close(rec)
    return rec if rec.ticks_done == n_ticks and not rec.interrupted else rec.truncated()


_R = TypeVar("_R")
CLOCK_EPS_S = 1e-9
"""A virtual clock stops within rounding of the time asked for (s): closer than this counts as there."""


class EveryoneLandedError(RuntimeError):
    """The safety layer landed every drone while a procedure flew (a stale pose, the fence, the battery)."""


class SafePause:
    """`pause(seconds)` for a procedure flown instead of pursuit (`run_procedure`): waits on the fleet's
    clock in steps of at most one control period, and once per period ticks the safety layer and the
    guardian's heartbeat and obeys the operator's abort, as a pursuit tick does. Raises
    OperatorAbortError, EveryoneLandedError, or the heartbeat's error; the caller's `finally` lands."""

    def __init__(self, f: Fleet) -> None:
        self.f = f
        self._next_tick = f.clock.now()

    def tick_if_due(self) -> None:
        """The safety tick, the operator's abort and the landed check, when a control period has passed."""
        f = self.f
        now = f.clock.now()
        if now < self._next_tick - CLOCK_EPS_S:
            return
        self._next_tick = now + f.loop.dt_s
        f.ticker.tick()
        if f.safe and all(s.landed for s in f.safe.values()):
            raise EveryoneLandedError("the safety layer landed every drone")
        check_operator(f.bus)

    def __call__(self, seconds: float) -> None:
        f = self.f
        end = f.clock.now() + max(0.0, seconds)
        while True:
            self.tick_if_due()
            if f.clock.now() >= end - CLOCK_EPS_S:
                return
            f.clock.sleep_until(min(end, self._next_tick))


def run_procedure(f: Fleet, procedure: Callable[[Fleet, SafePause], _R]) -> _R:
    """Fly `procedure(f, pause)` instead of pursuit (a calibration's pattern): take every drone off as
    `run_mode` does, run it (it commands `f.drones`, the safety-wrapped drones, and waits only through
    `pause`, which keeps the safety layer, the heartbeat and the operator's abort going), then land every
    drone whatever ended it (its return, Ctrl-C or a signal, an abort, an exception: re-raised after the
    landing). Returns what the procedure returned."""
    signals = signal_guard(f.supervisor)
    signals.__enter__()
    reason = "procedure complete"
    try:
        take_off(f)
        return procedure(f, SafePause(f))
    except KeyboardInterrupt:
        reason = "interrupted"
        raise
    except BaseException as exc:
        reason = f"exception: {type(exc).__name__}: {exc}"
        raise
    finally:
        if f.supervisor is not None:  # a signal from here on must not interrupt landing or closing
            f.supervisor.ignore_signals(f"the procedure's end ({reason})")
        _land_everything(f, reason, f.loop.dt_s)
        signals.__exit__(None, None, None)


def wait_for_poses(f: Fleet) -> None:
    """Wait, bounded by POSE_WAIT_S, until every safety-wrapped drone's own pose is fresh.

    The pose source reports a body as None while its newest sample is older than its stale bound (0.1 s
    for motion capture), and SafeDrone.takeoff refuses without a fresh pose. A stream that has only just
    connected, or a single late frame on a loaded computer, must not abort a mission; a body that stays
    unseen for POSE_WAIT_S still does (RuntimeError naming the bodies), before any drone has left the
    ground."""
    if not f.safe:
        return

    def fresh(s: SafeDrone) -> bool:
        try:
            return s.poses.latest(s.body) is not None
        except Exception:  # a pose source that raises has no pose: counted as missing, never a crash here
            return False

    def missing() -> list[str]:
        return [s.body for s in f.safe.values() if not fresh(s)]

    if not advance_until(f.clock, lambda: not missing(), POSE_WAIT_S, f.loop.dt_s, f.ticker.tick):
        raise RuntimeError(
            f"no fresh motion-capture pose of {missing()} within {POSE_WAIT_S:g} s; nothing took off"
        )


def take_off(f: Fleet) -> None:
    """Wait for every agent on the bus (network bus), take every drone off together and wait, bounded by
    TAKEOFF_TIMEOUT_S, until each says it is airborne; then start each estimate from the drone's own
    motion-capture pose (rigs with motion capture). Raises RuntimeError with the reason."""
    clock, drones, wait_s = f.clock, f.drones, f.loop.start_timeout_s
    if wait_s is not None:  # a network bus: every agent must be on it
        missing = f.bus.wait_alive(set(f.everyone), wait_s)
        if missing:
            raise RuntimeError(f"agents {sorted(missing)} not on the bus after {wait_s:g} s")
    for d in drones.values():
        d.connect()
    wait_for_poses(f)
    if f.target is not None:  # the robot must move as commanded before anything flies (motion_check)
        try:
            moved = f.target.check_moves(clock, f.loop.dt_s, f.ticker.tick)
        except RuntimeError as exc:
            f.log.record(clock.now(), None, "robot_refuse_takeoff", str(exc))
            raise
        if moved is not None:
            f.log.record(
                clock.now(),
                None,
                "robot_moved",
                f"nudged {moved.commanded_m:+.3f} m: {moved.along_m:+.3f} m along, {moved.across_m:+.3f} m "
                "sideways",
            )
        try:  # a robot that is a device starts its law where it stands (the last mode left it there)
            phase = f.target.start_where_it_is()
        except RuntimeError as exc:
            f.log.record(clock.now(), None, "robot_refuse_takeoff", str(exc))
            raise
        if phase is not None:
            t0, dist, dth = phase
            where = f"{dist:.3f} m and {dth:+.3f} rad from the path"
            f.log.record(
                clock.now(), None, "robot_law_start", f"the law starts at lap time {t0:.2f} s ({where})"
            )
            f.ticker.tick()  # the guardian's heartbeat: the search for the lap time held this thread
        wait_for_poses(f)  # again: the robot's check took seconds, and takeoff refuses a pose stale now
    for d in drones.values():  # on real drones each returns at once: they climb together
        d.takeoff()

    def during_takeoff() -> None:
        f.ticker.tick()
        now = clock.now()
        for a in f.agents:  # the poses the first frames of the pursuit were captured from
            a.record_own_pose(now)
        check_operator(f.bus)  # an abort is obeyed during the takeoff too
        failed = {i: s.takeoff_error for i, s in f.safe.items() if s.takeoff_error}
        if failed:
            raise RuntimeError(f"takeoff failed: {failed}")

    def airborne() -> bool:
        return all(d.state().flying for d in drones.values())

    if not advance_until(clock, airborne, TAKEOFF_TIMEOUT_S, f.loop.dt_s, during_takeoff):
        raise RuntimeError(f"takeoff: not every drone airborne after {TAKEOFF_TIMEOUT_S} s")
    if f.loop.reset_estimates:
        for a in f.agents:  # the target's pose is unknown: assume it sits at the desired relative pose
            own = a.poses.latest(a.cfg.body_name)
            if own is None:
                raise RuntimeError(f"no motion-capture pose for {a.cfg.body_name} at pursuit start")
            a.reset_estimate(compose(own.pose, a.cfg.g_d), clock.now())
            a.seed_own_pose(own)


def pursuit_tick(f: Fleet, t: float, t_pursuit: float, rec: Recording) -> str | None:
    """One control period at mission time t (s; t_pursuit since pursuit began): the robot's command, the
    safety tick, the operator's abort, phase 1 (sense, estimate, publish) of every agent, the lock-step
    wait, the supervisor's visibility rule, phase 2 (fuse, control, act). Returns why the run ends now
    (every drone landed by the safety layer; the robot's pose not believed, `rec.error` set), or None."""
    if f.target is not None:
        f.target.tick(t_pursuit)
        if f.target.suspect is not None:  # the law cannot drive a robot it cannot see: end with an error
            rec.error = f.target.suspect
            return "robot pose suspect"
    f.ticker.tick()
    if f.safe and all(s.landed for s in f.safe.values()):  # the safety layer landed everyone
        return "every drone landed"
    check_operator(f.bus)
    for a in f.agents:
        a.sense_and_publish(t)
    wait_s = f.loop.lockstep_timeout_s
    if f.loop.lockstep and wait_s is not None:  # phase 2 needs every neighbour's message of this tick
        # own messages too: Zenoh loops them back asynchronously
        late = f.bus.wait_for_stamp(set(f.everyone), t, wait_s)
        if late:
            rec.events.append(
                Event(t, None, "lock-step wait timed out", facts={"late": sorted(late)}).record(f.mode)
            )
    if f.supervisor is not None:
        hold = f.supervisor.update_visibility({a.cfg.drone_id: a.last.visible for a in f.agents})
        for a in f.agents:
            a.hold = hold
    for a in f.agents:
        a.fuse_control_act(t)
    return None


def finish_recording(f: Fleet, rec: Recording, book: TickBook, wall_seconds: float) -> None:
    """After landing: the safety tick's timing, each drone's own word on whether it is down, the safety
    events, the bus's drop counts and presence changes, vision rejections and the true errors."""
    mode, now = f.mode, f.clock.now
    rec.events.append(Event(now(), None, "safety tick", facts=f.ticker.summary()).record(mode))
    for i in f.ids:
        st = f.backend.drone(i).state()
        fate: RunKind = "landed" if not st.flying else "NOT LANDED"
        # telemetry_alive False: height_m is the last one received
        facts = {"height_m": st.height_m, "telemetry_alive": st.link_alive}
        rec.events.append(Event(now(), i, fate, facts=facts).record(mode))
    rec.events.extend(e.record(mode) for e in f.log.events)
    rec.wall_seconds = wall_seconds
    rec.bus_dropped = dict(f.bus.dropped)
    rec.events.extend(p.record(mode) for p in f.bus.presence_events)  # detail of a second session: the report
    rec.vision_rejections = book.vision_rejections()
    rec.vision_gate = book.vision_gate()
    rec.video_counts = {
        i: {k: v - book.video_at_start.get(i, {}).get(k, 0) for k, v in c.items()}
        for i, c in stream_counts(f).items()
    }
    rec.fill_true_errors(f.g_d)


def stream_counts(f: Fleet) -> dict[str, dict[str, int]]:
    """Per drone whose camera counts its stream (hal.StreamCounting), its counts so far (an agent's
    backend lives for the whole flight: a mode's counts are the difference from its start). Never
    raises: it runs on the way to writing the recording, and counts are only a report."""
    out: dict[str, dict[str, int]] = {}
    for i in f.ids:
        try:
            cam = f.backend.camera(i)
            if isinstance(cam, StreamCounting):
                out[str(i)] = dict(cam.stream_counts())
        except Exception as exc:  # a camera that failed to start: no counts, the recording goes on
            _log.warning("drone %s: no video counts (%s: %s)", i, type(exc).__name__, exc)
    return out


def _land_everything(f: Fleet, reason: str, dt: float) -> None:
    """Land every drone and stop the robot; on a virtual clock also let the landing complete.

    Real drones land in parallel on worker threads while this keeps ticking the safety layer (it confirms
    each landing, hovers and re-sends land on a silent link) and the guardian's heartbeat, bounded by
    LAND_TIMEOUT_S; only then are the drivers closed (closing lands whatever is still up)."""
    backend, clock, supervisor = f.backend, f.clock, f.supervisor
    try:
        if f.target is not None:
            f.target.stop()
    except Exception as exc:  # the drones land regardless
        _log.error("stopping the robot failed: %s", exc)
    if supervisor is not None:
        supervisor.land_all(reason)
        if any(s.background for s in supervisor.drones.values()):
            advance_until(
                clock,
                lambda: all(s.landed for s in supervisor.drones.values()),
                LAND_TIMEOUT_S,
                dt,
                lambda: _quietly(f.ticker.tick, f.bus),
            )
    backend.close()  # lands any drone the supervisor did not reach
    if backend.simulated:  # let the virtual landing finish: each drone's own state says it is down
        settle_virtual_landing(backend, list(f.drones), dt)


def _quietly(tick: Callable[[bool], None], bus: OperatorChannel) -> None:
    """One tick while landing; an abort arriving now is already being obeyed (drained; the bus acks it)."""
    tick(False)
    with contextlib.suppress(OperatorAbortError):
        check_operator(bus)
