"""drivers/tello/ against the loopback Tello emulator (sim_backend/emulators/tello/), on 127.0.0.x only.

Every scenario of issue 14 is flown through the emulator with one of its real-firmware fault switches,
and judged at the emulator: nothing sent that the drone rejected or ignored in its phase
(`emu.refused == []`), the driver's phase equal to the drone's after every driver call, takeoff()
returning only when the drone is airborne, no auto-land while the mission flies.

Each emulator sends its state stream to its own free port (the driver's `state_port`), so these tests
do not need UDP 8889/8890 (djitellopy, used by other tests for its own client, binds them).
"""

from __future__ import annotations

import re
import socket
import threading
import time
from typing import Any

import numpy as np
import pytest

pytest.importorskip("av")

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.drivers.tello.camera import TelloCamera
from flightstack.drivers.tello.config import TelloCommandError, TelloConfig, TelloLinkError
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.rc import velocity_to_rc
from flightstack.drivers.tello.sdk_video import VideoSetting
from flightstack.hal import FlightPhase
from flightstack.paper.geometry import Pose, rot_z
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.net import wait_until
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from flightstack.sim_backend.emulators.tello.recorded import H_DRIFT_CM_S, H_DRIFT_MAX_CM
from flightstack.sim_backend.scene.render import RenderOptions, render_markers
from flightstack.vision.camera_file import load_calibration
from flightstack.vision.markers import extract_markers
from tests.conftest import MISSIONS, Bound, tello_config, tello_emulator

CAL = load_calibration(MISSIONS / "cameras" / "tello_down_sim.yaml")
P0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])
# the target 0.9 m below the drone (downward camera, as the observing drone flies), slightly yawed
G_I0 = Pose.make([0.05, -0.03, -0.9], 0.3)
# the emulator's phase names -> hal.FlightPhase values
AS_DRIVER = {"landed": "ground", "takeoff": "taking_off", "flying": "flying", "landing": "landing"}


def marker_truth() -> tuple[np.ndarray, np.ndarray]:
    """Centres and normals (the target's z axis) of the markers in the downward camera's frame."""
    R_ic = CAMERA_MOUNTS["down"]
    centres = (P0 @ rot_z(G_I0.theta).T + G_I0.p) @ R_ic
    normals = np.tile(R_ic.T @ np.array([0.0, 0.0, 1.0]), (4, 1))
    return centres, normals


def marker_frame(t: float, emu: TelloEmulator) -> np.ndarray:
    centres, normals = marker_truth()
    img, _, _ = render_markers(CAL, centres, normals, RenderOptions(marker_radius_m=0.03))
    return img


def make_emulator(ip: str = "127.0.0.3", **kw: Any) -> TelloEmulator:
    """conftest.tello_emulator (state and video to free ports of 127.0.0.1, see the module docstring) with
    a fast takeoff (FAST_TAKEOFF_S) unless `kw` names one: the recorded 8.7 s would add 8.4 s to each of
    these flights; the tests that are about the takeoff's duration set their own."""
    kw.setdefault("takeoff_s", FAST_TAKEOFF_S)
    return tello_emulator(ip, **kw)  # type: ignore[no-any-return]


def config(emu: TelloEmulator, **kw: object) -> TelloConfig:
    """tello_config with a shorter link timeout (0.5 s) and keep-alive (1 s) for these tests."""
    return tello_config(emu, **{"link_timeout_s": 0.5, "keepalive_s": 1.0, **kw})


@pytest.fixture
def emu():
    e = make_emulator(frame_source=marker_frame, fps=30.0, video_size=(CAL.width, CAL.height))
    e.start()
    yield e
    e.close()


def agree(d: TelloDriver, emu: TelloEmulator) -> None:
    assert d.phase.value == AS_DRIVER[emu.phase], (d.phase, emu.phase, d.events[-5:])


def fly(d: TelloDriver, emu: TelloEmulator, seconds: float = 1.0) -> dict[str, float]:
    """connect, takeoff, rc at 20 Hz for `seconds`, land; phase agreement after every call.

    Returns the times (s) to confirm takeoff and land from telemetry."""
    d.connect()
    agree(d, emu)
    t0 = time.monotonic()
    d.takeoff()
    t_takeoff = time.monotonic() - t0
    assert emu.phase == "flying", "takeoff() returned before the drone was airborne"
    agree(d, emu)
    n = len(emu.rc_history)
    for k in range(round(20 * seconds)):
        d.send_body_velocity(np.array([0.2 * np.sin(k / 5), 0.0, 0.0, 0.0]))
        time.sleep(0.05)
    assert wait_until(lambda: len(emu.rc_history) - n >= round(20 * seconds) - 1, 1.0)
    t0 = time.monotonic()
    d.land()
    t_land = time.monotonic() - t0
    agree(d, emu)
    assert emu.phase == "landed"
    return {"takeoff_s": t_takeoff, "land_s": t_land}


