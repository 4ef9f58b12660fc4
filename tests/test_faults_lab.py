"""`flightstack faults`: the emulated-lab rows (flightstack/faults/rows_lab.py, rows_lab_cli.py)
are handled, and their measured reaction times are within their limits.

Every row runs once (module fixture, about 2 min on 2 cores); the tests read the results. The rows fly the
loopback emulators of two Tellos (127.0.0.6/.7, each on a free port), NatNet and a MAVLink rover
(flightstack.sim_backend.emulators),
through the
hardware backend in this process or `flightstack fly` in a child process; clock_skew and
abort_agent_missing use Zenoh sessions on 127.0.0.1. The last tests check the harness's measurements on
hand-made emulator records (no network), including that a late reaction fails.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from flightstack import faults
from flightstack.faults import rows_lab, rows_lab_drivers
from flightstack.faults.lab_flight import drone_reaction
from flightstack.faults.result import Checks, FaultResult
from flightstack.sim_backend import emulated_lab
from flightstack.sim_backend.emulated_lab import LabUnavailableError, command_times, max_gap, rc_times
from tests.conftest import Bound

LAB_ROWS = [
    "link_loss_uplink",
    "loop_stall",
    "driver_thread_error",
    "land_reply_lost",
    "sighup",
    "double_sigint",
    "disk_full",
    "robot_not_moving",
    "auto_land_in_flight",
    "raised_surface",
    "mocap_frozen_tello",
    "clock_skew",
    "abort_during_takeoff",
    "abort_agent_missing",
    "process_killed",
    "agent_stopped",
    "guardian_killed",
]


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict[str, FaultResult]:
    for module in ("av", "motioncapture", "pymavlink", "zenoh"):
        pytest.importorskip(module)
    out = tmp_path_factory.mktemp("faults_lab")
    res = faults.run_faults(LAB_ROWS, out)
    print("\n" + faults.format_table(res))
    faults.write_json(res, out / "faults.json")
    return {r.name: r for r in res}


def test_lab_rows_are_in_the_table_in_order() -> None:
    assert list(rows_lab.ROWS) == LAB_ROWS
    names = list(faults.FAULTS)
    assert [n for n in names if n in LAB_ROWS] == LAB_ROWS
    assert "flightstack.faults.rows_lab" in faults.ROW_MODULES


@pytest.mark.parametrize("name", LAB_ROWS)
def test_row_handled(results: dict[str, FaultResult], name: str) -> None:
    r = results[name]
    assert r.handled, "\n".join([r.observed, *r.problems])
    assert r.problems == [] and r.expected and r.observed and r.seconds > 0


def test_faults_json_reports_the_reaction_times(results: dict[str, FaultResult], tmp_path: Path) -> None:
    faults.write_json(list(results.values()), tmp_path / "faults.json")
    doc = json.loads((tmp_path / "faults.json").read_text())
    by_name = {r["name"]: r for r in doc["results"]}
    assert by_name["link_loss_uplink"]["details"]["land_after_detect_ms"] > 0
    assert by_name["sighup"]["details"]["drone1"]["land_ms"] > 0


# ---- the measured numbers against their limits (ms) ---------------------------------------------------
def test_link_loss_with_a_working_uplink(results: dict[str, FaultResult], safety_bound: Bound) -> None:
    d = results["link_loss_uplink"].details
    assert d["detect_ms"] >= 800.0  # link_timeout_s 1 s after the last state packet, not earlier
    safety_bound("link loss detected after the last state packet", d["detect_ms"], 1250.0)
    safety_bound("hover after the detection (two ticks)", d["rc0_after_detect_ms"], 100.0)
    safety_bound("land after the detection", d["land_after_detect_ms"], 1000.0)
    assert d["land_sends"] >= 2  # re-sent about every 1 s
    safety_bound("land re-sent after the previous one", max(d["land_resend_ms"]), 1300.0)
    safety_bound("the other drone's largest rc gap (flies on)", d["drone2_max_rc_gap_ms"], 150.0)


def test_loop_stall_hovers_then_lands(results: dict[str, FaultResult], safety_bound: Bound) -> None:
    d = results["loop_stall"].details
    assert d["stall_ms"] >= 2900.0
    for i in (1, 2):
        one = d[f"drone{i}"]
        safety_bound(
            f"drone {i} hover after the loop's last rc (0.5 s + 0.1 s)", one["hover_after_last_rc_ms"], 600.0
        )
        safety_bound(
            f"drone {i} land after the loop's last rc (2 s + 0.3 s)", one["land_after_last_rc_ms"], 2300.0
        )
        assert one["down_after_last_rc_ms"] is not None


def test_driver_threads_count_errors_and_keep_going(
    results: dict[str, FaultResult], safety_bound: Bound
) -> None:
    d = results["driver_thread_error"].details
    counted = d["errors_counted"]
    assert counted["state receiver"] == rows_lab_drivers.INJECTED["state receiver recv_error"]
    for i in (1, 2):
        assert (
            counted[f"drone {i} command channel (send)"]
            == rows_lab_drivers.INJECTED["command channel send_error"]
        )
        assert counted[f"drone {i} monitor"] == rows_lab_drivers.INJECTED["monitor_error"]
        assert counted[f"drone {i} video"] == rows_lab_drivers.INJECTED["video recv_error"]
    assert counted["robot link"] == rows_lab_drivers.INJECTED["robot send_error"]
    assert all(d["threads_alive"].values()) and len(d["threads_alive"]) == 10
    safety_bound("largest rc gap while driver threads fail", max(d["max_rc_gap_ms"].values()), 350.0)
    assert d["robot_setpoints_after_errors"] > 0


def test_lost_land_replies_never_block_a_safety_tick(
    results: dict[str, FaultResult], safety_bound: Bound
) -> None:
    d = results["land_reply_lost"].details
    safety_bound(
        "longest safety tick with land replies lost (one period)", d["safety_tick_ms"]["max_ms"], 50.0
    )
    assert d["land_replies_received"] == 0
    safety_bound("land after the fence", d["land_after_fence_ms"], 500.0)
    safety_bound("hover after the fence", d["rc0_after_fence_ms"], 100.0)
    safety_bound("drone 2's largest rc gap while drone 1 lands", d["drone2_max_rc_gap_ms"], 150.0)
    assert d["down_after_fence_ms"] >= 1900.0  # the slow landing (2 s) really was in progress


@pytest.mark.parametrize("name", ["sighup", "double_sigint"])
def test_signals_land_every_drone_and_exit_130(
    results: dict[str, FaultResult], name: str, safety_bound: Bound
) -> None:
    d = results[name].details
    assert d["exit_code"] == 130
    for i in (1, 2):
        safety_bound(f"{name}: drone {i} hover after the signal", d[f"drone{i}"]["rc0_ms"], 500.0)
        safety_bound(f"{name}: drone {i} land after the signal", d[f"drone{i}"]["land_ms"], 500.0)
    if name == "double_sigint":
        assert (
            15.0 <= d["second_signal_after_ms"] <= 200.0
        )  # the row's own timing: the second came mid-landing


def test_disk_full_stops_the_recording_not_the_flight(results: dict[str, FaultResult]) -> None:
    d = results["disk_full"].details
    assert d["ticks_flown"] == 100 and 0 <= d["ticks_written"] < 100
    assert d["recording"]["complete"] is False and "No space left" in d["recording"]["reason"]


def test_a_robot_that_does_not_move_stops_the_mission_before_takeoff(results: dict[str, FaultResult]) -> None:
    d = results["robot_not_moving"].details
    assert d["takeoffs_sent"] == {"1": 0, "2": 0} or d["takeoffs_sent"] == {1: 0, 2: 0}
    assert d["robot_moved_m"] < 0.005


def test_skewed_clocks_fuse_and_go_stale_alike(results: dict[str, FaultResult]) -> None:
    d = results["clock_skew"].details
    stale = d["stale_after_last_send_ms"]
    assert set(stale) == {"+0 s", "+600 s", "-600 s"}
    assert max(stale.values()) - min(stale.values()) < 30.0
    assert all(270.0 < v < 400.0 for v in stale.values())
    assert not any(d["unfused"].values())


def test_abort_during_takeoff(results: dict[str, FaultResult], safety_bound: Bound) -> None:
    d = results["abort_during_takeoff"].details
    assert d["abort_exit_code"] == 0 and sorted(d["ack_ms"]) == ["1", "2"]
    safety_bound("abort: drone 1 land", d["drone1_after_abort"]["land_ms"], 500.0)
    safety_bound("abort: drone 1 hover", d["drone1_after_abort"]["rc0_ms"], 500.0)
    safety_bound("abort: drone 2 land while it takes off", d["drone2_first_land_after_abort_ms"], 500.0)
    assert d["drone2_takeoff_done_after_abort_ms"] > 1000.0  # the abort came during its takeoff
    safety_bound(
        "abort: drone 2 land after its takeoff ended", d["drone2_after_its_takeoff"]["land_ms"], 500.0
    )
    assert d["fly_exit_code"] == 1


def test_abort_names_the_missing_agent(results: dict[str, FaultResult]) -> None:
    d = results["abort_agent_missing"].details
    assert d["exit_code"] == 1 and sorted(d["ack_ms"]) == ["1", "2"]
    assert d["control_exit_code"] == 0 and sorted(d["control_ack_ms"]) == ["1", "2", "3"]
    assert "agents [3] did not acknowledge" in results["abort_agent_missing"].observed


# ---- the harness, without a network ---------------------------------------------------------------------
def _emu(
    rc: list[tuple[float, tuple[int, int, int, int]]],
    commands: list[tuple[float, str]],
    landed_at: float = 2.0,
) -> SimpleNamespace:
    """What a TelloEmulator records (times in s): rc_history, commands, phase_log."""
    return SimpleNamespace(
        rc_history=rc, commands=commands, phase_log=[(0.0, "flying"), (landed_at, "landed")]
    )


def test_measurements_on_emulator_records() -> None:
    emu = _emu(
        [(0.95, (10, 0, 0, 0)), (1.0, (0, 0, 0, 0)), (1.05, (0, 0, 0, 0)), (1.6, (0, 0, 0, 0))],
        [(1.0, "rc 0 0 0 0"), (1.2, "land"), (2.2, "land")],
    )
    assert rc_times(emu, after=0.9, value=(0, 0, 0, 0)) == [1.0, 1.05, 1.6]
    assert rc_times(emu, nonzero=True) == [0.95]
    assert command_times(emu, "land", after=1.2) == [2.2]
    assert max_gap([1.0, 1.05, 1.6], 1.0, 2.0) == pytest.approx(0.55)
    assert max_gap([], 1.0, 2.0) == pytest.approx(1.0)


def test_a_late_reaction_fails_the_row() -> None:
    """The check the signal and abort rows apply: a land 0.8 s after the signal fails (limit 0.5 s), and
    so does a non-zero rc after it."""
    on_time = _emu([(10.001, (0, 0, 0, 0))], [(10.15, "land")], landed_at=10.5)
    late = _emu([(10.001, (0, 0, 0, 0)), (10.3, (20, 0, 0, 0))], [(10.8, "land")], landed_at=11.1)
    c = Checks()
    drone_reaction(on_time, 10.0, c, "on time")
    assert c.ok
    drone_reaction(late, 10.0, c, "late")
    assert [p.split(":")[0] for p in c.failed] == ["late", "late"]  # the land and the non-zero rc


def test_without_an_optional_package_the_lab_says_which(monkeypatch: pytest.MonkeyPatch) -> None:
    """The emulators ship in the package; what can be missing is an optional dependency."""
    monkeypatch.setitem(sys.modules, "pymavlink", None)  # `import pymavlink` now raises ImportError
    with pytest.raises(LabUnavailableError, match="pymavlink"):
        emulated_lab.load_emulators()


def test_a_killed_process_is_landed_by_its_guardian(
    results: dict[str, FaultResult], safety_bound: Bound
) -> None:
    """Parent killed -> rc 0 0 0 0 <= 0.5 s and land <= 2 s at the emulators, robot disarmed."""
    d = results["process_killed"].details
    for i in (1, 2):
        safety_bound(f"flight killed: drone {i} hover", d[f"drone{i}"]["rc0_ms"], 500.0)
        safety_bound(f"flight killed: drone {i} land", d[f"drone{i}"]["land_ms"], 2000.0)
        assert d[f"drone{i}"]["down_ms"] is not None
    assert d["robot_armed"] is False and d["robot_speed"] < 1e-6


def test_a_stopped_process_is_taken_over_and_muted_after_it_resumes(
    results: dict[str, FaultResult], safety_bound: Bound
) -> None:
    d = results["agent_stopped"].details
    for i in (1, 2):
        assert d[f"drone{i}"]["rc0_ms"] >= 400, d  # the guardian's 0.5 s stall bound, not earlier
        safety_bound(f"flight stopped: drone {i} hover by the guardian", d[f"drone{i}"]["rc0_ms"], 800.0)
        safety_bound(f"flight stopped: drone {i} land by the guardian", d[f"drone{i}"]["land_ms"], 2500.0)
    assert d["exit_code"] not in (0, None)


def test_a_killed_guardian_lands_the_flight(results: dict[str, FaultResult], safety_bound: Bound) -> None:
    d = results["guardian_killed"].details
    assert d["exit_code"] == 1
    for i in (1, 2):
        safety_bound(f"guardian killed: drone {i} stopped", d[f"drone{i}"]["stop_ms"], 500.0)
        safety_bound(f"guardian killed: drone {i} down", d[f"drone{i}"]["down_ms"], 8000.0)
