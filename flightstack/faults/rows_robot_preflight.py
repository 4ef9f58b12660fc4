"""Fault rows of the robot's preflight: an ArduPilot Rover that could not move indoors is refused before
anything moves, in one line that says what to set on the vehicle (drivers/lab/preflight.py `robot_rows`).

The vehicle is `spec_rover.SpecRover` on loopback (written from the MAVLink specification and ArduPilot's
source). Each row runs the preflight's robot checks against it and checks: the one refusing row is FAIL
with one line naming what to set; every other robot row is as on a vehicle set up as docs/drivers.md
says; the vehicle was neither armed nor moved out of HOLD.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path

from flightstack.faults.result import Checks, FaultResult, FaultRow

NAV_LINE = "no external position source: set on the vehicle "
ORIGIN_LINE = "no EKF origin: "


def _row(
    name: str, expected: str, check: str, starts: str, params: Mapping[str, float], origin: bool
) -> FaultResult:
    from flightstack.drivers.lab.preflight import robot_rows  # pymavlink (extra scamper): only when run
    from flightstack.drivers.scamper.link import ScamperConfig
    from flightstack.faults.spec_rover import HOLD, SpecRover

    wall0 = time.perf_counter()
    rover = SpecRover(answer_origin=origin, params=params)
    c, crash = Checks(), Checks()
    observed = ""
    try:
        rows = {r.check: r for r in robot_rows(ScamperConfig(url=f"udpout:127.0.0.1:{rover.port}"))}
        got = rows.get(check)
        crash.check(got is not None, f"no {check!r} row: {sorted(rows)}")
        if got is not None:
            observed = f"{got.status}: {got.detail}"
            c.check(got.status == "FAIL", f"{check}: {got.status}")
            c.check(got.detail.startswith(starts), f"{check}: {got.detail!r} does not start {starts!r}")
            c.check("\n" not in got.detail, f"{check}: more than one line")
        others = {k: r.status for k, r in rows.items() if k != check and r.status == "FAIL"}
        c.check(not others, f"other robot rows failed: {others}")
        moved = rover.mode != HOLD or rover.armed
        c.check(not moved, f"the vehicle was armed or left HOLD (mode {rover.mode}, armed {rover.armed})")
    finally:
        rover.close()
    return FaultResult(
        name=name,
        expected=expected,
        observed=observed + ("" if c.ok else f" ({'; '.join(c.failed)})"),
        all_safe=rover.mode == HOLD and not rover.armed,
        recording_complete=True,  # nothing flies: preflight writes nothing
        crashed=not crash.ok,
        seconds=time.perf_counter() - wall0,
        reaction_ok=c.ok,
        problems=[f"reaction: {p}" for p in c.failed] + [f"crashed: {p}" for p in crash.failed],
    )


def robot_no_origin(mission_path: Path, workdir: Path) -> FaultResult:
    """The robot never reports an EKF origin (no GPS_GLOBAL_ORIGIN after SET_GPS_GLOBAL_ORIGIN)."""
    from flightstack.faults.spec_rover import LAB_SETTINGS

    expected = (
        f"preflight's `EKF origin` row FAILs in one line starting {ORIGIN_LINE!r}; nothing armed or moved"
    )
    return _row("robot_no_origin", expected, "EKF origin", ORIGIN_LINE, LAB_SETTINGS, origin=False)


def robot_no_extnav(mission_path: Path, workdir: Path) -> FaultResult:
    """The robot keeps ArduPilot's default EKF sources (GPS, compass, baro; VISO_TYPE 0)."""
    from flightstack.faults.spec_rover import ARDUPILOT_DEFAULTS, LAB_SETTINGS

    params = {
        **LAB_SETTINGS,
        **{k: ARDUPILOT_DEFAULTS[k] for k in ARDUPILOT_DEFAULTS if k.startswith(("EK3_SRC1_", "VISO_"))},
    }
    expected = (
        f"preflight's `external navigation` row FAILs in one line starting {NAV_LINE!r} naming each parameter"
    )
    return _row("robot_no_extnav", expected, "external navigation", NAV_LINE, params, origin=True)


ROWS: dict[str, FaultRow] = {"robot_no_origin": robot_no_origin, "robot_no_extnav": robot_no_extnav}
"""The robot preflight rows, in table order."""
