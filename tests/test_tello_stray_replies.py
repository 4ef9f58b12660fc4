"""Stray replies never complete a command: the driver against the loopback Tello emulator
(127.0.0.x) with its `stray_replies` fault, and the reply ledger and `parse_sdk` alone.

Real transcripts show replies against the wrong request (`battery?` → `ok`, `forward 139` → `70`). Before:
a keep-alive's `ok` confirmed a takeoff before the drone's own, the takeoff's late `ok` then completed an
unanswered `streamon`, `streamon` answered `70` raised although its `ok` came 0.3 s later, and `sdk?`
answered `70` read as SDK 7.0 and passed the firmware check.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("av")  # streamon starts the emulator's video

from flightstack.drivers.tello.config import TelloCommandError, parse_sdk
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.replies import PROMPT_REPLY_S, SLOW_REPLY_S, ReplyLedger
from flightstack.drivers.tello.traffic import TrafficWriter, read_traffic
from flightstack.hal import FlightPhase
from flightstack.sim_backend.emulators.net import wait_until
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from tests.conftest import tello_config, tello_emulator


@pytest.fixture
def emu() -> Iterator[TelloEmulator]:
    e = tello_emulator("127.0.0.7", takeoff_s=FAST_TAKEOFF_S)
    e.start()
    yield e
    e.close()


def strays(d: TelloDriver) -> dict[str, int]:
    return {k: n for k, n in d.counts.items() if k.startswith("stray_reply_")}


def test_a_keepalive_ok_during_takeoff_does_not_confirm_it(emu: TelloEmulator) -> None:
    """`battery?` answered `ok` (its own answer lost) while the drone holds after its climb: the takeoff is
    confirmed by the drone's own `ok`, 5 s after the command, not by a keep-alive's."""
    emu.faults.takeoff_s = 5.0  # climbs in 2 s, then holds until its ok
    emu.faults.stray_replies = {"battery?": "ok"}
    emu.faults.lost_replies = {"battery?"}
    d = TelloDriver(tello_config(emu, keepalive_s=0.5, link_timeout_s=0.5))
    try:
        d.connect()
        t0 = time.monotonic()
        d.takeoff()
        returned = time.monotonic()
        assert wait_until(lambda: emu.phase == "flying", 6.0)
        own_ok = next(t for t, text, kind in emu.replies_sent if text == "ok" and kind == "normal" and t > t0)
        probes = [t for t, text in emu.commands if text == "battery?"]
        assert probes and probes[0] < own_ok - 1.0, "no keep-alive went out before the takeoff's own ok"
        assert returned >= own_ok, f"takeoff confirmed {own_ok - returned:.2f} s before the drone's own ok"
        assert returned - own_ok < 0.5
        assert d.phase is FlightPhase.AIRBORNE
        assert strays(d) == {"stray_reply_ok": len(probes)}  # each keep-alive's ok, counted
        logged = [e.detail for e in d.events if e.kind == "stray_reply"]
        assert len(logged) == 1 and "'battery?'" in logged[0]  # logged once per kind
        d.land()
    finally:
        d.close()


def test_a_late_takeoff_ok_does_not_complete_an_unanswered_streamon(emu: TelloEmulator) -> None:
    """The takeoff confirmed by telemetry at takeoff_timeout_s (4 s) before its `ok` (5.5 s); `streamon`,
    sent right after, is never answered: the takeoff's late `ok` arriving meanwhile does not complete it."""
    emu.faults.takeoff_s = 5.5
    emu.faults.lost_replies = {"streamon"}
    d = TelloDriver(tello_config(emu, takeoff_timeout_s=4.0, link_timeout_s=0.5))
    try:
        d.connect()
        d.takeoff()
        assert emu.phase == "takeoff"  # the drone has not answered yet
        with pytest.raises(TelloCommandError, match="'streamon' got no answer"):
            d.control("streamon", 2.5, attempts=1)
        t_streamon = next(t for t, text in emu.commands if text == "streamon")
        late_ok = next(t for t, text, _ in emu.replies_sent if text == "ok" and t > t_streamon)
        assert late_ok < t_streamon + 2.5  # within streamon's wait
        assert strays(d) == {"stray_reply_ok": 1}
        detail = next(e.detail for e in d.events if e.kind == "stray_reply")
        assert "'streamon' got 'ok'" in detail and "'takeoff'" in detail
        d.land()
    finally:
        d.close()


