"""Builds a backend, agents, safety and a bus from a mission and drives the clock (DESIGN §1–2, §7).

`run_mode` flies one mode of a mission in lock-step: each tick the target driver (sim_lab) commands the
ground robot, the safety supervisor checks every drone, all agents run phase 1, then all run phase 2,
then the backend's clock advances by dt. Before the loop every drone takes off (bounded wait); after it,
whatever ended it (end of mission, a signal, an operator abort, an exception in any agent), every drone is
landed and the recording is returned with what was flown.

On real drones nothing waits for a drone on the control thread (issue 15): takeoffs and landings run on
worker threads (flightstack.safety, `background`), and the safety tick, the operator's abort and the
backend's heartbeat (the guardian process) keep running while they do, also during takeoff and landing.
Signals (SIGINT, SIGTERM, SIGHUP, SIGQUIT, SIGTSTP) land every drone; a repeated one is ignored.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from flightstack.comms.bus import Bus, OperatorChannel, PredictionBus
from flightstack.comms.factory import make_bus
from flightstack.config.mission import Mission
from flightstack.hal import Backend, Clock, Drone
from flightstack.paper.control import Gains
from flightstack.paper.geometry import compose, inverse
from flightstack.recording.timeseries import Recording
from flightstack.runtime.agent import Agent, AgentConfig, Predictor
from flightstack.runtime.backends import build_backend
from flightstack.runtime.phases import (
    LAND_TIMEOUT_S,
    TAKEOFF_TIMEOUT_S,
    TargetDriver,
    advance_until,
    settle_virtual_landing,
)
from flightstack.safety import EventLog, SafeDrone, SafetyLimits
from flightstack.safety.supervisor import MissionSupervisor
from flightstack.vision.camera_file import load_calibration

_log = logging.getLogger(__name__)


def make_agents(
    mission: Mission,
    mode: str,
    backend: Backend,
    drones: dict[int, Drone],
    bus: PredictionBus,
    predictors: Mapping[int, Predictor] | None,
    agent_ids: list[int] | None = None,
) -> list[Agent]:
    """One Agent per drone of the mission (or of `agent_ids`); estimates start from the initial errors."""
    P0 = np.array(mission.target.feature_points, dtype=float)
    gains = Gains.make(mission.gains.k_c, mission.gains.k_e, mission.gains.k_s)
    ids = [d.id for d in mission.drones]
    g_w0 = mission.target.initial_pose.pose()
    agents = []
    for k, d in enumerate(mission.drones):
        if agent_ids is not None and d.id not in agent_ids:
            continue
        cfg = AgentConfig(
            mission=mission.name,
            drone_id=d.id,
            body_name=f"drone{d.id}",
            g_d=d.desired_pose.pose(),
            P0=P0,
            camera=mission.camera_model(k),
            gains=gains,
            mode=mode,
            fusion_rule=mission.gp.fusion,
            neighbour_ids=tuple(ids[j] for j in mission.neighbours(k)),
            stale_after=mission.bus.stale_after_s,
            calibration=None
            if d.camera is None or d.camera.calibration is None
            else load_calibration(mission.resolve(d.camera.calibration)),
            max_frame_age_s=math.inf if mission.hardware is None else mission.hardware.max_frame_age_s,
        )
        # ḡ_w,i(0) = g_w0(0) g_e(0)⁻¹; on sim_lab reset at pursuit start from the drone's own pose
        g_bar = compose(g_w0, inverse(d.initial_estimate_error.pose()))
        pred = None if predictors is None else predictors.get(d.id)
        agents.append(Agent(cfg, drones[d.id], backend.camera(d.id), backend.pose_source(), bus, pred, g_bar))
    return agents


def safety_limits(mission: Mission) -> SafetyLimits:
    s = mission.safety
    return SafetyLimits(**s.model_dump(exclude={"enabled"}))


class SafetyTickTimer:
    """Ticks every SafeDrone once per control period, then beats the backend's heartbeat (the guardian
    process watches it), and measures how long that took (wall clock): a safety tick must never take
    longer than one control period."""

    MAX_SAMPLES = 1_000_000

    def __init__(self, safe: dict[int, SafeDrone], heartbeat: Callable[[], None] | None) -> None:
        self.safe = safe
        self.heartbeat = heartbeat
        self.durations: list[float] = []

    def tick(self, raise_heartbeat: bool = True) -> None:
        """Tick every SafeDrone, then the heartbeat; its error (a guardian takeover) is raised after the
        safety rules ran, unless raise_heartbeat is False (landing: nothing may interrupt it)."""
        t0 = time.perf_counter()
        for s in self.safe.values():
            s.tick()
        if self.heartbeat is not None:
            try:
                self.heartbeat()
            except Exception:
                if raise_heartbeat:
                    raise
                _log.exception("heartbeat while landing")
        if len(self.durations) < self.MAX_SAMPLES:
            self.durations.append(time.perf_counter() - t0)

    def summary(self) -> dict[str, float | int]:
        """ticks, and p50/p99/max of the safety tick's wall time in ms."""
        if not self.durations:
            return {"ticks": 0}
        d = np.array(self.durations) * 1e3
        return {
            "ticks": int(d.size),
            "p50_ms": float(np.percentile(d, 50)),
            "p99_ms": float(np.percentile(d, 99)),
            "max_ms": float(d.max()),
        }


