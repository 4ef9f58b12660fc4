"""The emulated-lab row of `flightstack faults` whose fault is a pose that lies: drone 1's motion-capture
body frozen at the NatNet emulator (the same pose in every frame, with fresh frame numbers and stamps,
marked tracking-valid), judged on times measured at drone 1's Tello emulator (flightstack/faults/rows_lab.py
for the conventions: monotonic seconds, reaction times in ms in `FaultResult.details`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from flightstack.faults.lab_flight import (
    ZERO,
    emulator_errors,
    event_t,
    fly_inprocess,
    run_result,
    sub,
    wait_then,
    within,
)
from flightstack.faults.result import Checks, FaultResult
from flightstack.safety.drone import SUSPECT_LAND_AFTER_S
from flightstack.sim_backend.emulated_lab import EmulatedLab, command_times, first, ms, phase_times, rc_times
from flightstack.sim_backend.emulators.tello.recorded import LAND_OK_S, LAND_TOUCHDOWN_S

HOVER_S = 1.0
"""Zero velocity at the drone within this long of the freeze (s)."""
DOWN_S = 5.0
"""The drone down (its emulator's phase "landed") within this long of the freeze (s)."""


def mocap_frozen_tello(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1's motion-capture pose freezes at the NatNet emulator 1 s into pursuit."""
    wall0 = time.perf_counter()
    name = "mocap_frozen_tello"
    root = workdir / name
    marks: dict[str, float] = {}
    heights: list[tuple[float, float]] = []  # (monotonic s, drone 1's true height m) from the freeze on
    # drone 1 lands as the recorded Tello did (touchdown 2.83 s after `land`, its `ok` 1.4 s later)
    landing = {"land_s": LAND_TOUCHDOWN_S, "land_ok_s": LAND_OK_S}
    with EmulatedLab(root, duration_s=8.0, tello={1: landing}) as lab:
        e1, e2 = lab.tellos[1], lab.tellos[2]
        mission = lab.mission()
        dt, ceiling = mission.dt_s, mission.safety.fence_hi[2]

        def freeze() -> None:
            lab.natnet.faults.frozen_bodies = {lab.body(1)}

        def inject(backend: Any) -> None:  # bounded: the flight joins it
            if wait_then(lab, marks, freeze):
                t_end = time.monotonic() + DOWN_S + 1.0
                while time.monotonic() < t_end:
                    heights.append((time.monotonic(), e1.position_cm[2] / 100.0))
                    time.sleep(0.02)

        run = fly_inprocess(lab, root / "run", injector=inject)
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_f = marks.get("fault")
        c.check(t_f is not None, "the pursuit never started: nothing frozen")
        t0 = t_f if t_f is not None else run.t_start
        ev = next((e for e in run.safety("pose_frozen") if e["drone"] == 1), None)
        c.check(ev is not None, "no pose_frozen for drone 1")
        c.check(not [e for e in run.safety("pose_frozen") if e["drone"] == 2], "pose_frozen for drone 2")
        detect = sub(event_t(ev), t0)
        c.check(within(detect, HOVER_S), f"pose_frozen {detect} s after the freeze (limit {HOVER_S:g} s)")
        t_ev = event_t(ev)
        td = t_ev if t_ev is not None else t0
        t_hover = first(rc_times(e1, after=td - 0.005, value=ZERO))
        hover = sub(t_hover, t0)
        c.check(within(hover, HOVER_S), f"drone 1: rc 0 0 0 0 {hover} s after the freeze (≤ {HOVER_S:g} s)")
        moving = rc_times(e1, after=td + dt, nonzero=True)
        c.check(not moving, f"drone 1: {len(moving)} non-zero rc after pose_frozen")
        t_land = first(command_times(e1, "land", after=t0))
        t_down = first(phase_times(e1, "landed", after=t0))
        down = sub(t_down, t0)
        c.check(within(down, DOWN_S), f"drone 1 down {down} s after the freeze (limit {DOWN_S:g} s)")
        z_max = max((z for t, z in heights if t >= t0), default=float("nan"))
        c.check(z_max <= ceiling, f"drone 1 reached {z_max:.3f} m after the freeze (ceiling {ceiling:g} m)")
        why2 = [e["detail"] for e in run.safety("land", 2)]
        c.check(len(why2) == 1 and why2[0].startswith("mission complete"), f"drone 2 landed for {why2}")
        emulator_errors(lab, c)
        details = {
            "detect_ms": ms(detect),
            "rc0_after_freeze_ms": ms(hover),
            "land_after_freeze_ms": ms(sub(t_land, t0)),
            "down_after_freeze_ms": ms(down),
            "max_height_after_freeze_m": round(z_max, 3),
            "drone2_rc_after_freeze": len(rc_times(e2, after=t0, nonzero=True)),
        }
        observed = (
            f"drone 1's body frozen at the NatNet emulator: pose_frozen +{details['detect_ms']} ms; at its "
            f"emulator rc 0 0 0 0 +{details['rc0_after_freeze_ms']} ms, land "
            f"+{details['land_after_freeze_ms']} ms, down +{details['down_after_freeze_ms']} ms, highest "
            f"{details['max_height_after_freeze_m']} m (ceiling {ceiling:g} m); drone 2 sent "
            f"{details['drone2_rc_after_freeze']} non-zero rc after the freeze; end: {run.end_reason()}"
        )
        expected = (
            f"drone 1: pose_frozen, rc 0 0 0 0 and no other rc within {HOVER_S:g} s of the freeze, land "
            f"(pose_stale_land {SUSPECT_LAND_AFTER_S:g} s after it), down within {DOWN_S:g} s, never above "
            "the ceiling; drone 2 flies to the end"
        )
        return run_result(
            name,
            expected,
            observed,
            wall0,
            lab,
            run,
            c,
            details,
        )


ROWS = {"mocap_frozen_tello": mocap_frozen_tello}
"""This module's rows, in table order."""