def assert_clean(d: TelloDriver, emu: TelloEmulator) -> None:
    assert emu.refused == [], emu.refused  # nothing the drone rejected or ignored in its phase
    assert not emu.landed_by_timeout
    assert emu.errors == []


# ---- the happy path, video, link ---------------------------------------------------------------------
def test_short_flight_rc_values_and_video(safety_bound: Bound, emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu, downward_camera=True))
    try:
        d.connect()
        assert d.sdk_version == "3.0" and d.serial
        checks = {c.name: c for c in d.preflight()}
        assert all(c.ok for c in checks.values()), checks
        assert "SDK 3.0" in checks["firmware"].detail and d.serial in checks["firmware"].detail
        d.takeoff()
        assert emu.phase == "flying" and d.state().flying and d.state().link_alive
        sent = []
        for V in ([0.3, 0.0, 0.0, 0.0], [0.0, -0.25, 0.1, 0.0], [0.1, 0.1, 0.0, 0.5], [0.0, 0.0, 0.0, -0.35]):
            t0 = time.monotonic()
            d.send_body_velocity(np.array(V))
            safety_bound("send_body_velocity returns (fire and forget)", 1e3 * (time.monotonic() - t0), 10.0)
            sent.append(velocity_to_rc(np.array(V), d.cfg.rc_gains))
            time.sleep(0.3)
        assert wait_until(lambda: len(emu.rc_history) >= 4, 2.0)
        # a loaded computer may stretch a 0.3 s sleep past the loop watchdog's 0.5 s: its hover
        # (rc 0 0 0 0, event loop_silent_hover) is then between the commands, and is not what is tested
        hovers = [rc for _, rc in emu.rc_history if rc == (0, 0, 0, 0)]
        assert len(hovers) <= sum(e.kind == "loop_silent_hover" for e in d.events)
        got = [rc for _, rc in list(emu.rc_history) if rc != (0, 0, 0, 0)][-4:]
        assert got == sent  # forward → b > 0, right (−v_y) → a > 0, ccw yaw → d < 0
        assert got[0] == (0, 30, 0, 0) and got[1] == (25, 0, 10, 0) and got[3][3] == 20
        # video: ≥ 30 decoded frames through PyAV, markers within 2 px of the render truth
        cam = TelloCamera(d, frame_timeout_s=10.0)
        cam.start()
        _, true_px, _ = render_markers(CAL, *marker_truth(), RenderOptions(marker_radius_m=0.03))
        errors = []
        deadline = time.monotonic() + 20
        while cam.frames_seen < 30 and time.monotonic() < deadline:
            f = cam.latest()
            if f is not None and f.image is not None and f.image.shape == (CAL.height, CAL.width, 3):
                det = extract_markers(f.image, CAL)
                if det.pixels is not None:
                    errors.append(np.linalg.norm(det.pixels - true_px, axis=1).max())
            time.sleep(0.01)
        cam.stop()
        assert emu.downvision  # the driver switched the EDU to its downward camera
        assert cam.frames_seen >= 30
        assert len(errors) >= 20 and max(errors) < 2.0, (len(errors), max(errors, default=None))
        d.land()
        agree(d, emu)
        assert not d.state().flying
        assert_clean(d, emu)
    finally:
        d.close()


def test_connect_to_a_silent_drone_fails_fast_naming_the_ip(emu: TelloEmulator) -> None:
    emu.faults.silent = True
    emu.faults.drop_state = True
    d = TelloDriver(config(emu, connect_timeout_s=1.0))
    t0 = time.monotonic()
    with pytest.raises(TelloLinkError, match=r"127\.0\.0\.3"):
        d.connect()
    assert time.monotonic() - t0 < 3.0
    d.close()


def test_state_stream_loss_is_detected_and_reported(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu))
    try:
        d.connect()
        assert d.state().link_alive
        emu.faults.drop_state = True
        assert wait_until(lambda: not d.state().link_alive, 2.0)
        assert wait_until(lambda: any(e.kind == "link_lost" for e in d.events), 1.0)
        emu.faults.drop_state = False
        assert wait_until(lambda: d.state().link_alive, 2.0)
        assert wait_until(lambda: any(e.kind == "link_restored" for e in d.events), 1.0)
    finally:
        d.close()


