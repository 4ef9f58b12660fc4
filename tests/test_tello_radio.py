"""What a lossy radio does to a Tello flight, judged at the loopback Tello emulator (what it received, when).

- A two-way outage that begins just before land() (its hover and land lost): `rc 0 0 0 0` + `land` reach
  the drone at once when the link returns, through SafeDrone (which starts no second land meanwhile); on a
  one-way uplink outage (telemetry fine) within `land_resend_s` of the uplink's return.
- A drone that lost power in flight reboots out of SDK mode: `command` goes out at a bounded rate while
  the link is lost, the drone streams again and land() confirms it down.
- A drone landing by itself on low battery gets no rc once its telemetry shows the descent.

Timing knobs are the driver's defaults (link_timeout_s 1 s, land_resend_s 0.5 s, land_confirm_s 1.5 s,
rejoin_s 1 s) and the emulator lands in 1.7 s (a real Tello's land `ok` came after 1.7 s, dji-sdk/
Tello-Python #88). Each emulator streams state to its own free port (no fixed ports).
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from flightstack.drivers.lab.hardware import WallClock
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.hal import FlightPhase, StampedPose
from flightstack.netem import LinkProfile, NetworkProfile
from flightstack.paper.geometry import Pose
from flightstack.safety import EventLog, SafeDrone, SafetyLimits
from flightstack.sim_backend.emulated_lab import MOCAP_NOISE_M
from flightstack.sim_backend.emulators.net import wait_until
from flightstack.sim_backend.emulators.radio import DeviceRadio
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from tests.conftest import Bound, tello_config, tello_emulator

LAND_S = 1.7
"""The emulated landing's duration (s): a real Tello answered `land` after 1.7 s (Tello-Python #88)."""
OUTAGE_S = 1.4
"""The outage of the observation that motivated these tests (s): the drone flew on its last rc 4.2 s."""
HOVER = (0, 0, 0, 0)


def make_emulator(**kw: Any) -> TelloEmulator:
    """conftest.tello_emulator with a fast takeoff (FAST_TAKEOFF_S): these tests are about outages and
    landings; the recorded 8.7 s takeoff would add 8.4 s to each."""
    return tello_emulator(takeoff_s=FAST_TAKEOFF_S, **kw)  # type: ignore[no-any-return]


config = tello_config


class LivePose:
    """hal.PoseSource: every body at 0.8 m, stamped now, with a real capture's noise (MOCAP_NOISE_M): a live
    motion capture inside the fence. Without the noise it would be a frozen pose, which SafeDrone lands."""

    def __init__(self, clock: WallClock) -> None:
        self.clock = clock
        self.rng = np.random.default_rng(0)

    def latest(self, body: str) -> StampedPose | None:
        jitter = MOCAP_NOISE_M * self.rng.standard_normal(3)
        return StampedPose(self.clock.now(), Pose.make(np.array([0.0, 0.0, 0.8]) + jitter, 0.0))


