"""Will the Scamper stop by itself when flightstack's heartbeat stops?  The rule over its ArduPilot
GCS-failsafe parameters (`judge_gcs_failsafe`, pure: no I/O) and what to read for it.

ArduPilot Rover's GCS failsafe (the parameters and their semantics, with the ArduPilot sources, are
written down where the emulator implements them: sim_backend/emulators/rover/): once no
HEARTBEAT came from the GCS system id (``SYSID_MYGCS``; newer firmware ``MAV_GCS_SYSID`` ..
``MAV_GCS_SYSID_HI``) for ``FS_GCS_TIMEOUT`` s and that lasted ``FS_TIMEOUT`` s more, Rover takes
``FS_ACTION`` — if ``FS_GCS_ENABLE`` is on.

The decisions (the lab's Scamper must be set to FS_GCS_ENABLE 1, FS_ACTION 2, FS_GCS_TIMEOUT 3,
FS_TIMEOUT 1, SYSID_MYGCS / MAV_GCS_SYSID 255):

* FAIL when any of the parameters could not be read (naming them): unknown is not safe.
* ``FS_GCS_ENABLE``: 0 FAILs (no failsafe); 1 passes; 2 passes (it differs from 1 only for an AUTO
  mission, and flightstack drives in GUIDED); anything else FAILs.
* ``FS_ACTION``: 2 Hold passes (stops and stays stopped, armed); 5 Terminate passes (disarms: the motors
  stop).  0 Nothing, 1 RTL, 3 SmartRTL or RTL, 4 SmartRTL or Hold and 6 Loiter or Hold FAIL: each keeps
  the robot driving on its own (its last set-point until Guided's 3 s timeout, back toward home, or to
  hold a position), among people and under the drones, with nobody commanding it.
* Delay ``FS_GCS_TIMEOUT + FS_TIMEOUT`` (s from our last heartbeat to the action): FAIL above
  `MAX_FAILSAFE_DELAY_S` = 5 s.  At the paper's 0.1 m/s the robot moves at most 0.5 m (half a square
  side) in that time, inside the fence's margin; ArduPilot's defaults (5 + 1.5 s) are over it.  WARN
  below 3 heartbeat periods (3 s): two lost 1 Hz heartbeats in a row (Wi-Fi) would then hold the robot
  mid-run.  A negative or non-finite value FAILs.
* The GCS system id must include every system id flightstack sends its heartbeats from (the driver's
  ``ScamperConfig.source_system``, the guardian's ``robot_source``): otherwise the failsafe watches
  another ground station, and ours stopping goes unnoticed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

from flightstack.drivers.scamper.link import GCS_HEARTBEAT_PERIOD_S

Status = Literal["PASS", "WARN", "FAIL"]

FS_GCS_ENABLE = "FS_GCS_ENABLE"
FS_ACTION = "FS_ACTION"
FS_TIMEOUT = "FS_TIMEOUT"
FS_GCS_TIMEOUT = "FS_GCS_TIMEOUT"
SYSID_MYGCS = "SYSID_MYGCS"  # the GCS system id of older firmware
MAV_GCS_SYSID = "MAV_GCS_SYSID"  # newer firmware, with MAV_GCS_SYSID_HI
MAV_GCS_SYSID_HI = "MAV_GCS_SYSID_HI"
REQUIRED = (FS_GCS_ENABLE, FS_ACTION, FS_TIMEOUT, FS_GCS_TIMEOUT)
PARAMETERS = (*REQUIRED, SYSID_MYGCS, MAV_GCS_SYSID, MAV_GCS_SYSID_HI)  # what preflight reads

MAX_FAILSAFE_DELAY_S = 5.0  # FS_GCS_TIMEOUT + FS_TIMEOUT above this FAILs (module docstring)
MIN_FAILSAFE_DELAY_S = 3.0 * GCS_HEARTBEAT_PERIOD_S  # below this WARNs: 2 lost heartbeats would trip it
ENABLE_OK = {1: "enabled", 2: "enabled (an AUTO mission would continue)"}
ACTION_STOPS = {2: "Hold", 5: "Terminate (disarms)"}
ACTION_DRIVES = {
    0: "Nothing: it keeps its last set-point",
    1: "RTL: it drives back home",
    3: "SmartRTL or RTL: it drives back home",
    4: "SmartRTL or Hold: it drives back along its path",
    6: "Loiter or Hold: it drives to hold its position",
}
NEEDED = {FS_GCS_ENABLE: 1, FS_ACTION: 2, FS_GCS_TIMEOUT: 3, FS_TIMEOUT: 1}  # what to set (docs/drivers.md)


@dataclass(frozen=True)
class FailsafeVerdict:
    """The rule's answer: status, and one line per finding (problems first)."""

    status: Status
    findings: tuple[str, ...]

    @property
    def detail(self) -> str:
        return "; ".join(self.findings)