def test_bad_and_foreign_state_datagrams_are_dropped_and_counted(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu))
    try:
        d.connect()
        rx = d.link.rx
        assert rx is not None
        dest = ("127.0.0.1", emu.state_port)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as same_ip:
            same_ip.bind((emu.ip, 0))  # spoofing the drone's address from another port: still parsed
            for junk in (b"\xff\xfe\x00", b"h:nan;tof:10;vgz:0;time:0;bat:50;", b"h:1e9;", b"x" * 4000):
                same_ip.sendto(junk, dest)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
            stranger.bind(("127.0.0.9", 0))
            stranger.sendto(b"h:500;tof:510;vgz:0;time:99;bat:5;temph:60;", dest)
        assert wait_until(lambda: sum(rx.dropped.values()) >= 5, 2.0), rx.dropped
        assert rx.dropped["unknown_sender"] == 1
        assert rx.dropped["not_ascii"] == 1 and rx.dropped["too_long"] == 1
        time.sleep(0.3)
        assert d.state().link_alive and d.phase.value == "ground"  # the stranger's 5 m did not count
        assert d.state().battery_pct == emu.battery
    finally:
        d.close()


def hover_for(d: TelloDriver, seconds: float) -> list[tuple[float, bool]]:
    """The loop's zero velocity every 0.05 s for `seconds`; (h in cm, link alive) at each tick."""
    seen = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        d.send_body_velocity(np.zeros(4))
        seen.append((d.current_state()["h"], d.state().link_alive))
        time.sleep(0.05)
    return seen


def test_h_drifting_down_to_minus_3000_cm_keeps_the_link_and_is_flagged_once() -> None:
    """Before: state lines whose h ran below −1000 cm were all rejected, the link went silent and land()
    sent 30 lands. Here the emulator's h drifts at −20 m/s to −3000 cm (true height 80 cm): every line
    parses, the link never drops, `state_implausible` names h once, and one land brings the drone down."""
    with make_emulator(h_drift_cm_s=-2000.0, h_drift_max_cm=3080.0) as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            d.takeoff()
            seen = hover_for(d, 2.5)
            d.land()
        finally:
            d.close()
    lowest = min(h for h, _ in seen)
    flagged = [e.detail for e in d.events if e.kind == "state_implausible"]
    print(
        f"h down to {lowest:.0f} cm; state_implausible: {flagged}; dropped {d.link.rx and d.link.rx.dropped}"
    )
    assert lowest == -3000 and all(alive for _, alive in seen)
    assert len(flagged) == 1 and flagged[0].startswith("h=-") and "outside [-1000, 3000]" in flagged[0]
    assert not [e for e in d.events if e.kind in ("link_lost", "state_rejected_run")]
    assert d.counts["state_implausible"] > 10  # every such line counted, one event
    assert emu.command_texts().count("land") == 1
    assert_clean(d, emu)


def test_400_s_of_the_recorded_h_drift_keep_the_link_quiet() -> None:
    """The recorded drift (−3.5 cm/s) over 400 s, compressed 200-fold into 2 s of flight: the emulator
    holds it at the recorded 70 cm (recorded.H_DRIFT_MAX_CM), so h never leaves its plausible bounds, the
    link stays up and nothing is flagged (before: h passed −1000 cm after ~290 s and the link went silent)."""
    with make_emulator(h_drift_cm_s=200 * H_DRIFT_CM_S) as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            d.takeoff()
            seen = hover_for(d, 2.0)
            d.land()
        finally:
            d.close()
    print(f"h {min(h for h, _ in seen):.0f} … {max(h for h, _ in seen):.0f} cm at a true 80 cm")
    assert seen[-1][0] == 80 - H_DRIFT_MAX_CM  # hovering at 80 cm, h 70 cm low
    assert min(h for h, _ in seen) >= -H_DRIFT_MAX_CM and all(alive for _, alive in seen)
    assert not [e for e in d.events if e.kind in ("link_lost", "state_implausible", "state_rejected_run")]
    assert emu.command_texts().count("land") == 1
    assert_clean(d, emu)


