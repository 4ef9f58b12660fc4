"""The simulated rows of `flightstack faults`: each flies the (lab) mission under one fault.

Every row is a `FaultRow`: (mission file, work directory) -> FaultResult, and never raises for a failure
of the system under test. Fault windows are in mission-clock seconds: the drones take off at t = 0 and
pursuit starts at t ≈ 2.05 s on `paper_experiment.yaml`, so faults start at T_FAULT = 4 s.
The drone ids 1 and 2 are those of the lab mission (drone 1 sees the target, drone 2 does not).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from flightstack.faults.fly import (
    SimRun,
    event_story,
    fly_with_faults,
    judge_recording,
    judge_safety,
    landed_before_end,
    load_fault_mission,
)
from flightstack.faults.inject import FaultSpec, Window
from flightstack.faults.result import Checks, FaultResult, FaultRow
from flightstack.safety.drone import SUSPECT_LAND_AFTER_S

T_FAULT = 4.0
"""Mission-clock time (s) at which the faults start, about 2 s into pursuit."""
DURATION_S = 8.0
"""Pursuit seconds of each simulated row (≈ 2.5 s wall on 2 cores)."""


def sim_result(
    name: str,
    expected: str,
    run: SimRun,
    reaction: Checks,
    observed: str,
    *,
    expect_ticks: int | None = None,
    expect_error: bool = False,
    details: dict[str, Any] | None = None,
) -> FaultResult:
    """FaultResult of a simulated row from the run and the row's reaction checks."""
    safety = judge_safety(run)
    recording = judge_recording(run, expect_ticks, expect_error)
    problems = [f"safety: {p}" for p in safety] + [f"recording: {p}" for p in recording]
    problems += [f"reaction: {p}" for p in reaction.failed]
    if run.crashed:
        problems.insert(0, f"crashed: {run.crashed}")
    info: dict[str, Any] = {"run_dir": str(run.run_dir)}
    if run.rec is not None:
        info |= {
            "ticks": run.rec.ticks_done,
            "bus_dropped": dict(run.rec.bus_dropped),
            "vision_rejections": run.rec.vision_rejections,
        }
    return FaultResult(
        name=name,
        expected=expected,
        observed=observed if run.rec is not None else f"run_mode raised {run.crashed}",
        all_safe=not safety,
        recording_complete=not recording,
        crashed=run.crashed is not None,
        seconds=run.seconds,
        reaction_ok=reaction.ok and run.rec is not None,
        problems=problems,
        details=info | (details or {}),
    )


def _near(t: float | None, t_want: float, tol: float = 0.12) -> bool:
    return t is not None and abs(t - t_want) <= tol


def _t(ev: dict[str, Any] | None) -> float | None:
    return None if ev is None else float(ev["t"])


def _flew_to_end(run: SimRun, drones: list[int], c: Checks) -> None:
    for i in drones:
        c.check(not landed_before_end(run, i), f"drone {i} landed before the end of the mission")


