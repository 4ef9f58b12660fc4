"""Fly one simulated mission mode under injected faults and judge safety and the recording.

`fly_with_faults` loads the mission (shortened, mode `none` only, always on an in-process bus so that no
traffic leaves the process), flies it (flightstack.runtime.flight) with its backend (and bus) wrapped by
flightstack.faults.inject, writes the recording, events and metrics to the row's directory, and returns
a `SimRun`.
`judge_safety` and `judge_recording` turn a SimRun into the FaultResult's flags and problem lists.
Times are mission-clock seconds; positions are in the world frame Σw (m).
"""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flightstack.analysis.metrics import mode_metrics
from flightstack.comms.bus import InProcBus
from flightstack.config.mission import Mission, load_mission
from flightstack.config.rig import resolved_document
from flightstack.faults.inject import FaultSpec, FaultyBackend, FaultyBus
from flightstack.faults.result import Checks
from flightstack.hal import Backend
from flightstack.recording.run_dir import RunWriter
from flightstack.recording.timeseries import ARRAY_FIELDS, LOOP_HEALTH_FIELDS, Recording
from flightstack.runtime.fleet import safety_limits
from flightstack.runtime.flight import Flight
from flightstack.safety import outside_hard_fence, outside_soft_fence

FINITE_FIELDS = tuple(
    f for f in ARRAY_FIELDS if f not in ("visible", "n_fused", "wall_t", *LOOP_HEALTH_FIELDS)
)
"""Recording arrays that must be finite on every recorded tick (loop health is NaN where unmeasured)."""