def test_a_run_of_rejected_state_lines_is_an_event_and_the_link_loss_says_why(emu: TelloEmulator) -> None:
    """The drone keeps sending, but nothing it sends parses (here `h:nan`) for longer than the link timeout
    (0.5 s in these tests): one `state_rejected_run` with the reason counts per run, and the `link_lost`
    it causes names the rejected datagrams instead of calling the drone silent."""
    d = TelloDriver(config(emu))

    def garbage(seconds: float) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as drone:
            drone.bind((emu.ip, 0))  # the drone's address: its datagrams, rejected by the parser
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                drone.sendto(b"h:nan;tof:10;vgz:0;time:0;bat:50;", ("127.0.0.1", emu.state_port))
                time.sleep(0.05)

    try:
        d.connect()
        for run in (1, 2):
            emu.faults.drop_state = True
            garbage(1.2)
            runs = [e.detail for e in d.events if e.kind == "state_rejected_run"]
            lost = [e.detail for e in d.events if e.kind == "link_lost"]
            assert len(runs) == run and len(lost) == run, (runs, lost)
            span = re.search(r"over ([0-9.]+) s", runs[-1])
            assert span is not None and 0.5 <= float(span.group(1)) < 1.2, runs
            assert "none valid (not_finite " in runs[-1], runs
            assert lost[-1].startswith("no valid state packet for") and "not_finite" in lost[-1], lost
            emu.faults.drop_state = False
            assert wait_until(lambda: d.state().link_alive, 2.0)
        print(f"runs: {runs}; link_lost: {lost}")
    finally:
        d.close()


def test_low_battery_fails_preflight(emu: TelloEmulator) -> None:
    emu.faults.battery_pct = 12
    d = TelloDriver(config(emu))
    try:
        d.connect()
        assert wait_until(lambda: d.state().battery_pct == 12, 2.0)
        checks = {c.name: c for c in d.preflight()}
        assert not checks["battery"].ok and "12 %" in checks["battery"].detail
        assert checks["temperature"].ok and checks["state stream"].ok
    finally:
        d.close()


def test_a_silent_loop_makes_the_drone_hover_then_land_by_itself(emu: TelloEmulator) -> None:
    """The keep-alive is tied to the loop: no velocity for loop_hover_s -> rc 0 0 0 0; for loop_land_s ->
    the driver lands on its own thread; nothing is sent after the drone is down (no hover forever)."""
    d = TelloDriver(config(emu, loop_hover_s=0.3, loop_land_s=1.0))
    try:
        d.connect()
        d.takeoff()
        d.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
        t_last = time.monotonic()
        n = len(emu.rc_history)
        assert wait_until(lambda: len(emu.rc_history) > n and emu.rc_history[-1][1] == (0, 0, 0, 0), 2.0)
        t_hover = time.monotonic() - t_last
        assert any(e.kind == "loop_silent_hover" for e in d.events)
        assert wait_until(lambda: "land" in emu.command_texts(), 3.0)
        t_land = time.monotonic() - t_last
        assert 0.3 <= t_hover < 0.6 and 1.0 <= t_land < 1.5, (t_hover, t_land)
        assert any(e.kind == "loop_lost_land" for e in d.events)
        assert wait_until(lambda: d.phase is FlightPhase.GROUND, 10.0)
        assert not emu.landed_by_timeout
        n = len(emu.rc_history)
        time.sleep(1.0)
        assert len(emu.rc_history) == n  # nothing sent on the ground
        assert_clean(d, emu)
    finally:
        d.close()


def test_a_loop_that_keeps_commanding_is_never_landed(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu, loop_hover_s=0.3, loop_land_s=1.0))
    try:
        d.connect()
        d.takeoff()
        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            d.send_body_velocity(np.zeros(4))
            time.sleep(0.05)
        assert "land" not in emu.command_texts() and d.phase is FlightPhase.AIRBORNE
        d.land()
        assert_clean(d, emu)
    finally:
        d.close()


def test_two_drones_in_one_process() -> None:
    with make_emulator("127.0.0.3") as a, make_emulator("127.0.0.4") as b:
        b.state_port = a.state_port  # station mode: both stream state to one port of this computer
        da, db = TelloDriver(config(a)), TelloDriver(config(b))
        try:
            da.connect()
            db.connect()
            da.takeoff()
            da.send_body_velocity(np.array([0.5, 0, 0, 0]))
            db.send_body_velocity(np.array([0, 0.5, 0, 0]))  # on the ground: suppressed, not sent
            assert wait_until(lambda: bool(a.rc_history), 2.0)
            assert a.rc_history[-1][1] == (0, 50, 0, 0) and not b.rc_history
            assert db.counts["rc_suppressed"] == 1
            assert a.flying and not b.flying
            agree(da, a)
            agree(db, b)
            da.land()
            assert_clean(da, a)
            assert_clean(db, b)
        finally:
            da.close()
            db.close()