def enough(values: Mapping[str, float]) -> bool:
    """A read may stop: every required parameter and one GCS system id (with its _HI) answered."""
    sysid = SYSID_MYGCS in values or (MAV_GCS_SYSID in values and MAV_GCS_SYSID_HI in values)
    return sysid and all(n in values for n in REQUIRED)


def _fmt(v: float) -> str:
    return f"{v:g}"


def _integer(v: float) -> int | None:
    return int(v) if math.isfinite(v) and v == math.floor(v) else None


def judge_gcs_failsafe(values: Mapping[str, float], our_sysids: Mapping[str, int]) -> FailsafeVerdict:
    """Judge the parameters that were read (`values`, by name; an absent name was not read).

    our_sysids: who sends heartbeats with which MAVLink system id, e.g. {"flightstack": 255, "guardian":
    255}.  Returns FAIL, WARN or PASS with the findings (module docstring's rules).
    """
    fails: list[str] = []
    warns: list[str] = []
    notes: list[str] = []
    missing = [n for n in REQUIRED if n not in values]
    if SYSID_MYGCS not in values and MAV_GCS_SYSID not in values:
        missing.append(f"{SYSID_MYGCS} (or {MAV_GCS_SYSID})")
    if missing:
        fails.append(f"could not read {', '.join(missing)}")

    if FS_GCS_ENABLE in values:
        v = values[FS_GCS_ENABLE]
        e = _integer(v)
        if e in ENABLE_OK:
            notes.append(f"{FS_GCS_ENABLE} {e} ({ENABLE_OK[e]})")
        else:
            why = "disabled: the robot ignores our heartbeat stopping" if e == 0 else "not a known value"
            fails.append(f"{FS_GCS_ENABLE} = {_fmt(v)} ({why}), needed {NEEDED[FS_GCS_ENABLE]}")

    if FS_ACTION in values:
        v = values[FS_ACTION]
        a = _integer(v)
        if a in ACTION_STOPS:
            notes.append(f"{FS_ACTION} {a} ({ACTION_STOPS[a]})")
        else:
            why = (
                f"{ACTION_DRIVES[a]} when our heartbeat stops" if a in ACTION_DRIVES else "not a known action"
            )
            fails.append(f"{FS_ACTION} = {_fmt(v)} ({why}), needed {NEEDED[FS_ACTION]} (Hold)")

    if FS_GCS_TIMEOUT in values and FS_TIMEOUT in values:
        lost, persist = values[FS_GCS_TIMEOUT], values[FS_TIMEOUT]
        delay = lost + persist
        what = f"{FS_GCS_TIMEOUT} {_fmt(lost)} + {FS_TIMEOUT} {_fmt(persist)}"
        needed = f"{FS_GCS_TIMEOUT} {NEEDED[FS_GCS_TIMEOUT]}, {FS_TIMEOUT} {NEEDED[FS_TIMEOUT]}"
        if not (math.isfinite(lost) and math.isfinite(persist) and lost >= 0.0 and persist >= 0.0):
            fails.append(f"{what} (not a valid time), needed {needed}")
        elif delay > MAX_FAILSAFE_DELAY_S:
            fails.append(
                f"{what} = {_fmt(delay)} s from our last heartbeat to the failsafe (more than "
                f"{_fmt(MAX_FAILSAFE_DELAY_S)} s), needed {needed}"
            )
        elif delay < MIN_FAILSAFE_DELAY_S:
            warns.append(
                f"{what} = {_fmt(delay)} s (two lost heartbeats, {_fmt(GCS_HEARTBEAT_PERIOD_S)} s apart, "
                f"would hold the robot mid-run), enough: {needed}"
            )
        else:
            notes.append(f"acts {_fmt(delay)} s after our last heartbeat ({what})")

    sysid_name = MAV_GCS_SYSID if MAV_GCS_SYSID in values else SYSID_MYGCS
    if sysid_name in values:
        v = values[sysid_name]
        lo = _integer(v)
        hi_v = values.get(MAV_GCS_SYSID_HI) if sysid_name == MAV_GCS_SYSID else None
        hi = None if hi_v is None else _integer(hi_v)
        ids = sorted(set(our_sysids.values()))
        accepted = range(0) if lo is None else range(lo, (hi if hi is not None and hi >= lo else lo) + 1)
        shown = f"{sysid_name} {_fmt(v)}" + (f"..{MAV_GCS_SYSID_HI} {hi}" if len(accepted) > 1 else "")
        strangers = {who: s for who, s in our_sysids.items() if s not in accepted}
        if strangers:
            ours = ", ".join(f"{who} {s}" for who, s in strangers.items())
            need = f"{ids[0]}" + (f", {MAV_GCS_SYSID_HI} {ids[-1]}" if len(ids) > 1 else "")
            fails.append(
                f"{shown} (the failsafe watches another ground station, not the heartbeats of {ours}), "
                f"needed {need}"
            )
        else:
            notes.append(f"{shown} = our system id")

    status: Status = "FAIL" if fails else ("WARN" if warns else "PASS")
    return FailsafeVerdict(status, tuple(fails + warns + notes))
