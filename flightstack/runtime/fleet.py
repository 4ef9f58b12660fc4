"""Assembling the fleet of one run: bus, backend, safety layer, agents, the robot's driver (DESIGN §1–2).

`assemble_fleet` is a context manager: whatever it opened is closed when assembly fails (nothing took
off: an armed robot, video, mocap), and the bus it opened is closed when the run leaves the block. The
parts every tick uses live on the `Fleet`; the runner (flightstack.runtime.runner) flies it.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from flightstack.comms.bus import Bus, OperatorChannel, PredictionBus, restart_counts
from flightstack.comms.factory import make_bus
from flightstack.config.mission import Mission
from flightstack.hal import Backend, Clock, Drone
from flightstack.paper.control import Gains
from flightstack.paper.geometry import compose, inverse
from flightstack.paper.kernels_warmup import warm_up
from flightstack.recording.files import DeviceFiles
from flightstack.runtime.agent import Agent, AgentConfig, Predictor
from flightstack.runtime.phases import TargetDriver
from flightstack.runtime.rig import build_backend, rig_of
from flightstack.safety import EventLog, SafeDrone, SafetyLimits
from flightstack.safety.supervisor import MissionSupervisor
from flightstack.vision.camera_file import load_calibration
from flightstack.vision.gate import DEFAULT_NOISE_PX, GateSpec

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
    compensation = mission.delay_compensation()
    agents = []
    for k, d in enumerate(mission.drones):
        if agent_ids is not None and d.id not in agent_ids:
            continue
        cal = None
        if d.camera is not None and d.camera.calibration is not None:
            cal = load_calibration(mission.resolve(d.camera.calibration))
        cfg = AgentConfig(
            mission=mission.name,
            drone_id=d.id,
            body_name=mission.identity(d.id).name,
            g_d=d.desired_pose.pose(),
            P0=P0,
            camera=mission.camera_model(k),
            gains=gains,
            mode=mode,
            fusion_rule=mission.gp.fusion,
            neighbour_ids=tuple(ids[j] for j in mission.neighbours(k)),
            stale_after=mission.bus.stale_after_s,
            calibration=cal,
            max_frame_age_s=math.inf if mission.hardware is None else mission.hardware.max_frame_age_s,
            compensation=compensation,
            command_limits=safety_limits(mission) if mission.safety.enabled else None,
            gate=None if cal is None else GateSpec(noise_px=cal.rms_px or DEFAULT_NOISE_PX),
        )
        # ḡ_w,i(0) = g_w0(0) g_e(0)⁻¹; on sim_lab reset at pursuit start from the drone's own pose
        g_bar = compose(g_w0, inverse(d.initial_estimate_error.pose()))
        pred = None if predictors is None else predictors.get(d.id)
        agents.append(Agent(cfg, drones[d.id], backend.camera(d.id), backend.pose_source(), bus, pred, g_bar))
    return agents


@runtime_checkable
class DelaysBus(Protocol):
    """A backend that models the link between the agents of its process (the simulated lab's `bus`
    link, on its own clock): returns the bus as that link delivers it."""

    def delay_bus(self, bus: Bus) -> Bus: ...


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


def check_operator(bus: OperatorChannel) -> None:
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
                    "restarts": restart_counts(self.bus.presence_events),
                },
            )


def signal_guard(supervisor: MissionSupervisor | None) -> Any:
    """The supervisor's signal handlers, on the main thread (signals are only delivered there)."""
    if supervisor is None or threading.current_thread() is not threading.main_thread():
        return contextlib.nullcontext()
    return supervisor.install_signal_handlers()


@dataclass(frozen=True)
class LoopSpec:
    """What the runner needs of the mission, derived once per mode: dt_s (s), n_ticks (of pursuit),
    lockstep (a simulated clock: phase 2 waits for every neighbour's message of the same tick, on a
    network bus), start_timeout_s and lockstep_timeout_s of the network bus (s; None: in-process bus),
    reset_estimates (each estimate starts from the drone's own motion-capture pose at pursuit start:
    every rig but the ideal one, where the truth is the initial estimate)."""

    dt_s: float
    n_ticks: int
    lockstep: bool
    start_timeout_s: float | None
    lockstep_timeout_s: float | None
    reset_estimates: bool

    @classmethod
    def of(cls, mission: Mission) -> LoopSpec:
        z = mission.bus.zenoh
        return cls(
            dt_s=mission.dt_s,
            n_ticks=mission.n_ticks,
            lockstep=mission.simulated,
            start_timeout_s=None if z is None else z.start_timeout_s,
            lockstep_timeout_s=None if z is None else z.lockstep_timeout_s,
            reset_estimates=not mission.rig_type.estimates_start_from_truth,
        )


@dataclass
class Fleet:
    """Everything one run flies with: `ids` the drones this process flies (recording order), `drones`
    what the agents command (SafeDrone wrappers when safety is on), `safe` those wrappers ({} when off)."""

    loop: LoopSpec
    mode: str
    ids: list[int]
    bus: Bus
    backend: Backend
    clock: Clock
    log: EventLog
    safe: dict[int, SafeDrone]
    supervisor: MissionSupervisor | None
    drones: dict[int, Drone]
    agents: list[Agent]
    target: TargetDriver | None
    ticker: SafetyTickTimer
    status: StatusPublisher
    g_d: np.ndarray  # (n, 4) desired relative poses g_d,i as vectors, recording order
    everyone: frozenset[int]  # every drone of the mission, own ones too (the lock-step wait's senders)