class OperatorAbortError(Exception):
    """`flightstack abort` was received: land every drone now."""


def run_mode(
    mission: Mission,
    mode: str,
    predictors: Mapping[int, Predictor] | None = None,
    progress: Callable[[int], None] | None = None,
    *,
    backend: Backend | None = None,
    bus: Bus | None = None,
    agent_ids: list[int] | None = None,
    writer: Any = None,
) -> Recording:
    """Fly `mode` of a mission for mission.duration_s of pursuit; never leaves a drone flying.

    backend: built from the mission when None (the served world's client for an agent process).
    bus: built from `mission.bus` when None (closed here if built here).
    agent_ids: the drones this process flies (default all); the others are neighbours on the bus.
    writer: a flightstack.recording.run_dir mode writer that appends the recording to disk as the run goes.
    On a simulated clock with a network bus, phase 2 waits for the neighbours' messages of the same tick
    (`bus.zenoh.lockstep_timeout_s`), so the result equals the in-process bus's."""
    ids = [d.id for d in mission.drones] if agent_ids is None else list(agent_ids)
    own_bus = bus is None
    if bus is None:  # first: a bus that cannot open must not leave a connected (armed) backend behind
        participant = "agents" if agent_ids is None else str(ids[0])
        bus = make_bus(mission, participant, set(ids))
    if backend is None:
        try:
            backend = build_backend(mission)
        except BaseException:
            if own_bus:
                bus.close()
            raise
    try:  # setup; on failure nothing took off: close what is connected (an armed robot, video, mocap)
        lockstep = mission.simulated
        zspec = mission.bus.zenoh
        # every agent's message, own ones too: Zenoh loops them back asynchronously
        everyone = sorted(d.id for d in mission.drones)
        clock = backend.clock
        log = EventLog()
        if writer is not None:  # safety events reach the disk as they happen, also in takeoff and landing
            writer.add_event_source(lambda: [{"event": "safety", "mode": mode, **e} for e in log.to_dicts()])
        limits = safety_limits(mission)
        safe: dict[int, SafeDrone] = {}
        supervisor: MissionSupervisor | None = None
        background = not mission.simulated  # real drones: takeoff and land never block the loop
        if mission.safety.enabled:
            safe = {
                i: SafeDrone(
                    i, backend.drone(i), backend.pose_source(), f"drone{i}", clock, limits, log, background
                )
                for i in ids
            }
            supervisor = MissionSupervisor(safe, clock, limits, log)
            drones: dict[int, Drone] = dict(safe)
        else:
            drones = {i: backend.drone(i) for i in ids}
        agents = make_agents(mission, mode, backend, drones, bus, predictors, ids)
        target = TargetDriver(mission, backend) if mission.target.motion == "square" else None
        g_d = np.array([a.cfg.g_d.as_vector() for a in agents])
        dt = mission.dt_s
        n_ticks = round(mission.duration_s / dt)
        rec = Recording.empty(mode, ids, n_ticks)
        rejections: dict[int, Counter[str]] = {i: Counter() for i in ids}
        neighbours_used: dict[int, set[int]] = {i: set() for i in ids}
        wall0 = time.perf_counter()
        reason = "mission complete"
        status = StatusPublisher(bus, mode)
        ticker = SafetyTickTimer(safe, backend.heartbeat)
        signals = _signal_guard(supervisor)
    except BaseException:
        backend.close()
        if own_bus:
            bus.close()
        raise
    signals.__enter__()
    try:
        if zspec is not None:
            missing = bus.wait_alive({d.id for d in mission.drones}, zspec.start_timeout_s)
            if missing:
                raise RuntimeError(
                    f"agents {sorted(missing)} not on the bus after {zspec.start_timeout_s:g} s"
                )
        for d in drones.values():
            d.connect()
        for d in drones.values():  # on real drones each returns at once: they climb together
            d.takeoff()

        def during_takeoff() -> None:
            ticker.tick()
            _check_operator(bus)  # an abort is obeyed during the takeoff too
            failed = {i: s.takeoff_error for i, s in safe.items() if s.takeoff_error}
            if failed:
                raise RuntimeError(f"takeoff failed: {failed}")

        airborne = lambda: all(d.state().flying for d in drones.values())  # noqa: E731
        if not advance_until(clock, airborne, TAKEOFF_TIMEOUT_S, dt, during_takeoff):
            raise RuntimeError(f"takeoff: not every drone airborne after {TAKEOFF_TIMEOUT_S} s")
        t0 = clock.now()
        if mission.backend != "sim_ideal":
            for a in agents:  # the target's pose is unknown: assume it sits at the desired relative pose
                own = a.poses.latest(a.cfg.body_name)
                if own is None:
                    raise RuntimeError(f"no motion-capture pose for {a.cfg.body_name} at pursuit start")
                a.reset_estimate(compose(own.pose, a.cfg.g_d))
        for k in range(n_ticks):
            t = clock.now()
            if target is not None:
                target.tick(t - t0)
            ticker.tick()
            if safe and all(s.landed for s in safe.values()):  # the safety layer landed everyone
                reason = "every drone landed"
                break
            _check_operator(bus)
            for a in agents:
                a.sense_and_publish(t)
            if lockstep and zspec is not None:  # phase 2 needs every neighbour's message of this tick
                late = bus.wait_for_stamp(set(everyone), t, zspec.lockstep_timeout_s)
                if late:
                    rec.events.append({"t": t, "event": "lock-step wait timed out", "late": sorted(late)})
            if supervisor is not None:
                hold = supervisor.update_visibility({a.cfg.drone_id: a.last.visible for a in agents})
                for a in agents:
                    a.hold = hold
            for a in agents:
                a.fuse_control_act(t)
            g_w0, g_wis = backend.truth()
            rec.t[k] = t
            rec.g_w0[k] = g_w0.as_vector()
            for i, a in enumerate(agents):
                last = a.last
                rec.g_wi[k, i] = g_wis[a.cfg.drone_id].as_vector()
                rec.g_bar_w[k, i] = last.g_bar_w.as_vector()
                rec.e_e_meas[k, i] = last.e_e_meas
                rec.u_e[k, i] = last.u_e
                rec.mu_used[k, i] = last.mu_used
                rec.var_own[k, i] = last.var_own
                rec.V_cmd[k, i] = last.V_cmd
                rec.visible[k, i] = last.visible
                if last.rejection:
                    rejections[a.cfg.drone_id][last.rejection] += 1
                used = set(last.neighbours_used)
                if used != neighbours_used[a.cfg.drone_id]:  # a neighbour left or rejoined fusion/consensus
                    prev = neighbours_used[a.cfg.drone_id]
                    rec.events.append(
                        {
                            "t": t,
                            "event": "neighbours",
                            "drone": a.cfg.drone_id,
                            "dropped": sorted(prev - used),
                            "added": sorted(used - prev),
                            "mode": mode,
                        }
                    )
                    neighbours_used[a.cfg.drone_id] = used
                if not last.own_pose_fresh:
                    rejections[a.cfg.drone_id]["own pose lost (hovered)"] += 1
                rec.n_fused[k, i] = last.n_fused
            rec.wall_t[k] = time.time()
            rec.ticks_done = k + 1
            if writer is not None:
                writer.append(rec, k + 1)
            status.maybe_publish(t, k, agents)
            if progress is not None:
                progress(1)
            clock.sleep_until(t + dt)
    except KeyboardInterrupt:
        rec.interrupted = True
        reason = "interrupted"
    except OperatorAbortError as exc:
        rec.error = f"operator abort: {exc}"
        reason = "operator abort"
    except Exception as exc:  # an exception in any agent: land everyone, keep the data, report
        rec.error = f"{type(exc).__name__}: {exc}"
        reason = f"exception: {rec.error}"
    finally:
        if supervisor is not None:  # a signal from here on must not interrupt the landing or the closing
            supervisor.ignore_signals(f"the run's end ({reason})")
        rec.events.append({"t": clock.now(), "event": "end", "reason": reason, "mode": mode})
        if writer is not None:
            writer.event(rec.events[-1])
        _land_everything(backend, clock, drones, supervisor, target, reason, dt, ticker, bus)
        with contextlib.suppress(Exception):  # `status` and `guard` see the drones down before we leave
            status.maybe_publish(clock.now(), rec.ticks_done, agents, force=True)
        signals.__exit__(None, None, None)
        rec.events.append({"t": clock.now(), "event": "safety tick", "mode": mode, **ticker.summary()})
        for i in ids:
            st = backend.drone(i).state()
            rec.events.append(
                {
                    "t": clock.now(),
                    "event": "landed" if not st.flying else "NOT LANDED",
                    "drone": i,
                    "height_m": st.height_m,
                    "telemetry_alive": st.link_alive,  # False: height_m is the last one received
                    "mode": mode,
                }
            )
        rec.events.extend({"event": "safety", "mode": mode, **e} for e in log.to_dicts())
        rec.wall_seconds = time.perf_counter() - wall0
        rec.bus_dropped = dict(bus.dropped)
        rec.events.extend(
            {"event": "bus presence", "mode": mode, "sender": j, "what": what, "monotonic": tm}
            for tm, j, what in bus.presence_events
        )
        if own_bus:
            bus.close()
        rec.vision_rejections = {str(i): dict(c) for i, c in rejections.items() if c}
        rec.fill_true_errors(g_d)
        if writer is not None:
            writer.close(rec)
    return rec if rec.ticks_done == n_ticks and not rec.interrupted else rec.truncated()