def test_streamon_answered_70_then_ok_succeeds_and_the_stray_is_recorded(
    emu: TelloEmulator, tmp_path: Path
) -> None:
    """`streamon` answered `70` at once and `ok` 0.3 s later: the `70` is skipped (counted, logged once,
    in the traffic file), the `ok` completes it; twice."""
    path = tmp_path / "traffic.jsonl"
    traffic = TrafficWriter(path, emu.ip)
    d = TelloDriver(tello_config(emu), traffic)
    try:
        d.connect()
        emu.faults.stray_replies = {"streamon": "70"}
        emu.faults.reply_delay_s = 0.3
        for _ in range(2):
            t0 = time.monotonic()
            d.control("streamon", 1.0, attempts=1)
            assert 0.3 <= time.monotonic() - t0 < 1.0
        assert strays(d) == {"stray_reply_value": 2}
        assert [e.kind for e in d.events].count("stray_reply") == 1
    finally:
        d.close()
        traffic.close()
    replies = [r.text for r in read_traffic(path).of("reply")]
    assert replies.count("70") == 2 and replies.count("ok") >= 3  # command's and both streamon's


@pytest.mark.parametrize("stray", ["70", "59"])
def test_sdk_answered_a_battery_value_fails_the_firmware_check(emu: TelloEmulator, stray: str) -> None:
    """`sdk?` answered `70` or `59` (its own answer lost): no SDK version, so a mission that needs SDK 3.0
    (the downward camera) fails the firmware check."""
    emu.faults.stray_replies = {"sdk?": stray}
    emu.faults.lost_replies = {"sdk?"}
    d = TelloDriver(tello_config(emu, downward_camera=True))
    try:
        d.connect()
        assert d.sdk_version is None
        firmware = {c.name: c for c in d.preflight()}["firmware"]
        assert not firmware.ok and "not answered" in firmware.detail
        assert strays(d) == {"stray_reply_value": 2}  # both tries
    finally:
        d.close()


def test_parse_sdk_accepts_only_versions_that_exist() -> None:
    assert [parse_sdk(r) for r in ("13", "20", "30\r\n")] == ["1.3", "2.0", "3.0"]
    assert [parse_sdk(r) for r in ("70", "59", "21", "3", "300", "ok", "")] == [None] * 7


def test_ledger_gives_a_reply_to_the_oldest_owed_request_it_could_answer() -> None:
    ledger = ReplyLedger()
    ledger.sent(0.0, "takeoff")
    ledger.sent(5.0, "battery?")
    ledger.sent(5.1, "rc 0 0 0 0")  # no reply owed
    stray = ledger.place(5.2, "ok", "takeoff", accepted=True)  # the keep-alive's
    assert stray is not None and stray.command == "battery?"
    own = ledger.place(8.0, "ok", "takeoff", accepted=True)
    assert own is not None and own.command == "takeoff"
    again = ledger.place(8.1, "ok", "takeoff", accepted=True)  # a duplicate: nothing else owed, so taken
    assert again is not None and again.command == "takeoff"


def test_ledger_a_value_answers_only_a_query_and_owed_requests_expire() -> None:
    ledger = ReplyLedger()
    ledger.sent(0.0, "takeoff")
    ledger.sent(0.5, "wifi?")
    assert ledger.place(0.6, "70", "streamon") is not None  # wifi?'s: a value answers no takeoff
    assert ledger.place(0.7, "70", "streamon") is None
    late = ledger.place(SLOW_REPLY_S - 0.1, "ok", "streamon", accepted=True)
    assert late is not None and late.command == "takeoff"
    ledger.sent(20.0, "sdk?")
    assert ledger.place(20.0 + PROMPT_REPLY_S + 0.1, "ok") is None  # sdk? no longer owed
    ledger.sent(30.0, "streamon")
    ledger.sent(30.5, "streamon")  # a resend joins its entry: either ok is the answer
    own = ledger.place(30.6, "ok", "streamon", accepted=True)
    assert own is not None and own.t == 30.0