def _nudge_fence(mission: Mission) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The fence's xy box (m) in which the robot is nudged before takeoff on a rig whose robot is a
    device (RigFacts.robot_is_device: the real and the emulated lab; flightstack.runtime.motion_check); None
    on the simulated rigs, which do not nudge it."""
    if not mission.rig_type.robot_is_device:
        return None
    lo, hi = mission.safety.fence_lo, mission.safety.fence_hi
    return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))


@contextlib.contextmanager
def assemble_fleet(
    mission: Mission,
    mode: str,
    predictors: Mapping[int, Predictor] | None,
    *,
    backend: Backend | None,
    bus: Bus | None,
    agent_ids: list[int] | None,
    writer: Any,
    wrap_backend: Callable[[Backend], Backend] | None = None,
    wrap_bus: Callable[[Bus], Bus] | None = None,
    devices: DeviceFiles | None = None,
) -> Iterator[Fleet]:
    """Build the fleet (bus first: a bus that cannot open must not leave a connected, armed backend
    behind); on failure close what was opened and re-raise. The bus built here is closed on exit; a bus
    or backend passed in belongs to the caller (the backend is closed by landing). A bus built here goes
    through the backend's bus link (DelaysBus: the simulated lab's), then wrap_bus; wrap_backend and
    wrap_bus wrap what is built here (the fault table's injectors). devices: where a backend built here
    records its devices' raw traffic (real devices only)."""
    ids = [d.id for d in mission.drones] if agent_ids is None else list(agent_ids)
    # compile (or load) the tick's kernels before any device is opened: a compile mid-flight holds the GIL
    warm_up(loop=rig_of(mission).compiled_loop() is not None)
    own_bus = bus is None
    if bus is None:
        participant = "agents" if agent_ids is None else mission.identity(ids[0]).agent
        bus = make_bus(mission, participant, set(ids))
    built_bus = bus
    try:
        built = backend
        if backend is None:
            if not mission.simulated:
                # a full collection holds the GIL for every thread (0.16-0.20 s over ~194 000 objects in a
                # test's process, quiet): run it while no device is open, where it cannot starve a driver's
                # stream (run with the robot connected, it lapsed the robot's pose feed, whose loss holds the
                # robot after 1 s, for 1.1 s on a loaded CI machine)
                gc.collect()
                gc.freeze()
            backend = built = build_backend(mission, devices)
            if wrap_backend is not None:
                try:
                    backend = wrap_backend(backend)
                except BaseException:
                    backend.close()
                    raise
        try:
            if own_bus and isinstance(built, DelaysBus):  # the lab's own link, under any injector
                bus = built.delay_bus(bus)
            if own_bus and wrap_bus is not None:
                bus = wrap_bus(bus)
            fleet = _build(mission, mode, predictors, backend, bus, ids, writer)
        except BaseException:
            backend.close()
            raise
        yield fleet
    finally:
        if own_bus:
            built_bus.close()


def _build(
    mission: Mission,
    mode: str,
    predictors: Mapping[int, Predictor] | None,
    backend: Backend,
    bus: Bus,
    ids: list[int],
    writer: Any,
) -> Fleet:
    clock = backend.clock
    log = EventLog()
    if writer is not None:  # safety events reach the disk as they happen, also in takeoff and landing
        writer.add_event_source(lambda: [e.record(mode) for e in log.events])
    limits = safety_limits(mission)
    safe: dict[int, SafeDrone] = {}
    supervisor: MissionSupervisor | None = None
    background = not mission.simulated  # real drones: takeoff and land never block the loop
    if mission.safety.enabled:
        safe = {
            i: SafeDrone(
                i,
                backend.drone(i),
                backend.pose_source(),
                mission.identity(i).name,
                clock,
                limits,
                log,
                background,
            )
            for i in ids
        }
        supervisor = MissionSupervisor(safe, clock, limits, log)
        drones: dict[int, Drone] = dict(safe)
    else:
        drones = {i: backend.drone(i) for i in ids}
    agents = make_agents(mission, mode, backend, drones, bus, predictors, ids)
    if not mission.simulated:
        # what exists now lives for the whole flight: out of the collector's way, so that a full collection
        # mid-flight walks only what the flight allocates (its pause stays far below the loop watchdog's).
        # No collection first: the devices are streaming by now (see assemble_fleet); freeze itself is O(1)
        gc.freeze()
    return Fleet(
        loop=LoopSpec.of(mission),
        mode=mode,
        ids=ids,
        bus=bus,
        backend=backend,
        clock=clock,
        log=log,
        safe=safe,
        supervisor=supervisor,
        drones=drones,
        agents=agents,
        target=TargetDriver(mission.target_law(), backend, _nudge_fence(mission), log)
        if mission.target.motion == "square"
        else None,
        ticker=SafetyTickTimer(safe, backend.heartbeat),
        status=StatusPublisher(bus, mode),
        g_d=np.array([a.cfg.g_d.as_vector() for a in agents]),
        everyone=frozenset(d.id for d in mission.drones),
    )