def loop(seconds: float, step: Callable[[], None], until: Callable[[], bool] = lambda: False) -> None:
    """Call `step` at 20 Hz (the control loop) for `seconds`, or until `until()`."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end and not until():
        step()
        time.sleep(0.05)


def first(times: list[float]) -> float | None:
    return min(times) if times else None


def rc_stop_after(emu: TelloEmulator, t: float) -> float | None:
    """When the drone stopped obeying a non-zero rc after `t` (s): its first hover rc or landing start."""
    hovers = [tr for tr, rc in list(emu.rc_history) if tr >= t and rc == HOVER]
    landings = [tp for tp, ph in list(emu.phase_log) if tp >= t and ph in ("landing", "landed")]
    return first(hovers + landings)


def commands_at(emu: TelloEmulator, text: str, after: float = -1.0) -> list[float]:
    return [t for t, c in list(emu.commands) if c == text and t >= after]


# ---- item: land() re-sends the moment the link returns -----------------------------------------------------
def test_two_way_outage_before_land_hover_and_land_arrive_as_the_link_returns(safety_bound: Bound) -> None:
    """SafeDrone lands; the outage (both directions) began just before, so its hover and land are lost."""
    with make_emulator(land_s=LAND_S) as emu:
        d = TelloDriver(config(emu))
        clock = WallClock()
        log = EventLog()
        sd = SafeDrone(1, d, LivePose(clock), "tello1", clock, SafetyLimits(), log, background=True)
        try:
            d.connect()
            d.takeoff()

            def fly() -> None:
                sd.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
                sd.tick()

            loop(1.0, fly)
            rc_moving = [t for t, rc in list(emu.rc_history) if rc != HOVER]
            assert rc_moving, "the drone never got a non-zero rc"
            emu.faults.uplink_down = emu.faults.downlink_down = True
            t_out = time.monotonic()
            sd.land("test: end of mission")
            loop(OUTAGE_S - (time.monotonic() - t_out), fly)
            t_back = time.monotonic()
            emu.faults.uplink_down = emu.faults.downlink_down = False
            loop(12.0, fly, until=lambda: sd.landed)
            assert sd.landed and emu.phase == "landed" and not emu.landed_by_timeout

            lost = [text for _, text, _ in list(emu.uplink_lost)]
            assert "land" in lost and "rc 0 0 0 0" in lost  # sent during the outage, never arrived
            assert not [t for t, _ in list(emu.commands) if t_out < t < t_back]  # the outage was total
            t_stop = rc_stop_after(emu, t_back)
            assert t_stop is not None
            safety_bound("two-way outage: the drone on a non-zero rc after the link returned",
                         1e3 * (t_stop - t_back), 500.0)  # fmt: skip
            t_land = first(commands_at(emu, "land", t_back))
            assert t_land is not None
            safety_bound(
                "two-way outage: land received after the link returned", 1e3 * (t_land - t_back), 500.0
            )
            last_moving = max(t for t, rc in list(emu.rc_history) if rc != HOVER and t < t_out)
            safety_bound("two-way outage: flying on the last rc in all (1.4 s outage included)",
                         1e3 * (t_stop - last_moving), 1e3 * OUTAGE_S + 600.0)  # fmt: skip
            # one land job: the driver's land() brought it down, SafeDrone started no second one
            assert [e.kind for e in d.events].count("land_confirmed") == 1
            assert not log.of_kind("land_failed") and not log.of_kind("pose_frozen")
            assert any(e.kind == "resend" and "telemetry back" in e.detail for e in d.events), d.events[-10:]
        finally:
            sd.close(land_wait_s=5.0)


def test_uplink_outage_before_land_the_hover_and_land_follow_the_uplinks_return(safety_bound: Bound) -> None:
    """Only the uplink fails: telemetry proves the drone holding its height, so rc 0 0 0 0 + land go out
    again every land_confirm_s (a real Tello shows its descent 0.76 s after a land it heard: no sooner
    can a land be judged lost); the first after the uplink returns stops the drone. The uplink returns
    just after a lost re-send: the worst case, a whole re-send period."""
    with make_emulator(land_s=LAND_S) as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            d.takeoff()
            loop(1.0, lambda: d.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0])))
            emu.faults.uplink_down = True
            worker = threading.Thread(target=d.land, daemon=True)
            worker.start()
            # the worst case: the uplink returns right after a lost re-send (the second lost re-send)
            assert wait_until(lambda: [x[1] for x in list(emu.uplink_lost)].count("land") >= 3, 8.0)
            t_back = time.monotonic()
            emu.faults.uplink_down = False
            worker.join(12.0)
            assert not worker.is_alive() and d.phase is FlightPhase.GROUND and emu.phase == "landed"
            t_stop = rc_stop_after(emu, t_back)
            assert t_stop is not None
            # the driver cannot see an uplink return: its bound is the re-send period plus one loop period
            safety_bound("uplink outage: the drone on a non-zero rc after the uplink returned",
                         1e3 * (t_stop - t_back), 1e3 * d.cfg.land_confirm_s + 100.0)  # fmt: skip
            sent = sorted(t for t, text, _ in list(emu.uplink_lost) if text == "land")
            gaps = [b - a for a, b in itertools.pairwise(sent)]
            period = d.cfg.land_confirm_s
            assert len(sent) >= 2 and all(period - 0.1 <= g <= period + 0.3 for g in gaps), gaps
        finally:
            d.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_lossy_state_stream_gets_one_land_while_it_shows_the_descent(seed: int) -> None:
    """A quarter of the state datagrams lost (seeded, independent per datagram), commands and replies
    clean: the land is heard, the descent shows in what arrives, and `land` goes out once (a Tello busy
    landing answers `error`; the driver used to read the sparse stream as a stuck drone)."""
    lossy = NetworkProfile(
        "state-loss-25", "25 % of state datagrams lost", {"state": LinkProfile(loss_good=0.25)}
    )
    radio = DeviceRadio(lossy, seed, "tello1", {"command": "rc", "reply": "rc", "state": "state"})
    with make_emulator(land_s=LAND_S, radio=radio) as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            d.takeoff()
            loop(1.0, lambda: d.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0])))
            d.land()
            assert d.phase is FlightPhase.GROUND and emu.phase == "landed"
            lands = emu.command_texts().count("land")
            lost = radio.counts()["state"]
            print(f"seed {seed}: {lands} land sent; radio {lost}")
            assert lands == 1, [e.detail for e in d.events if e.kind == "resend"]
        finally:
            d.close()
            radio.close()


# ---- item: command at a bounded rate while the link is lost ------------------------------------------------
def test_a_drone_that_rebooted_in_flight_streams_again_and_its_landing_is_confirmed(
    safety_bound: Bound,
) -> None:
    with make_emulator() as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            d.takeoff()
            loop(1.0, lambda: d.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0])))
            emu.faults.powered_off = True  # battery knocked loose: it falls, it reboots
            assert wait_until(lambda: any(kind == "off" for _, kind in list(emu.power_log)), 1.0)
            errors: list[BaseException] = []

            def land() -> None:
                try:
                    d.land()
                except Exception as exc:  # reported by the test
                    errors.append(exc)

            worker = threading.Thread(target=land, daemon=True)
            worker.start()
            time.sleep(1.5)
            emu.faults.powered_off = False
            assert wait_until(lambda: any(kind == "boot" for _, kind in list(emu.power_log)), 1.0)
            t_boot = next(t for t, kind in list(emu.power_log) if kind == "boot")
            worker.join(10.0)
            assert not worker.is_alive() and not errors, errors
            assert d.phase is FlightPhase.GROUND and emu.sdk_mode and emu.phase == "landed"
            t_command = first(commands_at(emu, "command", t_boot))
            assert t_command is not None
            safety_bound("reboot: `command` received after the boot", 1e3 * (t_command - t_boot),
                         1e3 * d.cfg.rejoin_s + 200.0)  # fmt: skip
            t_done = max(e.t for e in d.events if e.kind == "land_confirmed")
            safety_bound("reboot: landing confirmed after the boot", 1e3 * (t_done - t_boot),
                         1e3 * (d.cfg.rejoin_s + d.cfg.phase.motor_quiet_s) + 800.0)  # fmt: skip
            # the rate is bounded: every `command` sent while the link was lost, arrived or not
            lost = [t for t, text, _ in list(emu.uplink_lost) if text == "command"]
            sent = sorted(lost + commands_at(emu, "command", t_boot))
            gaps = [b - a for a, b in itertools.pairwise(sent)]
            assert len(sent) >= 2 and min(gaps) >= 0.9 * d.cfg.rejoin_s, gaps
            assert d.counts["rejoin_sent"] == len(sent)
        finally:
            d.close()


# ---- item: no rc for a drone landing by itself -------------------------------------------------------------
def test_a_drone_landing_by_itself_on_low_battery_gets_no_rc(safety_bound: Bound) -> None:
    with make_emulator(land_s=LAND_S) as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            d.takeoff()

            def fly() -> None:
                d.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))

            loop(1.0, fly)
            emu.faults.battery_pct = 8  # below the firmware's own landing level: it lands by itself
            loop(LAND_S + 3.0, fly, until=lambda: d.phase is FlightPhase.GROUND)
            assert emu.landed_by_battery and emu.phase == "landed"
            t_ld = next(t for t, ph in list(emu.phase_log) if ph == "landing")
            t_down = next(t for t, ph in list(emu.phase_log) if ph == "landed" and t > t_ld)
            during = [t for t, _ in list(emu.rc_history) if t_ld <= t <= t_down]
            last = max(during, default=t_ld)
            # telemetry shows the descent after ~10 cm over 3 falling state packets (10 Hz): then no rc
            safety_bound("own landing: last rc received after its descent began", 1e3 * (last - t_ld), 600.0)
            safety_bound("own landing: rc datagrams during the descent", len(during), 12, unit="rc")
            assert "land" not in emu.command_texts()  # it was landing: nothing else sent either
            assert any(e.kind == "phase" and "its own landing" in e.detail for e in d.events), d.events[-5:]
            n = len(emu.rc_history)
            loop(0.5, fly)
            assert len(emu.rc_history) == n  # on the ground: nothing
        finally:
            d.close()