# ---- rows ---------------------------------------------------------------------------------------------
def link_loss(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1's link is down for 3 s (no telemetry, commands and land unanswered)."""
    lost = Window(T_FAULT, T_FAULT + 3.0)
    expected = (
        "that drone: link_lost at once, zero velocity on every tick, land sent at once and re-sent every "
        "land_retry_s, accepted when the link returns; the other drone flies on"
    )
    run = fly_with_faults(
        mission_path, workdir / "link_loss", FaultSpec(link_loss={1: lost}), duration_s=DURATION_S
    )
    c = Checks()
    t_lost, t_land = _t(run.first("link_lost", 1)), _t(run.first("land", 1))
    c.check(_near(t_lost, lost.start), f"link_lost of drone 1 at {t_lost}, expected ≈ {lost.start}")
    c.check(_near(t_land, lost.end), f"drone 1 landed at {t_land}, the link returned at {lost.end}")
    _flew_to_end(run, [2], c)
    dropped = run.backend.drone(1).dropped_commands
    return sim_result(
        "link_loss", expected, run, c, event_story(run), details={"commands_lost_in_the_air": dropped}
    )


def _dropout(mission_path: Path, workdir: Path, name: str, length_s: float) -> SimRun:
    spec = FaultSpec(mocap_dropout=Window(T_FAULT + 1.0, T_FAULT + 1.0 + length_s))
    return fly_with_faults(mission_path, workdir / name, spec, duration_s=DURATION_S)


def _hover_ticks(run: SimRun) -> dict[str, int]:
    rej = {} if run.rec is None else run.rec.vision_rejections
    return {i: r.get("own pose lost (hovered)", 0) for i, r in rej.items()}


def mocap_dropout_short(mission_path: Path, workdir: Path) -> FaultResult:
    """Motion capture loses every body for 0.2 s (< pose_timeout)."""
    expected = (
        "each agent hovers (V = 0) on the ticks without its own pose, then resumes; "
        "shorter than pose_timeout: no safety event, no landing"
    )
    run = _dropout(mission_path, workdir, "mocap_dropout_short", 0.2)
    c = Checks()
    hovered = _hover_ticks(run)
    c.check(
        set(hovered) == {str(i) for i in run.mission.drone_ids()} and all(n > 0 for n in hovered.values()),
        f"hover ticks {hovered}",
    )
    for kind in ("pose_stale_hover", "pose_stale_land"):
        c.check(not run.events(kind), f"{kind} events {run.events(kind)}")
    _flew_to_end(run, run.mission.drone_ids(), c)
    observed = f"agents hovered {hovered} ticks without pose, then pursued; {event_story(run)}"
    return sim_result("mocap_dropout_short", expected, run, c, observed)


def mocap_dropout_long(mission_path: Path, workdir: Path) -> FaultResult:
    """Motion capture loses every body for 3 s (> pose_land_after)."""
    expected = (
        "pose_stale_hover after pose_timeout (0.3 s), pose_stale_land after pose_land_after (2 s): "
        "every drone lands; the run ends when the last one is down"
    )
    run = _dropout(mission_path, workdir, "mocap_dropout_long", 3.0)
    c = Checks()
    lim = run.mission.safety
    t_drop = T_FAULT + 1.0
    for i in run.mission.drone_ids():
        t_h, t_l = _t(run.first("pose_stale_hover", i)), _t(run.first("pose_stale_land", i))
        c.check(_near(t_h, t_drop + lim.pose_timeout), f"drone {i} pose_stale_hover at {t_h}")
        c.check(_near(t_l, t_drop + lim.pose_land_after), f"drone {i} pose_stale_land at {t_l}")
        c.check(landed_before_end(run, i), f"drone {i} did not land before the end")
    return sim_result("mocap_dropout_long", expected, run, c, event_story(run))


FROZEN_HOVER_S = 1.0
"""A frozen pose: zero velocity within this long of the freeze (s)."""
FROZEN_DOWN_S = 5.0
"""A frozen pose: the drone down (true z at or below landed_height) within this long of the freeze (s)."""


def _frozen_row(run: SimRun, name: str, expected: str) -> FaultResult:
    """Judge drone 1 under a frozen pose: `pose_frozen`, zero velocity sent within FROZEN_HOVER_S, down
    within FROZEN_DOWN_S, never above the fence's ceiling (true z); drone 2 untouched and flying on."""
    c = Checks()
    frozen = run.backend.pose_lies_began().get("drone1")
    c.check(frozen is not None, "drone 1's pose never froze")
    t_f = frozen if frozen is not None else float("nan")
    ev = run.first("pose_frozen", 1)
    t_ev = _t(ev)
    c.check(t_ev is not None and t_ev - t_f <= FROZEN_HOVER_S, f"pose_frozen at {t_ev}, froze at {t_f:.2f}")
    sent = run.backend.drone(1).sent_after(t_f)
    t_moved = max((t for t, v in sent if np.any(v)), default=t_f)  # the last non-zero command
    t_zero = next((t for t, v in sent if t >= t_moved and not np.any(v)), None)  # the hover from then on
    hover = None if t_zero is None else t_zero - t_f
    c.check(hover is not None and hover <= FROZEN_HOVER_S, f"zero velocity from {hover} s after the freeze")
    lim = run.mission.safety
    down, z_max = None, float("nan")
    if run.rec is not None:
        k = run.rec.ticks_done
        t, z = run.rec.t[:k], run.rec.g_wi[:k, 0, 2]
        after = t >= t_f
        z_max = float(np.max(z[after])) if after.any() else float("nan")
        low = np.flatnonzero(after & (z <= lim.landed_height))
        down = float(t[low[0]] - t_f) if low.size else None
    c.check(down is not None and down <= FROZEN_DOWN_S, f"drone 1 down {down} s after the freeze")
    c.check(z_max <= lim.fence_hi[2], f"drone 1 reached z {z_max:.3f} m (ceiling {lim.fence_hi[2]:g} m)")
    for kind in ("pose_frozen", "pose_disagrees"):
        c.check(not run.events(kind, 2), f"drone 2: {kind} {run.events(kind, 2)}")
    _flew_to_end(run, [2], c)
    details = {
        "froze_at_s": round(t_f, 3),
        "event_after_ms": None if t_ev is None else round(1e3 * (t_ev - t_f)),
        "hover_after_ms": None if hover is None else round(1e3 * hover),
        "down_after_ms": None if down is None else round(1e3 * down),
        "max_z_after_m": round(z_max, 3),
    }
    observed = (
        f"froze at {t_f:.2f} s: pose_frozen +{details['event_after_ms']} ms, zero velocity "
        f"+{details['hover_after_ms']} ms, down +{details['down_after_ms']} ms, highest z after the freeze "
        f"{details['max_z_after_m']} m (ceiling {lim.fence_hi[2]:g} m); {event_story(run)}"
    )
    return sim_result(name, expected, run, c, observed, details=details)


def mocap_frozen(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1's pose freezes (same pose, fresh stamps, valid) 1 s into pursuit."""
    expected = (
        f"pose_frozen and zero velocity within {FROZEN_HOVER_S:g} s, land (pose_stale_land) "
        f"{SUSPECT_LAND_AFTER_S:g} s after the freeze, down within {FROZEN_DOWN_S:g} s, never above the "
        "ceiling; drone 2 flies on"
    )
    spec = FaultSpec(mocap_frozen={"drone1": (T_FAULT - 1.0, None)})
    run = fly_with_faults(mission_path, workdir / "mocap_frozen", spec, duration_s=DURATION_S)
    return _frozen_row(run, "mocap_frozen", expected)


CEILING_M = 1.3
"""mocap_frozen_climbing: the fence's ceiling (m), 0.3 m above the height drone 1 takes off to (1.0 m)."""
CLIMB_TO_M = 1.25
"""mocap_frozen_climbing: drone 1's desired height above the target's frame (m), just below CEILING_M."""


def mocap_frozen_climbing(mission_path: Path, workdir: Path) -> FaultResult:
    """The fence's ceiling lowered to CEILING_M, drone 1 asked to climb to CLIMB_TO_M; its pose freezes at
    the first sample 0.3 m below the ceiling once pursuit began. Frozen there, the loop would command the
    climb on and the climb limit (climb_cap), computed from the frozen height, would never tighten."""
    expected = (
        f"as mocap_frozen: pose_frozen and zero velocity within {FROZEN_HOVER_S:g} s, down within "
        f"{FROZEN_DOWN_S:g} s, the true z never above the ceiling ({CEILING_M:g} m)"
    )
    fence_hi = load_fault_mission(mission_path, DURATION_S).safety.fence_hi
    spec = FaultSpec(mocap_frozen={"drone1": (T_FAULT - 2.0, CEILING_M - 0.3)})
    run = fly_with_faults(
        mission_path,
        workdir / "mocap_frozen_climbing",
        spec,
        duration_s=DURATION_S,
        safety={"fence_hi": [fence_hi[0], fence_hi[1], CEILING_M]},
        desired_z={1: -CLIMB_TO_M},
    )
    return _frozen_row(run, "mocap_frozen_climbing", expected)


ROBOT_SHIFT_M = (0.3, 0.0, 0.0)
"""robot_pose_jumps: the offset (m, Σw) the robot's pose takes at once (a body swapped with one 0.3 m off)."""


def robot_pose_frozen(mission_path: Path, workdir: Path) -> FaultResult:
    """The ground robot's pose freezes (same pose, fresh stamps) 2 s into pursuit while its law drives it."""
    spec = FaultSpec(mocap_frozen={"target": (T_FAULT, None)})
    return _robot_row(mission_path, workdir, "robot_pose_frozen", spec, "frozen")


def robot_pose_jumps(mission_path: Path, workdir: Path) -> FaultResult:
    """The ground robot's pose jumps by ROBOT_SHIFT_M 2 s into pursuit (a swapped or mislabelled body)."""
    spec = FaultSpec(mocap_shifted={"target": (T_FAULT, ROBOT_SHIFT_M)})
    return _robot_row(mission_path, workdir, "robot_pose_jumps", spec, "off what its commands explain")


def _robot_row(mission_path: Path, workdir: Path, name: str, spec: FaultSpec, why: str) -> FaultResult:
    """Fly `spec` (a lie of the robot's pose) and judge: robot_pose_suspect within 1 s of the lie, its
    reason containing `why`, the run ended with that error and every drone landed."""
    expected = (
        "robot_pose_suspect within 1 s, the robot stopped, the run ends with an error (exit code 1) and "
        "every drone lands"
    )
    run = fly_with_faults(mission_path, workdir / name, spec, duration_s=DURATION_S)
    c = Checks()
    t_f = run.backend.pose_lies_began().get("target")
    t_ev = _t(run.first("robot_pose_suspect"))
    after = None if t_ev is None or t_f is None else t_ev - t_f
    c.check(after is not None and after <= 1.0, f"robot_pose_suspect {after} s after the lie at {t_f}")
    err = None if run.rec is None else run.rec.error
    c.check(err is not None and why in err, f"run error {err!r}")
    for i in run.mission.drone_ids():
        c.check(run.first("land", i) is not None, f"drone {i} was not landed")
    details = {"event_after_ms": None if after is None else round(1e3 * after)}
    observed = f"robot_pose_suspect +{details['event_after_ms']} ms after the lie began; error {err!r}"
    # the run ends at the tick of the event, before recording it: the ticks flown before it
    ticks = None if t_ev is None else round((t_ev - run.pursuit_start) / run.mission.dt_s)
    return sim_result(
        name, expected, run, c, observed, expect_ticks=ticks, expect_error=True, details=details
    )


def _visible_again(run: SimRun, after: float) -> float | None:
    """First tick time (s) ≥ after at which drone 1 (the observer) sees the target."""
    if run.rec is None:
        return None
    k = run.rec.ticks_done
    t, vis = run.rec.t[:k], run.rec.visible[:k, 0]
    idx = np.flatnonzero((t >= after - 1e-9) & vis)
    return float(t[idx[0]]) if idx.size else None


def _held_still(run: SimRun, t_from: float, t_to: float) -> bool:
    """Every drone commanded V = 0 on every tick in [t_from, t_to)."""
    assert run.rec is not None
    k = run.rec.ticks_done
    sel = (run.rec.t[:k] >= t_from - 1e-9) & (run.rec.t[:k] < t_to - 1e-9)
    return bool(sel.any()) and bool(np.all(run.rec.V_cmd[:k][sel] == 0.0))


def occlusion_short(mission_path: Path, workdir: Path) -> FaultResult:
    """Every camera sees nothing for 1.5 s, with target_lost_hover_after = 1 s."""
    occ = Window(T_FAULT, T_FAULT + 1.5)
    hold_after = 1.0
    expected = (
        f"after target_lost_hover_after ({hold_after:g} s here) the supervisor holds every drone "
        "(target_lost_hover, V = 0); when the target reappears pursuit resumes"
    )
    run = fly_with_faults(
        mission_path,
        workdir / "occlusion_short",
        FaultSpec(occlusion=occ),
        duration_s=DURATION_S,
        safety={"target_lost_hover_after": hold_after},
    )
    c = Checks()
    t_hold = _t(run.first("target_lost_hover"))
    c.check(_near(t_hold, occ.start + hold_after), f"target_lost_hover at {t_hold}")
    t_seen = _visible_again(run, occ.end)
    c.check(_near(t_seen, occ.end), f"target seen again at {t_seen}, occlusion ended at {occ.end}")
    if run.rec is not None and t_hold is not None and t_seen is not None:
        c.check(_held_still(run, t_hold, t_seen), "drones not held still (V = 0) during the hold")
        moving = np.abs(run.rec.V_cmd[: run.rec.ticks_done][run.rec.t[: run.rec.ticks_done] > t_seen]).max()
        c.check(moving > 0.0, "no pursuit after the target reappeared")
    _flew_to_end(run, run.mission.drone_ids(), c)
    seen = "never seen again" if t_seen is None else f"seen again @{t_seen:.2f}, pursuit resumed"
    observed = f"{event_story(run)}; target {seen}"
    return sim_result("occlusion_short", expected, run, c, observed)


def occlusion_long(mission_path: Path, workdir: Path) -> FaultResult:
    """Every camera sees nothing for 5 s, with target_lost_land_after = 4.5 s (default 15 s)."""
    occ = Window(T_FAULT, T_FAULT + 5.0)
    land_after = 4.5
    expected = (
        "hold after target_lost_hover_after (3 s); the target has left every camera's view by then, so "
        f"after target_lost_land_after ({land_after:g} s here) every drone lands (target_lost_land) and "
        "the run ends when they are down"
    )
    run = fly_with_faults(
        mission_path,
        workdir / "occlusion_long",
        FaultSpec(occlusion=occ),
        duration_s=DURATION_S,
        safety={"target_lost_land_after": land_after},
    )
    c = Checks()
    hold_after = run.mission.safety.target_lost_hover_after
    t_hold = _t(run.first("target_lost_hover"))
    c.check(_near(t_hold, occ.start + hold_after), f"target_lost_hover at {t_hold}")
    t_land = _t(run.first("target_lost_land"))
    c.check(_near(t_land, occ.start + land_after), f"target_lost_land at {t_land}")
    t_seen = _visible_again(run, occ.start + 0.1)
    if run.rec is not None and t_hold is not None:
        c.check(_held_still(run, t_hold, t_seen or run.pursuit_end + 1.0), "drones not held still")
    for i in run.mission.drone_ids():
        c.check(landed_before_end(run, i), f"drone {i} did not land on target_lost_land")
    seen = "never seen again (out of view)" if t_seen is None else f"seen again @{t_seen:.2f}"
    return sim_result("occlusion_long", expected, run, c, f"{event_story(run)}; target {seen}")


def nan_neighbour(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 2's prediction messages carry NaN (estimate and μ) for 2 s."""
    bad = Window(T_FAULT, T_FAULT + 2.0)
    expected = (
        "the decoder drops and counts them (non-finite g_bar_w); drone 1 uses drone 2's last valid "
        "message until stale (0.5 s), then flies without it; no NaN reaches an estimate or a command"
    )
    run = fly_with_faults(
        mission_path,
        workdir / "nan_neighbour",
        FaultSpec(),
        duration_s=DURATION_S,
        bus_faults={"nan_sender": 2, "nan_window": bad},
    )
    c = Checks()
    injected = run.bus.injected["nan"]
    dropped = {} if run.rec is None else run.rec.bus_dropped
    ok = injected > 0 and dropped.get("non-finite g_bar_w") == injected
    c.check(ok, f"{injected} sent, dropped {dropped}")
    c.check(dropped.get("stale", 0) > 0, "drone 2's last valid message never went stale")
    _flew_to_end(run, run.mission.drone_ids(), c)
    observed = f"{injected} NaN messages sent, bus dropped {dropped}; {event_story(run)}"
    return sim_result("nan_neighbour", expected, run, c, observed)


COMPARED = ("g_wi", "g_bar_w", "V_cmd")


def foreign_mission(mission_path: Path, workdir: Path) -> FaultResult:
    """Before each of our messages, a valid message of another mission with our ids and newer seq."""
    expected = (
        "every message of the other mission is dropped and counted (other mission); "
        "the flight is identical to the same run without them"
    )
    run = fly_with_faults(
        mission_path,
        workdir / "foreign_mission",
        FaultSpec(),
        duration_s=DURATION_S,
        bus_faults={"foreign_mission": "another_mission"},
    )
    clean_dir = workdir / "foreign_mission_clean"
    clean = fly_with_faults(mission_path, clean_dir, FaultSpec(), duration_s=DURATION_S)
    c = Checks()
    injected = run.bus.injected["foreign"]
    dropped = {} if run.rec is None else run.rec.bus_dropped
    c.check(injected > 0 and dropped.get("other mission") == injected, f"{injected} sent, dropped {dropped}")
    same = (
        run.rec is not None
        and clean.rec is not None
        and all(np.array_equal(getattr(run.rec, f), getattr(clean.rec, f)) for f in COMPARED)
    )
    c.check(same, "the flight differs from the clean run")
    _flew_to_end(run, run.mission.drone_ids(), c)
    observed = (
        f"{injected} foreign messages sent, bus dropped {dropped}; flight identical to a clean run: {same}; "
        f"{event_story(run)}"
    )
    res = sim_result("foreign_mission", expected, run, c, observed)
    res.seconds += clean.seconds
    return res


def low_battery(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1 reports 10 % battery from T_FAULT + 1 s (land_battery is 15 %)."""
    t_low = T_FAULT + 1.0
    expected = "that drone: battery_land, it lands; the other drone flies on"
    run = fly_with_faults(
        mission_path, workdir / "low_battery", FaultSpec(battery={1: (t_low, 10.0)}), duration_s=DURATION_S
    )
    c = Checks()
    t_bl, land = _t(run.first("battery_land", 1)), run.first("land", 1)
    c.check(_near(t_bl, t_low), f"battery_land of drone 1 at {t_bl}")
    c.check(land is not None and land["detail"] == "battery_land", f"drone 1 land event {land}")
    _flew_to_end(run, [2], c)
    return sim_result("low_battery", expected, run, c, event_story(run))


def low_battery_takeoff(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 2 reports 20 % at takeoff (min_battery_takeoff is 30 %); drone 1 has already taken off."""
    expected = (
        "takeoff refused (battery_refuse_takeoff); the run ends with that error before pursuit and "
        "the drone already climbing lands"
    )
    run = fly_with_faults(
        mission_path,
        workdir / "low_battery_takeoff",
        FaultSpec(battery={2: (0.0, 20.0)}),
        duration_s=DURATION_S,
    )
    c = Checks()
    refused = run.first("battery_refuse_takeoff", 2)
    c.check(refused is not None, "no battery_refuse_takeoff for drone 2")
    c.check(run.first("takeoff", 2) is None, "drone 2 took off")
    err = None if run.rec is None else run.rec.error
    c.check(err is not None and "takeoff refused" in err, f"run error {err!r}")
    c.check(run.first("land", 1) is not None, "drone 1 was not landed")
    observed = event_story(run, frozenset())
    return sim_result("low_battery_takeoff", expected, run, c, observed, expect_ticks=0, expect_error=True)


ROWS: dict[str, FaultRow] = {
    "link_loss": link_loss,
    "mocap_dropout_short": mocap_dropout_short,
    "mocap_dropout_long": mocap_dropout_long,
    "occlusion_short": occlusion_short,
    "occlusion_long": occlusion_long,
    "nan_neighbour": nan_neighbour,
    "foreign_mission": foreign_mission,
    "low_battery": low_battery,
    "low_battery_takeoff": low_battery_takeoff,
    "mocap_frozen": mocap_frozen,
    "mocap_frozen_climbing": mocap_frozen_climbing,
    "robot_pose_frozen": robot_pose_frozen,
    "robot_pose_jumps": robot_pose_jumps,
}
"""The simulated rows, in table order."""