# ---- the real-firmware scenarios of issue 14 -------------------------------------------------------------
def test_duplicated_late_ok_is_not_taken_as_the_takeoff_answer(emu: TelloEmulator) -> None:
    emu.faults.duplicate_reply_after_s = 0.4  # every reply arrives a second time 0.4 s later
    d = TelloDriver(config(emu))
    try:
        times = fly(d, emu)
        assert_clean(d, emu)
        assert d.counts["rc_suppressed"] == 0
        assert times["takeoff_s"] > emu.takeoff_s
    finally:
        d.close()


@pytest.mark.parametrize("lost", [{"takeoff"}, {"land"}, {"takeoff", "land"}, {"command"}])
def test_lost_replies_are_confirmed_by_telemetry(emu: TelloEmulator, lost: set[str]) -> None:
    """A lost takeoff `ok` is decided by telemetry at takeoff_timeout_s (5 s here, 20 s by default)."""
    emu.faults.lost_replies = set(lost)
    emu.takeoff_s = 1.5  # climbs, then stabilises at height until its `ok` (like a real Tello)
    d = TelloDriver(config(emu, takeoff_timeout_s=5.0))
    try:
        times = fly(d, emu)
        if "takeoff" in lost:
            assert 5.0 <= times["takeoff_s"] < 8.0  # decided at takeoff_timeout_s, not at the 20 s default
        else:
            assert times["takeoff_s"] < 5.0  # on the ok, before takeoff_timeout_s
        assert_clean(d, emu)
        confirmed = [e.detail for e in d.events if e.kind == "reply_lost_confirmed"]
        assert len(confirmed) == len(lost), d.events
        for verb in lost:
            assert any(verb in c for c in confirmed)
        assert sum(t == "land" for t in emu.command_texts()) == 1  # no retry of a land that worked
        texts = emu.command_texts()
        assert texts[texts.index("land") - 1] == "rc 0 0 0 0"  # hover first: the last rc is not kept
    finally:
        d.close()


def test_slow_climb_takeoff_returns_only_when_airborne(emu: TelloEmulator) -> None:
    emu.faults.takeoff_s = 11.5  # djitellopy allows 20 s for takeoff
    d = TelloDriver(config(emu))
    try:
        d.connect()
        t0 = time.monotonic()
        d.takeoff()  # the default 20 s bound, not the old 10 s
        assert time.monotonic() - t0 >= 11.5
        assert emu.phase == "flying"
        agree(d, emu)
        d.land()
        agree(d, emu)
        assert_clean(d, emu)
    finally:
        d.close()


def test_land_requested_during_takeoff_is_sent_at_once_and_again_on_its_ok(emu: TelloEmulator) -> None:
    """land() during a takeoff abandons the takeoff and sends `land` at once; a Tello busy taking off
    refuses it (`error Not joystick`), so it goes out again (after `rc 0 0 0 0`) on the takeoff's `ok`;
    nothing the busy drone ignores but that land; the velocity asked for during the climb never goes out."""
    emu.faults.takeoff_s = 2.0
    d = TelloDriver(config(emu))
    errors: list[BaseException] = []

    def takeoff() -> None:
        try:
            d.takeoff()
        except TelloCommandError as exc:
            errors.append(exc)

    try:
        d.connect()
        th = threading.Thread(target=takeoff, daemon=True)
        th.start()
        assert wait_until(lambda: emu.phase == "takeoff", 1.0)
        d.send_body_velocity(np.array([0.3, 0, 0, 0]))  # suppressed: the drone ignores rc while climbing
        t0 = time.monotonic()
        d.land()
        th.join(5.0)
        lands = [t for t, text in emu.commands if text == "land"]
        print(f"first land {lands[0] - t0:.3f} s after land(); {len(lands)} sent")
        assert lands[0] - t0 < 1.0
        assert len(errors) == 1 and "abandoned" in str(errors[0]), errors
        agree(d, emu)
        assert emu.phase == "landed" and all(rc == (0, 0, 0, 0) for _, rc in emu.rc_history)  # hover only
        assert any("its takeoff ended" in e.detail for e in d.events if e.kind == "resend"), d.events
        assert [r for r in emu.refused if r[2] != "land"] == [], emu.refused  # only the busy land
        assert not emu.landed_by_timeout and emu.errors == []
    finally:
        d.close()


def test_firmware_that_answers_rc(emu: TelloEmulator) -> None:
    emu.faults.rc_replies = True
    d = TelloDriver(config(emu))
    try:
        fly(d, emu, seconds=1.5)
        assert_clean(d, emu)
        assert d.link.chan is not None and d.link.chan.counts["reply_discarded"] >= 25  # the rc answers
        assert sum(t == "land" for t in emu.command_texts()) == 1
    finally:
        d.close()


