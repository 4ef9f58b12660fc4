"""`flightstack faults`: the kill rows (flightstack/faults/rows_lab_kills.py) on the emulated lab.

Every row runs once (module fixture, about 3 min on 2 cores: three rows wait for the Tello's own 15 s
auto-land); the tests read the results and hold each measured reaction to its bound (`safety_bound`).
The kills go by pid to this module's own flight processes and their guardians only, chosen by the real
`pgrep`; nothing else on the machine is signalled.
"""

from __future__ import annotations

import shutil

import pytest

from flightstack import faults
from flightstack.faults import rows_lab_kills
from flightstack.faults.result import FaultResult
from tests.conftest import Bound

PKILL_ROWS = list(rows_lab_kills.PATTERNS)
ALONE_ROWS = ["both_killed_pursuit", "both_killed_climb", "killed_guardian_stopped"]


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict[str, FaultResult]:
    for module in ("av", "motioncapture", "pymavlink", "zenoh"):
        pytest.importorskip(module)
    if shutil.which("pgrep") is None:
        pytest.skip("no pgrep on this machine")
    out = tmp_path_factory.mktemp("faults_lab_kills")
    res = faults.run_faults(list(rows_lab_kills.ROWS), out)
    print("\n" + faults.format_table(res))
    faults.write_json(res, out / "faults.json")
    return {r.name: r for r in res}


def test_rows_are_in_the_table_in_order() -> None:
    assert list(rows_lab_kills.ROWS) == PKILL_ROWS + ALONE_ROWS
    names = list(faults.FAULTS)  # one block in the table, in this order (other modules' rows may follow)
    first = names.index(PKILL_ROWS[0])
    assert names[first : first + len(rows_lab_kills.ROWS)] == PKILL_ROWS + ALONE_ROWS


@pytest.mark.parametrize("name", PKILL_ROWS)
def test_pkill_by_name_takes_the_flight_never_its_guardian(
    results: dict[str, FaultResult], name: str, safety_bound: Bound
) -> None:
    r = results[name]
    d = r.details
    print(f"{name}: {r.observed}; guardian {d.get('guardian')}")
    assert r.handled, r.problems
    assert d["killed"] and not set(d["killed"]) & set(d["guardian"])
    for i in (1, 2):
        safety_bound(f"{d['pattern']}: drone {i} first stop", d[f"drone{i}"]["stop_ms"], 500.0)
        safety_bound(f"{d['pattern']}: drone {i} down", d[f"drone{i}"]["down_ms"], 8000.0)
    safety_bound(f"{d['pattern']}: robot disarmed", d["disarm_ms"], 2000.0)


@pytest.mark.parametrize("name", ALONE_ROWS)
def test_with_nothing_of_ours_left_no_drone_climbs_through_the_ceiling(
    results: dict[str, FaultResult], name: str, safety_bound: Bound
) -> None:
    r = results[name]
    d = r.details
    print(f"{name}: {r.observed}; largest rise {d.get('largest_rise_m')} m")
    assert r.handled, r.problems
    for i in (1, 2):
        z_max_mm = 1e3 * d[f"drone{i}"]["z_max_m"]
        safety_bound(f"{name}: drone {i} highest z", z_max_mm, 1e3 * d["ceiling_m"], "mm")
        assert d[f"drone{i}"]["auto_land"]  # nobody of ours landed it: the Tello's own timeout did
    # its own failsafes held it: the EKF's once the pose feed stopped with the flight, else the GCS failsafe
    held = d["robot_ekf_failsafe_ms"] is not None or d["robot_failsafe_ms"] is not None
    assert held and d["robot_mode"] == 4 and not d["robot_speed"], d  # HOLD (4), stopped