def _check_operator(bus: OperatorChannel) -> None:
    """Raise OperatorAbortError when the operator channel carried an abort for this mission."""
    for ev in bus.control_events():
        if ev.kind == "abort":
            raise OperatorAbortError(str(ev.payload.get("reason", "abort")))


class StatusPublisher:
    """Publishes each hosted agent's status on the operator channel about twice a second (wall clock),
    for `flightstack status`. A bus without an operator channel (in-process) makes this a no-op."""

    PERIOD_S = 0.5

    def __init__(self, bus: Bus, mode: str) -> None:
        self.bus = bus
        self.mode = mode
        self._next = 0.0

    def maybe_publish(self, t: float, tick: int, agents: list[Agent], force: bool = False) -> None:
        """Publish if PERIOD_S has passed since the last one (or `force`: the final status after landing)."""
        now = time.monotonic()
        if now < self._next and not force:
            return
        self._next = now + self.PERIOD_S
        for a in agents:
            st = a.drone.state()
            last = a.last
            self.bus.publish_control(
                "status",
                {
                    "drone": a.cfg.drone_id,
                    "mode": self.mode,
                    "t": t,
                    "tick": tick,
                    # bounded as the receivers require (control.StatusReport): a NaN or out-of-range
                    # reading must neither raise here nor make the status unreadable to `guard`
                    "battery_pct": float(np.clip(np.nan_to_num(st.battery_pct, nan=0.0), 0.0, 100.0)),
                    "flying": st.flying,
                    "link_alive": st.link_alive,
                    "visible": bool(last.visible),
                    "n_fused": int(last.n_fused),
                    "pose_fresh": bool(last.own_pose_fresh),
                    "rejection": last.rejection,
                    "dropped": dict(self.bus.dropped),
                },
            )