def test_error_reply_to_takeoff_is_a_refusal_when_nothing_moves(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu))
    try:
        d.connect()
        emu.faults.error_replies = True
        with pytest.raises(TelloCommandError, match="takeoff refused"):
            d.takeoff()
        assert emu.phase == "landed"
        agree(d, emu)
        emu.faults.error_replies = False
        d.takeoff()  # the next takeoff works
        agree(d, emu)
        d.land()
        agree(d, emu)
    finally:
        d.close()


RAISED_CM = 21.0
"""How far the resting drone's tof reads above its floor value: a real Tello on a raised surface (a box, a
carpet, a landing pad) reads tof 31 cm on the ground, not 10 (users' flight logs)."""


def test_a_drone_on_a_raised_surface_is_on_the_ground() -> None:
    """tof 31 at rest: connect says GROUND (the motor time held, whatever tof reads), preflight passes, the
    loop watchdog sends no land to the grounded drone, takeoff() sends takeoff and returns only after the
    climb, and the flight lands normally; the emulator refused nothing."""
    emu = make_emulator(surface=lambda x, y: -RAISED_CM)
    emu.start()
    d = TelloDriver(config(emu, loop_hover_s=0.3, loop_land_s=0.5))
    try:
        t0 = time.monotonic()
        d.connect()
        print(f"connect: {time.monotonic() - t0:.2f} s, tof {d.status.tracker.latest.tof_cm:.0f} cm")
        assert d.status.tracker.latest.tof_cm == 10 + RAISED_CM
        assert d.phase is FlightPhase.GROUND, d.events[-5:]
        checks = {c.name: c for c in d.preflight()}
        assert all(c.ok for c in checks.values()), [c for c in checks.values() if not c.ok]
        time.sleep(1.0)  # the loop is silent: on the ground, the watchdog has nothing to land
        assert "land" not in emu.command_texts()
        t0 = time.monotonic()
        d.takeoff()
        assert emu.command_texts().count("takeoff") == 1
        assert emu.phase == "flying" and d.phase is FlightPhase.AIRBORNE
        print(f"takeoff returned after {time.monotonic() - t0:.2f} s")
        d.land()
        assert emu.phase == "landed" and d.phase is FlightPhase.GROUND
        assert emu.command_texts().count("land") == 1
        assert_clean(d, emu)
    finally:
        d.close()
        emu.close()


def test_land_while_the_drone_lands_by_itself_sends_no_land() -> None:
    """The drone lands of its own accord (the emulator's auto-land: no command for auto_land_s; a 2.5 s
    descent from its takeoff height, as a real one takes ~2 s): the driver calls it its own landing after
    self_land_s of descent, and a land() called then sends neither rc nor land (the drone would refuse them,
    and at touchdown reach a drone whose motors stopped); it returns once the motors are off."""
    emu = make_emulator(auto_land_s=1.0, land_s=2.5)
    emu.start()
    d = TelloDriver(config(emu, loop_hover_s=10.0, loop_land_s=14.0))
    try:
        d.connect()
        d.takeoff()
        n_rc = len(emu.rc_history)
        assert wait_until(lambda: d.status.tracker.self_landing, 5.0), d.events[-5:]
        assert emu.phase == "landing"
        d.land()
        assert d.phase is FlightPhase.GROUND and emu.phase == "landed"
        assert "land" not in emu.command_texts() and len(emu.rc_history) == n_rc
        assert any(e.kind == "resend" and "landing by itself" in e.detail for e in d.events)
        assert emu.refused == [], emu.refused
    finally:
        d.close()
        emu.close()