def same_array(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal shape and values, NaN equal to NaN (float arrays)."""
    return bool(np.array_equal(a, b, equal_nan=np.issubdtype(a.dtype, np.floating)))


@dataclass
class SimRun:
    """One faulty flight: the mission flown, the wrapped backend and bus, the recording (None if the
    flight raised: then `crashed` holds the traceback's last line), wall seconds and the row's directory."""

    mission: Mission
    backend: FaultyBackend
    bus: Any
    rec: Recording | None
    crashed: str | None
    seconds: float
    run_dir: Path
    n_ticks: int
    write_problems: list[str] = field(default_factory=list)

    def events(self, kind: str | None = None, drone: int | None = None) -> list[dict[str, Any]]:
        """Safety events of the run (of one kind / one drone), oldest first."""
        evs = [] if self.rec is None else [e for e in self.rec.events if e.get("event") == "safety"]
        evs = [e for e in evs if kind is None or e["kind"] == kind]
        return [e for e in evs if drone is None or e.get("drone") == drone]

    def first(self, kind: str, drone: int | None = None) -> dict[str, Any] | None:
        evs = self.events(kind, drone)
        return evs[0] if evs else None

    @property
    def pursuit_start(self) -> float:
        """Mission-clock time of the first recorded tick (s), NaN without ticks."""
        return float(self.rec.t[0]) if self.rec is not None and self.rec.ticks_done else float("nan")

    @property
    def pursuit_end(self) -> float:
        """Mission-clock time at which the run ended (the `end` event), NaN if absent."""
        for e in [] if self.rec is None else self.rec.events:
            if e.get("event") == "end":
                return float(e["t"])
        return float("nan")


def load_fault_mission(
    mission_path: Path,
    duration_s: float,
    safety: dict[str, Any] | None = None,
    desired_z: dict[int, float] | None = None,
) -> Mission:
    """The mission with `duration_s` of pursuit, mode `none` only, `safety` keys replaced and the drones of
    `desired_z` (id -> m) given that z of their desired pose (the camera frame's: negative is above)."""
    overrides: dict[str, Any] = {"duration_s": duration_s, "compare_modes": ["none"]}
    if desired_z:
        drones = resolved_document(mission_path)["drones"]
        for d in drones:
            if d["id"] in desired_z:
                p = d["desired_pose"]["p"]
                d["desired_pose"] = {**d["desired_pose"], "p": [p[0], p[1], desired_z[d["id"]]]}
        overrides["drones"] = drones
    if safety:
        data = resolved_document(mission_path)
        overrides["safety"] = {**(data.get("safety") or {}), **safety}
    return load_mission(mission_path, overrides)


def fly_with_faults(
    mission_path: Path,
    run_dir: Path,
    spec: FaultSpec,
    *,
    duration_s: float,
    safety: dict[str, Any] | None = None,
    bus_faults: dict[str, Any] | None = None,
    desired_z: dict[int, float] | None = None,
) -> SimRun:
    """Fly mode `none` of the mission for duration_s (s) of pursuit with the faults of `spec` and
    `bus_faults` (keyword arguments of FaultyBus), `safety` and `desired_z` as load_fault_mission takes
    them; write the run to run_dir. Never raises for a failure of the run itself (`SimRun.crashed`)."""
    wall0 = time.perf_counter()
    mission = load_fault_mission(mission_path, duration_s, safety, desired_z)
    ids = [d.id for d in mission.drones]
    inner_bus = InProcBus(mission.name, set(ids))
    bus = FaultyBus(inner_bus, **bus_faults) if bus_faults else inner_bus
    wrapped: list[FaultyBackend] = []

    def faulty(backend: Backend) -> Backend:
        wrapped.append(FaultyBackend(backend, spec, ids))
        return wrapped[-1]

    rec: Recording | None = None
    crashed: str | None = None
    try:
        with Flight(mission, bus=bus, wrap_backend=faulty) as flight:
            rec = flight.fly_mode("none")
    except Exception as exc:  # the runner must not let anything escape: this is the finding
        crashed = f"{type(exc).__name__}: {exc} ({traceback.format_exc(limit=-1).strip().splitlines()[-2]})"
    finally:
        inner_bus.close()
    if not wrapped:  # the backend itself could not be built: the row cannot judge anything
        raise RuntimeError(f"the backend was not built: {crashed}")
    run = SimRun(
        mission,
        wrapped[0],
        bus,
        rec,
        crashed,
        0.0,
        run_dir,
        mission.n_ticks,
    )
    if rec is not None:
        run.write_problems = write_run(run_dir, mission, rec)
    run.seconds = time.perf_counter() - wall0
    return run


def write_run(run_dir: Path, mission: Mission, rec: Recording) -> list[str]:
    """timeseries_<mode>.npz, events.jsonl and metrics.json (strict JSON, with "recording": {"complete",
    "reason"}) through flightstack.recording.run_dir (atomic files); the problems met doing so, among them an
    incomplete recording (e.g. a full disk)."""
    problems = []
    try:
        with RunWriter(run_dir) as writer:
            writer.record(rec)
            status = writer.write_metrics(mode_metrics(rec, mission))["recording"]
        if not status["complete"]:
            problems.append(f"recording incomplete: {status['reason']}")
    except Exception as exc:
        problems.append(f"writing the run failed: {type(exc).__name__}: {exc}")
    return problems


def judge_safety(run: SimRun) -> list[str]:
    """Problems with the drones' safety (empty: safe): every drone landed or hovering inside the soft
    fence at the end (backend truth and simulator phase), none `NOT LANDED`, none ever beyond the hard fence
    (true poses of every recorded tick; the floor is not checked: landing is below it)."""
    c = Checks()
    limits = safety_limits(run.mission)
    _, poses = run.backend.truth()
    for i in run.backend.ids:
        inner = run.backend.drone(i).inner
        phase = str(getattr(inner, "phase", "ground" if not inner.state().flying else "flying"))
        p = np.round(poses[i].p, 3).tolist()
        landed = phase == "ground" and poses[i].p[2] <= 0.05
        hovering = phase == "flying" and not outside_soft_fence(poses[i].p, limits)
        c.check(landed or hovering, f"drone {i} ended {phase} at {p}")
    if run.rec is not None:
        bad = [e for e in run.rec.events if e.get("event") == "NOT LANDED"]
        c.check(not bad, f"NOT LANDED events: {bad}")
        k = run.rec.ticks_done
        for j, i in enumerate(run.rec.drone_ids):
            out = [outside_hard_fence(p, limits, check_floor=False) for p in run.rec.g_wi[:k, j, :3]]
            n_out = sum(1 for f in out if f)
            c.check(n_out == 0, f"drone {i} beyond the hard fence on {n_out} ticks")
    return c.failed


def judge_recording(run: SimRun, expect_ticks: int | None = None, expect_error: bool = False) -> list[str]:
    """Problems with the recording (empty: complete). expect_ticks: ticks that must have been flown
    (default: the whole mission); expect_error: the run is meant to end with `rec.error` set."""
    c = Checks()
    rec = run.rec
    if not c.check(rec is not None, "no recording returned"):
        return c.failed
    assert rec is not None
    c.failed.extend(run.write_problems)
    k = rec.ticks_done
    ends = {str(e.get("reason")) for e in rec.events if e.get("event") == "end"}
    landed_early = "every drone landed" in ends
    want = (k if landed_early else run.n_ticks) if expect_ticks is None else expect_ticks
    c.check(k == want, f"{k} ticks recorded, {want} expected")
    c.check(not rec.interrupted, "recording marked interrupted")
    c.check(bool(rec.error) == expect_error, f"run error: {rec.error!r}")
    for name in FINITE_FIELDS:
        arr = getattr(rec, name)
        c.check(arr.shape[0] == k, f"{name} has {arr.shape[0]} rows for {k} ticks")
        c.check(bool(np.all(np.isfinite(arr[:k]))), f"{name} not finite")
    if k > 1:
        steps = np.diff(rec.t[:k])
        c.check(bool(np.allclose(steps, run.mission.dt_s, rtol=1e-6)), "tick times are not every dt")
    end_events = [e for e in rec.events if e.get("event") == "end"]
    c.check(len(end_events) == 1, f"{len(end_events)} end events")
    for i in rec.drone_ids:
        fates = [e for e in rec.events if e.get("drone") == i and e.get("event") in ("landed", "NOT LANDED")]
        c.check(len(fates) == 1, f"drone {i}: {len(fates)} landed/NOT LANDED events")
    path = run.run_dir / f"timeseries_{rec.mode}.npz"
    if c.check(path.is_file(), f"{path.name} not written"):
        back = Recording.load(str(path))
        c.check(back.ticks_done == k, f"saved recording has {back.ticks_done} ticks, flown {k}")
        same = all(same_array(getattr(back, f), getattr(rec, f)[:k]) for f in ARRAY_FIELDS)
        c.check(same, "saved recording differs from the flown one")
    n_lines = len((run.run_dir / "events.jsonl").read_text().splitlines()) if run.run_dir.is_dir() else 0
    c.check(n_lines == len(rec.events), f"events.jsonl has {n_lines} lines for {len(rec.events)} events")
    return c.failed


ROUTINE = frozenset({"takeoff", "command_after_land"})


def event_story(run: SimRun, skip: frozenset[str] = ROUTINE) -> str:
    """The safety events after pursuit start as 'kind d1 @t' in time order (the mission-complete landing
    and the command watchdog during takeoff left out), then how the run ended."""
    t0, t_end = run.pursuit_start, run.pursuit_end
    parts = []
    for e in run.events():
        if e["kind"] in skip or e["t"] < t0 - 1e-9:
            continue
        if e["t"] >= t_end - 1e-9 and "mission complete" in str(e.get("detail", "")):
            continue
        who = "" if e.get("drone") is None else f"d{e['drone']} "
        why = f"({e['detail']})" if e["kind"] == "land" and str(e.get("detail")).startswith("retry") else ""
        parts.append(f"{who}{e['kind']}{why} @{e['t']:.2f}")
    ends = [e for e in (run.rec.events if run.rec else []) if e.get("event") == "end"]
    reason = str(ends[0]["reason"]) if ends else "?"
    story = " → ".join(parts) if parts else "no safety event"
    return f"{story}; end @{t_end:.2f}: {reason}"


def landed_before_end(run: SimRun, drone: int) -> bool:
    """True if the drone was landed by a reaction (not by the end-of-mission land_all): a land accepted
    before the end, or at the end when the run ended because every drone had landed."""
    return any(
        e["t"] < run.pursuit_end - 1e-9 or "mission complete" not in str(e.get("detail", ""))
        for e in run.events("land", drone)
    )