def _signal_guard(supervisor: MissionSupervisor | None) -> Any:
    """The supervisor's signal handlers, on the main thread (signals are only delivered there)."""
    if supervisor is None or threading.current_thread() is not threading.main_thread():
        return contextlib.nullcontext()
    return supervisor.install_signal_handlers()


def _land_everything(
    backend: Backend,
    clock: Clock,
    drones: dict[int, Drone],
    supervisor: MissionSupervisor | None,
    target: TargetDriver | None,
    reason: str,
    dt: float,
    ticker: SafetyTickTimer,
    bus: Bus,
) -> None:
    """Land every drone and stop the robot; on a virtual clock also let the landing complete.

    Real drones land in parallel on worker threads while this keeps ticking the safety layer (it confirms
    each landing, hovers and re-sends land on a silent link) and the guardian's heartbeat, bounded by
    LAND_TIMEOUT_S; only then are the drivers closed (closing lands whatever is still up)."""
    try:
        if target is not None:
            target.stop()
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
                lambda: _quietly(ticker.tick, bus),
            )
    backend.close()  # lands any drone the supervisor did not reach
    if backend.simulated:  # let the virtual landing finish: each drone's own state says it is down
        settle_virtual_landing(backend, list(drones), dt)


def _quietly(tick: Callable[[bool], None], bus: OperatorChannel) -> None:
    """One tick while landing; an abort arriving now is already being obeyed (drained; the bus acks it)."""
    tick(False)
    with contextlib.suppress(OperatorAbortError):
        _check_operator(bus)