def test_an_unsolicited_error_auto_land_stops_the_sticks_at_once() -> None:
    """In flight, the loop sending rc at 20 Hz, the drone decides to land (low battery) and says `error Auto
    land` unprompted (faults.auto_land_notice, assumed): the driver records it (error_unanswered) and is in
    phase landing from that instant; no rc is sent after it, and the drone refuses nothing but an rc that
    crossed the notice on the wire. An `error …` that answers nothing else is an event too."""
    emu = make_emulator(land_s=2.0)
    emu.faults.auto_land_notice = True
    emu.start()
    d = TelloDriver(config(emu))
    try:
        d.connect()
        d.takeoff()
        t_end = time.monotonic() + 4.0
        emu.faults.battery_pct = 5  # below self_land_battery_pct: it lands by itself
        while time.monotonic() < t_end and emu.phase != "landed":
            d.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
            time.sleep(0.05)
        notices = [e for e in d.events if e.kind == "error_unanswered"]
        assert len(notices) == 1 and "Auto land" in notices[0].detail, notices
        assert "flying -> landing" in notices[0].detail
        late = [t for t, _ in emu.rc_history if t > notices[0].t]
        assert late == [], late
        # an rc sent before the notice arrived may cross it on the wire and reach a landing drone (seen
        # once under load: refused 'rc 0 10 0 0' in landing); none the driver sent after the notice
        crossed = [r for r in emu.refused if r[2].startswith("rc ") and r[0] <= notices[0].t]
        assert emu.landed_by_battery and len(emu.refused) == len(crossed), emu.refused
        assert wait_until(lambda: d.phase is FlightPhase.GROUND, 3.0)
        time.sleep(1.2)  # no request owed a reply any more (replies.PROMPT_REPLY_S)
        emu.send_unprompted("error Unknown")  # answers nothing: an event naming it
        assert wait_until(lambda: any("'error Unknown'" in e.detail for e in d.events), 1.0)
    finally:
        d.close()
        emu.close()


def test_land_on_the_ground_sends_nothing(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu))
    try:
        d.connect()
        d.land()
        assert "land" not in emu.command_texts()
        assert_clean(d, emu)
    finally:
        d.close()


def test_sdk20_firmware_fails_preflight_and_camera_for_sdk30_features(emu: TelloEmulator) -> None:
    emu.faults.sdk_version = "20"
    d = TelloDriver(config(emu, video_port=free_udp_port(), downward_camera=True))
    try:
        d.connect()
        assert d.sdk_version == "2.0"
        fw = {c.name: c for c in d.preflight()}["firmware"]
        assert not fw.ok and "SDK 2.0" in fw.detail and "SDK 3.0" in fw.detail and "downward" in fw.detail
        with pytest.raises(TelloCommandError, match=r"SDK 3\.0"):
            TelloCamera(d).start()
        assert not any(t.startswith(("port", "downvision")) for t in emu.command_texts())
        assert_clean(d, emu)
    finally:
        d.close()


def test_sdk20_with_default_video_port_passes(emu: TelloEmulator) -> None:
    emu.faults.sdk_version = "20"
    d = TelloDriver(config(emu, video_port=11111, downward_camera=False))
    try:
        d.connect()
        assert {c.name: c for c in d.preflight()}["firmware"].ok
    finally:
        d.close()


# ---- the SDK 3.0 video settings of a lab file (flightstack/config/tello_video.py) --------------------------
SETTINGS = (
    VideoSetting("hardware.video.resolution", "setresolution low"),
    VideoSetting("hardware.drones[id 1].video.fps", "setfps middle"),
    VideoSetting("hardware.video.bitrate", "setbitrate 1"),
)
NOISE = [np.random.default_rng(k).integers(0, 256, (720, 960, 3), dtype=np.uint8) for k in range(8)]


def noise_frame(t: float, emu: TelloEmulator) -> np.ndarray:
    """A 960 × 720 picture no encoder can compress (one of 8 noise images, a new one every frame)."""
    return NOISE[round(t * emu.fps) % len(NOISE)]


def test_video_settings_are_sent_at_connect_and_change_the_stream() -> None:
    emu = make_emulator(frame_source=noise_frame, fps=30.0, video_size=(960, 720))
    emu.start()
    d = TelloDriver(config(emu, video_settings=SETTINGS))
    cam = TelloCamera(d, frame_timeout_s=10.0)
    try:
        d.connect()
        checks = {c.name: c for c in d.preflight()}
        assert [checks[f"video {k}"].detail for k in ("resolution", "fps", "bitrate")] == [
            "`setresolution low` confirmed (ok)",
            "`setfps middle` confirmed (ok)",
            "`setbitrate 1` confirmed (ok)",
        ]
        assert all(c.ok for c in checks.values()), checks
        assert [e.detail for e in d.events if e.kind == "video_setting"] == [s.command for s in SETTINGS]
        assert (emu.resolution, emu.fps, emu.bitrate_mbps) == ("low", 15.0, 1)
        cam.start()
        texts = emu.command_texts()
        sent = [texts.index(s.command) for s in SETTINGS]  # after `command`, `sdk?`; before `streamon`
        assert texts.index("sdk?") < sent[0] < sent[1] < sent[2] < texts.index("streamon"), texts
        time.sleep(1.0)  # past the first keyframe
        n0, b0, t0 = emu.video_frames_sent, emu.video_bytes_sent, time.monotonic()
        shapes = set()
        while time.monotonic() < t0 + 3.0:
            f = cam.latest()
            if f is not None and f.image is not None:
                shapes.add(f.image.shape)
            time.sleep(0.02)
        frames, dt = emu.video_frames_sent - n0, time.monotonic() - t0
        mbps = 8e-6 * (emu.video_bytes_sent - b0) / frames * emu.fps  # at the stream's rate: skips aside
        print(f"stream: {frames / dt:.1f} frames/s, {mbps:.2f} Mbit/s, decoded {shapes}")
        assert shapes == {(478, 648, 3)}  # 480P as a real Tello EDU decodes (DJITelloPy #213)
        # setfps middle: 15 /s. A loaded machine skips some; a late video thread sends up to 3 frames it
        # owes at once (emulators/tello/video.py skips beyond that), so a window may hold 3 more plus the
        # fencepost (47 in 3.01 s seen beside a CPU-bound process); setfps high would be 30 /s
        assert frames / dt >= 12.0 and frames <= emu.fps * dt + 4, (frames, dt)
        assert 0.4 <= mbps <= 2.0, mbps  # setbitrate 1: 1 Mbit/s (this noise at 30 fps, 720P: 81 Mbit/s)
        cam.stop()
        assert_clean(d, emu)
    finally:
        cam.stop()
        d.close()
        emu.close()


def test_a_refused_or_unanswered_video_setting_fails_preflight_and_camera(emu: TelloEmulator) -> None:
    """A firmware that does not know `setfps` (DJITelloPy #144, #219) and a `setbitrate` whose answers
    are all lost: preflight FAILs one line each naming the key, the drone, its reply and the fix, and no
    video is started."""
    emu.faults.unknown_commands = {"setfps"}
    emu.faults.lost_replies = {"setbitrate"}
    settings = (VideoSetting("hardware.video.fps", "setfps high"), SETTINGS[2])
    d = TelloDriver(config(emu, video_settings=settings, command_timeout_s=0.3))
    try:
        d.connect()
        assert emu.fps == 30.0 and emu.bitrate_mbps == 1  # refused: not applied; unanswered: applied
        checks = {c.name: c for c in d.preflight()}
        fix = "remove the key or update the firmware (the SDK 3.0 video settings need a Tello EDU or Talent)"
        assert not checks["video fps"].ok and checks["video fps"].detail == (
            f"hardware.video.fps (`setfps high`): Tello {emu.ip} answered 'unknown command: setfps'; {fix}"
        )
        assert not checks["video bitrate"].ok and checks["video bitrate"].detail == (
            f"hardware.video.bitrate (`setbitrate 1`): Tello {emu.ip} did not answer (4 tries); {fix}"
        )
        assert checks["firmware"].ok  # SDK 3.0: the firmware's version is not the reason
        texts = emu.command_texts()
        assert texts.count("setbitrate 1") == 4 and texts.count("setfps high") == 1
        with pytest.raises(TelloCommandError, match=r"hardware\.video\.fps .*hardware\.video\.bitrate"):
            TelloCamera(d).start()
        assert "streamon" not in emu.command_texts()
        assert [(text, reply) for _, _, text, reply in emu.refused] == [
            ("setfps high", "unknown command: setfps")
        ]
        assert [e.kind for e in d.events if e.kind.startswith("video")] == ["video_setting_refused"] * 2
    finally:
        d.close()


def test_sdk20_firmware_gets_no_video_settings(emu: TelloEmulator) -> None:
    """Refused before sending, as `port` and `downvision` are: preflight names the settings, nothing of
    them reaches the drone, the camera does not start."""
    emu.faults.sdk_version = "20"
    d = TelloDriver(config(emu, video_port=11111, video_settings=SETTINGS))
    try:
        d.connect()
        checks = {c.name: c for c in d.preflight()}
        fw = checks["firmware"]
        assert not fw.ok and "SDK 2.0" in fw.detail
        assert "video settings (`setresolution low`, `setfps middle`, `setbitrate 1`)" in fw.detail
        assert not checks["video fps"].ok and checks["video fps"].detail.startswith(
            f"hardware.drones[id 1].video.fps (`setfps middle`): not sent to Tello {emu.ip}: it reports "
            "SDK 2.0, and SDK 3.0 is needed; remove the key or update the firmware"
        )
        with pytest.raises(TelloCommandError, match=r"SDK 2\.0.*video settings.*needs SDK 3\.0"):
            TelloCamera(d).start()
        assert not any(t.startswith(("set", "streamon")) for t in emu.command_texts()), emu.command_texts()
        assert_clean(d, emu)
    finally:
        d.close()
