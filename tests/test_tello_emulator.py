"""Drive the loopback Tello emulator with the real djitellopy client (and with raw UDP).

djitellopy binds process-global UDP sockets on ("", Tello.CONTROL_UDP_PORT) and ("", Tello.STATE_UDP_PORT)
the first time a ``Tello`` is constructed; the fixture points both at picked free ports (a real Tello replies
to the sender's port and streams its state to the port it is told), so the tests never hold 8889/8890 on
every address and can run beside other emulators (each on its own address at 8889).  The emulated drone
lives on 127.0.0.2; a second one (swarm routing) on 127.0.1.3 and raw-socket emulators on 127.0.1.4/5, so that
other test modules may use 127.0.0.3+ in the same process; the fault-switch tests use 127.0.1.6-15.  Every
datagram stays on 127.0.0.0/8.

djitellopy quirks these tests rely on (verified against djitellopy 2.5.0):

* ``timeout`` arguments are type-checked as ``int`` (``@enforce_types``): sub-second timeouts are impossible;
* the default ``timeout=RESPONSE_TIMEOUT`` (7 s) of ``send_command_with_return``/``send_control_command`` is
  bound at definition time - patching ``Tello.RESPONSE_TIMEOUT`` does not change it, so the fixture patches
  the functions' ``__defaults__``; ``takeoff`` reads ``Tello.TAKEOFF_TIMEOUT`` at call time;
* a reply arriving after its command timed out stays queued and is returned as the answer to the next command.
"""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import re
import socket
import time
from collections.abc import Iterator
from dataclasses import MISSING, dataclass, fields

import numpy as np
import pytest

from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.net import wait_until
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from flightstack.sim_backend.emulators.tello.faults import TelloFaults
from flightstack.sim_backend.emulators.tello.frames import default_square, read_frame_index
from tests.conftest import skip_or_fail_in_ci

try:
    import djitellopy  # noqa: F401  # the reference client (its opencv-python clashes with the headless one)
except ModuleNotFoundError:
    skip_or_fail_in_ci('no djitellopy: `python3 -m pip install --no-deps "djitellopy==2.5.0"` (.ci/run does)')
from djitellopy import tello as tello_module
from djitellopy.tello import Tello, TelloException

RESPONSE_TIMEOUT_S = 2  # must be an int for djitellopy
STATE_RE = re.compile(
    r"^mid:-1;x:-?\d+;y:-?\d+;z:-?\d+;mpry:0,0,0;pitch:-?\d+;roll:-?\d+;yaw:-?\d+;vgx:-?\d+;vgy:-?\d+;"
    r"vgz:-?\d+;templ:\d+;temph:\d+;tof:\d+;h:-?\d+;bat:\d+;baro:-?\d+\.\d+;time:\d+;agx:-?\d+\.\d+;"
    r"agy:-?\d+\.\d+;agz:-?\d+\.\d+;\r\n$"
)


@dataclass
class Rig:
    """A connected djitellopy client and the emulator it talks to."""

    tello: Tello
    emu: TelloEmulator
    vs_port: int

    @property
    def responses(self) -> list[bytes]:
        """djitellopy's queue of not-yet-consumed replies for this drone."""
        return tello_module.drones[self.tello.address[0]]["responses"]


def _inner(func: object) -> object:
    """The undecorated function behind djitellopy's ``@enforce_types`` wrapper."""
    return getattr(func, "__wrapped__", func)


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    """Module-wide emulator on 127.0.0.2 and a connected djitellopy ``Tello`` with short timeouts."""
    if tello_module.threads_initialized:  # bound by an earlier Tello of this process: reuse its ports
        state_port = Tello.STATE_UDP_PORT
    else:
        control_port, state_port = free_udp_port("127.0.0.1"), free_udp_port("127.0.0.1")
        Tello.CONTROL_UDP_PORT, Tello.STATE_UDP_PORT = control_port, state_port  # for the process's life
    faulthandler.dump_traceback_later(150, exit=True)  # last-resort guard against a hang
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Tello, "RESPONSE_TIMEOUT", RESPONSE_TIMEOUT_S)
        mp.setattr(Tello, "TAKEOFF_TIMEOUT", 3)
        mp.setattr(Tello, "FRAME_GRAB_TIMEOUT", 5)
        mp.setattr(_inner(Tello.send_command_with_return), "__defaults__", (RESPONSE_TIMEOUT_S,))
        mp.setattr(_inner(Tello.send_control_command), "__defaults__", (RESPONSE_TIMEOUT_S,))
        level = Tello.LOGGER.level
        Tello.LOGGER.setLevel(logging.ERROR)
        vs_port = free_udp_port("127.0.0.1")
        emu = TelloEmulator(
            "127.0.0.2", state_port=state_port, video_port=vs_port, takeoff_s=0.3, land_s=0.2
        ).start()
        tello = None
        try:
            tello = Tello("127.0.0.2", retry_count=1, vs_udp=vs_port)
            tello.address = emu.address
            tello.connect()
            yield Rig(tello, emu, vs_port)
        finally:
            if tello is not None:
                tello.is_flying = tello.stream_on = False  # end() must not wait for replies
                tello.end()
            emu.close()
            Tello.LOGGER.setLevel(level)
            faulthandler.cancel_dump_traceback_later()


@pytest.fixture(autouse=True)
def _reset_faults(request: pytest.FixtureRequest) -> Iterator[None]:
    """Restore the default fault switches after every test that uses the shared rig."""
    yield
    if "rig" in request.fixturenames:
        emu: TelloEmulator = request.getfixturevalue("rig").emu
        defaults = TelloFaults()  # lost_replies has a default_factory: its Field.default is MISSING
        for field in fields(TelloFaults):
            setattr(emu.faults, field.name, getattr(defaults, field.name))


# ---------------------------------------------------------------------------------------- raw protocol
def test_raw_protocol_sdk_mode_state_and_replies() -> None:
    """Without djitellopy: no reply before ``command``; replies come from emu.address; state at 10 Hz."""
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as cli,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as state_rx,
    ):
        cli.bind(("127.0.0.1", 0))
        cli.settimeout(0.3)
        state_rx.bind(("127.0.0.1", 0))
        state_rx.settimeout(0.3)
        with TelloEmulator("127.0.1.4", state_port=state_rx.getsockname()[1]) as emu:
            cli.sendto(b"battery?", emu.address)
            with pytest.raises(TimeoutError):
                cli.recvfrom(1024)
            with pytest.raises(TimeoutError):
                state_rx.recvfrom(1024)
            assert emu.command_texts() == ["battery?"] and not emu.sdk_mode

            cli.sendto(b"command", emu.address)
            data, src = cli.recvfrom(1024)
            assert (data, src) == (b"ok", emu.address) and emu.sdk_mode

            state_rx.settimeout(1.0)
            arrivals = []
            for _ in range(6):
                packet, src = state_rx.recvfrom(1024)
                arrivals.append(time.monotonic())
                assert src[0] == "127.0.1.4"
                assert STATE_RE.match(packet.decode("ascii")), packet
            period = (arrivals[-1] - arrivals[0]) / 5
            assert 0.07 < period < 0.14, period

            for command, expected in [
                (b"battery?", b"87"),
                (b"height?", b"0dm"),
                (b"temp?", b"60~63"),
                (b"sdk?", b"30"),
                (b"forward 50", b"error Motor stop"),
            ]:
                cli.sendto(command, emu.address)
                assert cli.recvfrom(1024)[0] == expected, command
            for silent in (b"rc 1 2 3 4", b"emergency"):
                cli.sendto(silent, emu.address)
                with pytest.raises(TimeoutError):
                    cli.recvfrom(1024)
            assert emu.rc_history[-1][1] == (1, 2, 3, 4)


def test_raw_one_way_links_power_loss_and_own_landing() -> None:
    """A datagram lost on the uplink never reaches the drone (``uplink_lost``); on the downlink it is run
    but its reply and the state are lost; a power loss drops the drone, which boots out of SDK mode and
    streams only after ``command``; below its low-battery level it lands by itself, ignoring rc and
    answering ``error Auto land``."""
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as cli,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as state_rx,
    ):
        cli.bind(("127.0.0.1", 0))
        cli.settimeout(0.3)
        state_rx.bind(("127.0.0.1", 0))
        state_rx.settimeout(0.3)
        with TelloEmulator(
            "127.0.1.5", state_port=state_rx.getsockname()[1], land_s=1.0, takeoff_s=FAST_TAKEOFF_S
        ) as emu:

            def ask(text: str, timeout: float = 1.0) -> str:
                cli.settimeout(timeout)
                cli.sendto(text.encode(), emu.address)
                return cli.recvfrom(1024)[0].decode()

            def silent(text: str) -> None:
                cli.settimeout(0.3)
                cli.sendto(text.encode(), emu.address)
                with pytest.raises(TimeoutError):
                    cli.recvfrom(1024)

            def drain_state() -> None:
                with contextlib.suppress(TimeoutError):
                    while True:
                        state_rx.recvfrom(1024)

            assert ask("command") == "ok"
            emu.faults.uplink_down = True
            silent("battery?")
            assert [(text, why) for _, text, why in emu.uplink_lost] == [("battery?", "uplink_down")]
            assert emu.command_texts() == ["command"]
            emu.faults.uplink_down, emu.faults.downlink_down = False, True
            n_state = emu.state_packets_lost
            silent("battery?")
            assert emu.command_texts()[-1] == "battery?" and emu.downlink_lost[-1][1].isdigit()
            assert wait_until(lambda: emu.state_packets_lost > n_state, 1.0)
            emu.faults.downlink_down = False

            assert ask("takeoff") == "ok" and emu.phase == "flying"
            emu.faults.powered_off = True
            assert wait_until(lambda: emu.phase == "landed" and emu.power_log[-1][1] == "off", 1.0)
            assert emu.position_cm[2] == 0.0 and not emu.sdk_mode  # it fell
            silent("land")
            assert emu.uplink_lost[-1][1:] == ("land", "powered_off")
            emu.faults.powered_off = False
            assert wait_until(lambda: emu.power_log[-1][1] == "boot", 1.0)
            drain_state()
            with pytest.raises(TimeoutError):  # booted out of SDK mode: no state until `command`
                state_rx.recvfrom(1024)
            silent("battery?")  # ignored before `command`
            assert ask("command") == "ok"
            state_rx.settimeout(1.0)
            assert b";time:0;" in state_rx.recvfrom(1024)[0]  # the motor-on time counts from power-on

            assert ask("takeoff") == "ok"
            emu.faults.battery_pct = 8
            assert wait_until(lambda: emu.phase == "landing", 1.0) and emu.landed_by_battery
            silent("rc 0 50 0 0")
            assert emu.refused[-1][1:3] == ("landing", "rc 0 50 0 0")
            assert ask("land") == "error Auto land"
            assert wait_until(lambda: emu.phase == "landed", 2.0)
            assert not emu.landed_by_timeout and emu.errors == []


def _drain(sock: socket.socket) -> list[bytes]:
    """Read every datagram currently queued on a non-blocking socket."""
    out = []
    while True:
        try:
            out.append(sock.recv(65536))
        except BlockingIOError:
            return out


def test_raw_video_datagrams_no_video_fault_and_close() -> None:
    """Video datagrams are ≤1460 B H.264 with SPS; no_video pauses them; close() joins threads in ~1 s."""
    with pytest.raises(ValueError):
        TelloEmulator("192.168.10.1")
    with pytest.raises(ValueError):
        TelloEmulator("127.0.1.5", client_ip="10.0.0.7")
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as cli,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as video_rx,
    ):
        cli.bind(("127.0.0.1", 0))
        cli.settimeout(1.0)
        video_rx.bind(("127.0.0.1", 0))
        video_rx.setblocking(False)
        emu = TelloEmulator(
            "127.0.1.5",
            video_port=video_rx.getsockname()[1],
            state_port=free_udp_port(),
            video_size=(320, 240),
        ).start()
        try:
            for command in (b"command", b"streamon"):
                cli.sendto(command, emu.address)
                assert cli.recvfrom(64)[0] == b"ok"
            assert wait_until(lambda: emu.video_frames_sent >= 20, 5.0), emu.errors
            assert len(emu.threads_alive) == 4
            stream = _drain(video_rx)
            assert stream and max(len(d) for d in stream) <= 1460
            assert b"\x00\x00\x00\x01\x67" in b"".join(stream)  # Annex-B SPS (repeat-headers)

            emu.faults.no_video = True
            time.sleep(0.1)
            _drain(video_rx)
            time.sleep(0.3)
            assert _drain(video_rx) == []
            emu.faults.no_video = False
            assert wait_until(lambda: bool(_drain(video_rx)), 1.0)
        finally:
            t0 = time.monotonic()
            emu.close()
            elapsed = time.monotonic() - t0
    assert emu.threads_alive == []
    print(f"emulator closed in {elapsed:.2f} s")
    assert emu.errors == []


# ------------------------------------------------------------------------- fault switches, raw UDP
@contextlib.contextmanager
def _raw_emu(ip: str, **kw: object) -> Iterator[tuple[TelloEmulator, socket.socket, socket.socket]]:
    """An emulator on ``ip`` with a raw command socket and a non-blocking state socket on 127.0.0.1."""
    kw.setdefault("takeoff_s", 0.2)
    kw.setdefault("land_s", 0.2)
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as cli,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as state_rx,
    ):
        cli.bind(("127.0.0.1", 0))
        cli.settimeout(1.0)
        state_rx.bind(("127.0.0.1", 0))
        state_rx.setblocking(False)
        emu = TelloEmulator(ip, state_port=state_rx.getsockname()[1], video_port=free_udp_port(), **kw)
        with emu:
            yield emu, cli, state_rx
        assert emu.errors == []


def _recv(cli: socket.socket, emu: TelloEmulator, timeout: float = 1.0) -> str:
    """The next reply, which must come from the emulator's command address."""
    cli.settimeout(timeout)
    data, src = cli.recvfrom(1024)
    assert src == emu.address
    return data.decode()


def _ask(cli: socket.socket, emu: TelloEmulator, text: str, timeout: float = 1.0) -> str:
    cli.sendto(text.encode(), emu.address)
    return _recv(cli, emu, timeout)


def _no_reply(cli: socket.socket, seconds: float) -> None:
    cli.settimeout(seconds)
    with pytest.raises(TimeoutError):
        cli.recvfrom(1024)


def _state(state_rx: socket.socket, timeout: float = 1.0) -> dict[str, str]:
    """Fields of the newest state packet (waits for one if none is queued)."""
    packets = _drain(state_rx)
    deadline = time.monotonic() + timeout
    while not packets and time.monotonic() < deadline:
        time.sleep(0.01)
        packets = _drain(state_rx)
    assert packets, "no state packet"
    fields_ = packets[-1].decode("ascii").strip().rstrip(";").split(";")
    return dict(f.split(":", 1) for f in fields_)


def _refusals(emu: TelloEmulator) -> list[tuple[str, str, str]]:
    return [(phase, text, reply) for _, phase, text, reply in emu.refused]


def _phases(emu: TelloEmulator) -> list[str]:
    return [phase for _, phase in emu.phase_log]


def test_fault_switch_interface_and_defaults() -> None:
    """The switches the driver tests use, with realistic defaults (SDK 3.0 EDU, rc unanswered)."""
    f = TelloFaults()
    assert (f.duplicate_reply_after_s, f.lost_replies, f.takeoff_s, f.rc_replies, f.sdk_version) == (
        None,
        set(),
        None,
        False,
        "30",
    )
    assert TelloFaults().lost_replies is not f.lost_replies
    by_name = {field.name: field for field in fields(TelloFaults)}
    assert by_name["lost_replies"].default is MISSING  # reset with TelloFaults(), not Field.default
    old_switches = {"silent", "error_replies", "reply_delay_s", "drop_state", "battery_pct", "no_video"}
    assert old_switches <= set(by_name)
    emu = TelloEmulator("127.0.1.14")
    assert _phases(emu) == ["landed"] and emu.refused == [] and emu.replies_sent == []


def test_duplicate_reply_arrives_twice_without_delaying_the_next() -> None:
    """Each reply comes again 0.5 s later; the pending duplicate does not hold back the next normal reply."""
    with _raw_emu("127.0.1.6") as (emu, cli, _):
        assert _ask(cli, emu, "command") == "ok"
        emu.faults.duplicate_reply_after_s = 0.5
        t0 = time.monotonic()
        cli.sendto(b"battery?", emu.address)
        got = [(_recv(cli, emu), time.monotonic() - t0)]
        cli.sendto(b"speed?", emu.address)
        got += [(_recv(cli, emu), time.monotonic() - t0) for _ in range(3)]
        assert [text for text, _ in got] == ["87", "100.0", "87", "100.0"]
        assert got[1][1] < 0.2, got  # the normal reply did not wait for the earlier reply's duplicate
        assert 0.45 <= got[2][1] <= 0.75, got
        sent = [(text, kind) for _, text, kind in emu.replies_sent]
        assert sent == [
            ("ok", "normal"),
            ("87", "normal"),
            ("100.0", "normal"),
            ("87", "duplicate"),
            ("100.0", "duplicate"),
        ]
        t_normal, t_dup = emu.replies_sent[1][0], emu.replies_sent[3][0]
        assert t_dup - t_normal == pytest.approx(0.5, abs=0.08)

        assert _ask(cli, emu, "takeoff") == "ok"  # the deferred ok of a takeoff is duplicated too
        assert _recv(cli, emu) == "ok"
        emu.faults.duplicate_reply_after_s = None
        assert _ask(cli, emu, "land") == "ok"
        _no_reply(cli, 0.4)
        assert emu.refused == []


def test_lost_replies_to_command_and_takeoff_still_take_off() -> None:
    """The replies to ``command`` and ``takeoff`` are lost, yet SDK mode is entered and the drone flies."""
    with _raw_emu("127.0.1.7") as (emu, cli, state_rx):
        emu.faults.lost_replies = {"command", "takeoff"}
        cli.sendto(b"command", emu.address)
        _no_reply(cli, 0.3)
        assert emu.sdk_mode
        cli.sendto(b"takeoff", emu.address)
        _no_reply(cli, 0.6)
        assert emu.phase == "flying"
        assert _phases(emu) == ["landed", "takeoff", "flying"]
        assert wait_until(lambda: _state(state_rx)["tof"] == "90", 1.0)
        assert emu.replies_sent == [] and emu.refused == []

        emu.faults.lost_replies = set()
        assert _ask(cli, emu, "takeoff") == "error"  # a client retrying the takeoff is told it already flies
        assert _refusals(emu) == [("flying", "takeoff", "error")]
        assert _ask(cli, emu, "land") == "ok"
        assert _phases(emu) == ["landed", "takeoff", "flying", "landing", "landed"]
        assert [text for _, text, _ in emu.replies_sent] == ["error", "ok"]


def test_slow_takeoff_climbs_then_hovers_until_its_ok() -> None:
    """``faults.takeoff_s``: motors on, climb to 80 cm, hover; reads answered, land refused; ok at the end."""
    with _raw_emu("127.0.1.8") as (emu, cli, state_rx):
        emu.TAKEOFF_CLIMB_S = 0.4  # a short climb so that the test sees the hover before the ok
        assert _ask(cli, emu, "command") == "ok"
        emu.faults.takeoff_s = 1.6
        t0 = time.monotonic()
        cli.sendto(b"takeoff", emu.address)
        assert wait_until(lambda: _state(state_rx)["tof"] == "90", 1.0)
        assert emu.phase == "takeoff"  # at 80 cm, before the ok
        assert _ask(cli, emu, "battery?") == "87"  # read commands are answered during the takeoff
        assert _ask(cli, emu, "land") == "error Not joystick"  # busy
        assert _recv(cli, emu, timeout=2.0) == "ok"
        elapsed = time.monotonic() - t0
        assert elapsed >= 1.6, elapsed  # the emulator's own clock: see phase_log below
        assert emu.phase == "flying"
        assert wait_until(lambda: _state(state_rx)["time"] == "1", 1.0)  # motor seconds rose since the start
        (t_takeoff, _), (t_flying, _) = emu.phase_log[1:3]
        assert t_flying - t_takeoff == pytest.approx(1.6, abs=0.1)
        assert _refusals(emu) == [("takeoff", "land", "error Not joystick")]
        assert _ask(cli, emu, "land") == "ok"


def test_busy_and_phase_refusals_are_recorded() -> None:
    """Everything refused or ignored because of the phase lands in ``refused``, and nothing else does."""
    with _raw_emu("127.0.1.9", takeoff_s=0.6, land_s=0.6) as (emu, cli, _):
        cli.sendto(b"rc 0 0 0 0", emu.address)  # before SDK mode: ignored, no reply
        _no_reply(cli, 0.2)
        assert _ask(cli, emu, "command") == "ok"
        cli.sendto(b"rc 0 10 0 0", emu.address)  # landed: ignored, no reply
        assert _ask(cli, emu, "forward 50") == "error Motor stop"
        cli.sendto(b"takeoff", emu.address)
        assert _ask(cli, emu, "takeoff") == "error Not joystick"
        assert _ask(cli, emu, "land") == "error Not joystick"
        cli.sendto(b"rc 0 10 0 0", emu.address)  # during the takeoff: ignored
        assert _recv(cli, emu) == "ok"  # the takeoff
        assert _ask(cli, emu, "forward 50") == "ok"
        cli.sendto(b"land", emu.address)
        assert _ask(cli, emu, "takeoff") == "error Not joystick"
        assert _recv(cli, emu) == "ok"  # the landing
        assert _refusals(emu) == [
            ("landed", "rc 0 0 0 0", "ignored"),
            ("landed", "rc 0 10 0 0", "ignored"),
            ("landed", "forward 50", "error Motor stop"),
            ("takeoff", "takeoff", "error Not joystick"),
            ("takeoff", "land", "error Not joystick"),
            ("takeoff", "rc 0 10 0 0", "ignored"),
            ("landing", "takeoff", "error Not joystick"),
        ]
        times = [t for t, *_ in emu.refused]
        assert times == sorted(times)
        assert [values for _, values in emu.rc_history] == [(0, 10, 0, 0)] * 2  # recorded, without effect
        assert emu.position_cm[0] == pytest.approx(50.0)


def test_land_when_landed_answers_motor_stop_and_emergency_stops_the_motors() -> None:
    """``land`` on the ground is refused; ``emergency`` gets no reply and the motor clock stops at once."""
    with _raw_emu("127.0.1.10") as (emu, cli, state_rx):
        assert _ask(cli, emu, "command") == "ok"
        assert _ask(cli, emu, "land") == "error Motor stop"
        assert _refusals(emu) == [("landed", "land", "error Motor stop")]
        assert _ask(cli, emu, "takeoff") == "ok"
        assert wait_until(lambda: _state(state_rx)["time"] == "1", 1.5)
        cli.sendto(b"emergency", emu.address)
        _no_reply(cli, 0.3)
        assert emu.phase == "landed" and emu.position_cm[2] == 0.0
        assert emu.phase_log[-1] == (emu.commands[-1][0], "landed")  # at the moment it was received
        assert wait_until(lambda: _state(state_rx)["tof"] == "10", 0.5)
        motor_s = _state(state_rx)["time"]
        time.sleep(1.1)
        assert _state(state_rx)["time"] == motor_s == "1"
        assert _refusals(emu) == [("landed", "land", "error Motor stop")]  # emergency is not a refusal
        assert _ask(cli, emu, "land") == "error Motor stop"


def test_rc_replies_firmware_answers_rc() -> None:
    """``rc_replies``: ``ok`` flying, ``error Not joystick`` otherwise; without it rc stays unanswered."""
    with _raw_emu("127.0.1.11") as (emu, cli, _):
        assert _ask(cli, emu, "command") == "ok"
        emu.faults.rc_replies = True
        assert _ask(cli, emu, "rc 0 0 0 0") == "error Not joystick"
        assert _ask(cli, emu, "takeoff") == "ok"
        assert _ask(cli, emu, "rc 0 20 0 0") == "ok"
        assert wait_until(lambda: emu.velocity_cm_s[0] > 15, 1.0)
        emu.faults.rc_replies = False
        cli.sendto(b"rc 0 0 0 0", emu.address)
        _no_reply(cli, 0.3)
        assert [values for _, values in emu.rc_history] == [(0, 0, 0, 0), (0, 20, 0, 0), (0, 0, 0, 0)]
        assert _refusals(emu) == [("landed", "rc 0 0 0 0", "error Not joystick")]
        assert _ask(cli, emu, "land") == "ok"


def test_sdk20_firmware_answers_unknown_command_to_sdk30_verbs() -> None:
    """``sdk_version="20"``: ``port``, ``downvision`` & co answer ``unknown command: <verb>``, do nothing."""
    with _raw_emu("127.0.1.12") as (emu, cli, _):
        assert _ask(cli, emu, "command") == "ok"
        assert _ask(cli, emu, "sdk?") == "30"
        emu.faults.sdk_version = "20"
        assert _ask(cli, emu, "sdk?") == "20"
        ports = (emu.state_port, emu.video_port)
        sdk30 = ["port 8890 11111", "downvision 1", "setfps high", "setbitrate 3", "motoron", "keepalive"]
        for command in [*sdk30, "reboot"]:
            assert _ask(cli, emu, command) == f"unknown command: {command.split()[0]}"
        assert (emu.state_port, emu.video_port) == ports and not emu.downvision and emu.sdk_mode
        assert (emu.fps, emu.bitrate_mbps, emu.resolution) == (30.0, 0, None)  # the video settings too
        assert _refusals(emu) == [
            ("landed", command, f"unknown command: {command.split()[0]}") for command in [*sdk30, "reboot"]
        ]
        emu.faults.sdk_version = "30"
        assert _ask(cli, emu, "downvision 1") == "ok" and emu.downvision
        assert len(emu.refused) == len(sdk30) + 1


def test_sdk30_video_settings_are_answered_kept_and_set_the_stream_format() -> None:
    """``setfps``, ``setresolution``, ``setbitrate`` with the SDK 3.0 guide's arguments answer ``ok`` and
    set the stream's format (the forward camera's size only); any other argument answers ``error`` and
    changes nothing; ``faults.unknown_commands`` makes an SDK 3.0 firmware not know a verb."""
    with _raw_emu("127.0.1.15", video_size=(320, 240)) as (emu, cli, _):
        assert _ask(cli, emu, "command") == "ok"
        assert emu.stream_format() == (30.0, (320, 240), None)  # nothing received: the constructor's
        for bad in (
            "setfps 30",
            "setfps",
            "setresolution 720p",
            "setbitrate 6",
            "setbitrate -1",
            "setbitrate x",
        ):
            assert _ask(cli, emu, bad) == "error", bad
        assert emu.stream_format() == (30.0, (320, 240), None)
        assert [text for _, text, _ in _refusals(emu)][-1] == "setbitrate x"
        for good in ("setfps low", "setresolution high", "setbitrate 5"):
            assert _ask(cli, emu, good) == "ok", good
        assert emu.stream_format() == (5.0, (960, 720), 5_000_000)
        assert _ask(cli, emu, "setresolution low") == "ok" and _ask(cli, emu, "setbitrate 0") == "ok"
        assert _ask(cli, emu, "setfps middle") == "ok"
        assert emu.stream_format() == (15.0, (648, 478), None)
        assert _ask(cli, emu, "downvision 1") == "ok"
        assert emu.stream_format() == (15.0, (320, 240), None)  # the downward picture keeps its own size
        emu.faults.unknown_commands = {"setbitrate"}
        assert _ask(cli, emu, "setbitrate 2") == "unknown command: setbitrate" and emu.bitrate_mbps == 0
        assert _refusals(emu)[-1] == ("landed", "setbitrate 2", "unknown command: setbitrate")


def test_phase_log_and_auto_land() -> None:
    """``phase_log`` follows takeoff, flight and the 15 s (here 0.5 s) auto-land; ``land`` then is refused."""
    with _raw_emu("127.0.1.13", auto_land_s=0.5, land_s=0.6) as (emu, cli, _):
        assert _ask(cli, emu, "command") == "ok"
        assert _ask(cli, emu, "takeoff") == "ok"
        assert wait_until(lambda: emu.phase == "landing", 1.5)
        assert emu.landed_by_timeout
        assert _ask(cli, emu, "land") == "error Auto land"
        assert wait_until(lambda: emu.phase == "landed", 1.5)
        assert _phases(emu) == ["landed", "takeoff", "flying", "landing", "landed"]
        times = [t for t, _ in emu.phase_log]
        assert times == sorted(times)
        assert times[2] - times[1] == pytest.approx(0.2, abs=0.1)  # takeoff_s
        assert times[3] - times[2] == pytest.approx(0.5, abs=0.1)  # auto_land_s without a command
        assert times[4] - times[3] == pytest.approx(0.6, abs=0.1)  # land_s
        assert _refusals(emu) == [("landing", "land", "error Auto land")]


# -------------------------------------------------------------------------------------------- djitellopy
def test_connect_enters_sdk_mode_and_reads_state(rig: Rig) -> None:
    """connect() sent ``command`` and got the first state packet; get_battery() comes from the state."""
    assert rig.emu.command_texts()[0] == "command"
    assert rig.emu.sdk_mode
    state = rig.tello.get_current_state()
    assert {"bat", "h", "vgx", "yaw", "tof", "baro", "agz"} <= set(state)
    assert rig.tello.get_battery() == 87
    assert rig.tello.get_distance_tof() == 10
    assert rig.tello.get_acceleration_z() == pytest.approx(-1000.0)


def test_read_commands(rig: Rig) -> None:
    """Read commands get a value; djitellopy's int parsers choke on the unit-suffixed formats."""
    assert rig.tello.send_read_command("battery?") == "87"
    assert rig.tello.query_battery() == 87
    assert rig.tello.query_sdk_version() == "30"  # Tello EDU with SDK 3.0 firmware
    assert rig.tello.send_read_command("height?") == "0dm"
    with pytest.raises(ValueError):
        rig.tello.query_height()  # int("0dm"): djitellopy limitation with the real format
    assert rig.tello.query_distance_tof() == pytest.approx(10.0)


def test_takeoff_rc_motion_and_land(rig: Rig) -> None:
    """rc values arrive as ints, velocities/height integrate, state reflects them, land brings tof to 10."""
    tello, emu = rig.tello, rig.emu
    t0 = time.monotonic()
    tello.takeoff()
    assert time.monotonic() - t0 >= emu.takeoff_s
    assert emu.phase == "flying"
    assert wait_until(lambda: tello.get_distance_tof() == 90, 1.0)  # 80 cm (h drifts: recorded.py)

    with pytest.raises(TypeError):
        tello.send_rc_control(0, 50.0, 0, 0)  # type: ignore[arg-type]  # djitellopy enforces int

    n0 = len(emu.rc_history)
    t_start = time.monotonic()
    while time.monotonic() - t_start < 0.8:
        tello.send_rc_control(0, 50, 20, 0)
        time.sleep(0.05)
    assert wait_until(lambda: len(emu.rc_history) - n0 >= 10, 1.0)
    received = [values for _, values in emu.rc_history[n0:]]
    assert all(values == (0, 50, 20, 0) for values in received)
    assert all(type(v) is int for values in received for v in values)
    # climbing at 20 cm/s reads vgz −2: positive down, as a real Tello (recorded.py)
    assert wait_until(lambda: tello.get_speed_x() == 5 and tello.get_speed_z() == -2, 1.0)
    assert tello.get_speed_y() == 0
    x, _, z = emu.position_cm
    assert x > 25 and z > 90
    assert abs(tello.get_distance_tof() - 10 - z) <= 4
    assert abs(tello.get_mission_pad_distance_x() - x) <= 7  # x carries the ground truth (cm)

    t_start = time.monotonic()
    while time.monotonic() - t_start < 0.6:
        tello.send_rc_control(0, 0, 0, 60)
        time.sleep(0.05)
    tello.send_rc_control(0, 0, 0, 0)
    assert wait_until(lambda: tello.get_speed_x() == 0 and tello.get_speed_z() == 0, 1.5)
    time.sleep(0.3)
    assert 20 <= emu.yaw_deg <= 50
    assert abs(tello.get_yaw() - emu.yaw_deg) <= 1.5

    x_before = emu.position_cm[0]
    tello.move_forward(50)  # discrete move: applied at once in the yaw direction
    dx = emu.position_cm[0] - x_before
    assert dx == pytest.approx(50 * np.cos(np.radians(emu.yaw_deg)), abs=1.0)

    tello.land()
    assert not emu.flying
    assert wait_until(lambda: tello.get_distance_tof() == 10, 1.0)  # on the floor
    assert not emu.landed_by_timeout


def _centroid(mask: np.ndarray) -> tuple[float, float] | None:
    ys, xs = np.nonzero(mask)
    if len(xs) < 50:
        return None
    return float(xs.mean()), float(ys.mean())


def _expected_centroid(index: int, emu: TelloEmulator) -> tuple[float, float]:
    x0, y0, x1, y1 = default_square(index / emu.fps, emu.video_size)
    return (x0 + x1 - 1) / 2, (y0 + y1 - 1) / 2


def test_video_stream_decodes_rendered_frames(rig: Rig) -> None:
    """≥30 decoded frames; each frame's square sits within 2 px of where the source drew that frame."""
    tello, emu = rig.tello, rig.emu
    tello.streamon()
    assert emu.streaming
    t0 = time.monotonic()
    reader = tello.get_frame_read(with_queue=True, max_queue_len=128)
    open_s = time.monotonic() - t0
    try:
        indices: list[int] = []
        downward_seen = False
        deadline = time.monotonic() + 20.0  # decoding 960x720 at 30 fps; a loaded machine decodes slower
        while time.monotonic() < deadline and not downward_seen:
            frame = reader.get_queued_frame()
            if frame is None:
                time.sleep(0.005)
                continue
            assert frame.shape == (720, 960, 3)
            index = read_frame_index(frame)
            red = (frame[..., 0] > 150) & (frame[..., 1] < 100) & (frame[..., 2] < 100)
            green = (frame[..., 1] > 150) & (frame[..., 0] < 100) & (frame[..., 2] < 100)
            for mask, downward in ((red, False), (green, True)):
                found = _centroid(mask)
                if found is None:
                    continue
                ex, ey = _expected_centroid(index, emu)
                assert abs(found[0] - ex) <= 2 and abs(found[1] - ey) <= 2, (index, found, (ex, ey))
                downward_seen |= downward
            assert not indices or index > indices[-1], "frames must arrive in order"
            indices.append(index)
            if len(indices) == 30:
                tello.set_video_direction(Tello.CAMERA_DOWNWARD)
                assert emu.downvision
        assert len(indices) >= 30, (len(indices), emu.errors)
        assert downward_seen, "no downward-camera frame decoded after downvision 1"
        sent = {index for index, _ in tuple(emu.video_log)}  # a snapshot: the video thread appends to it
        assert set(indices) <= sent
    finally:
        tello.set_video_direction(Tello.CAMERA_FORWARD)
        reader.stop()  # the worker exits on the next decoded frame, so stop it while the stream still runs
        reader.worker.join(timeout=3.0)
        tello.streamoff()
    assert not reader.worker.is_alive()
    assert not emu.streaming
    print(f"djitellopy opened the stream in {open_s:.2f} s")
    assert emu.errors == []


def test_fault_silent(rig: Rig) -> None:
    """No reply: djitellopy gives up after its (int) timeout; the command was still received."""
    tello, emu = rig.tello, rig.emu
    emu.faults.silent = True
    n0 = len(emu.commands)
    t0 = time.monotonic()
    with pytest.raises(TelloException, match="Did not receive a response"):
        tello.send_control_command("keepalive", timeout=1)
    assert 1.0 <= time.monotonic() - t0 < 2.9  # one timeout, no retry
    answer = tello.send_command_with_return("battery?", timeout=1)
    assert answer.startswith("Aborting command 'battery?'")  # read commands see this text, not an exception
    assert emu.command_texts()[n0:] == ["keepalive", "battery?"]
    emu.faults.silent = False
    assert tello.send_control_command("keepalive", timeout=1)
    assert rig.responses == []


def test_fault_error_replies(rig: Rig) -> None:
    """``error`` replies raise TelloException and the command is not executed."""
    tello, emu = rig.tello, rig.emu
    emu.faults.error_replies = True
    with pytest.raises(TelloException, match="error"):
        tello.takeoff()
    assert not emu.flying
    with pytest.raises(TelloException, match="error"):
        tello.send_read_command("battery?")
    emu.faults.error_replies = False
    assert tello.query_battery() == emu.battery


def test_fault_drop_state(rig: Rig) -> None:
    """With drop_state the emulator stops sending and the client's state dict stops changing."""
    tello, emu = rig.tello, rig.emu
    first = tello.get_current_state()
    assert wait_until(lambda: tello.get_current_state() is not first, 0.5)
    emu.faults.drop_state = True
    time.sleep(0.25)  # let a packet that was already in flight land
    sent, state = emu.state_packets_sent, tello.get_current_state()
    time.sleep(0.6)
    assert emu.state_packets_sent == sent
    assert tello.get_current_state() is state
    emu.faults.drop_state = False
    assert wait_until(lambda: tello.get_current_state() is not state, 0.5)
    # the emulator counts a packet after its sendto: the client may have it before the count moves
    assert wait_until(lambda: emu.state_packets_sent > sent, 0.5)


def test_fault_low_battery(rig: Rig) -> None:
    """A low battery shows up in state and ``battery?``; the emulator refuses to take off."""
    tello, emu = rig.tello, rig.emu
    emu.faults.battery_pct = 5
    assert wait_until(lambda: tello.get_battery() == 5, 1.0)
    assert tello.query_battery() == 5
    with pytest.raises(TelloException, match="battery low"):
        tello.takeoff()
    assert not emu.flying and not tello.is_flying
    emu.faults.battery_pct = 87
    assert wait_until(lambda: tello.get_battery() == 87, 1.0)


def test_fault_reply_delay_and_stray_late_reply(rig: Rig) -> None:
    """A late reply within the timeout works; one after the timeout becomes the answer to the next command."""
    tello, emu = rig.tello, rig.emu
    emu.faults.reply_delay_s = 0.6
    t0 = time.monotonic()
    assert tello.send_control_command("keepalive", timeout=2)
    assert 0.6 <= time.monotonic() - t0 < 2.0  # the late reply, before the 2 s timeout

    emu.faults.reply_delay_s = 1.4
    assert tello.send_command_with_return("keepalive", timeout=1).startswith("Aborting")
    emu.faults.reply_delay_s = 0.0
    assert wait_until(lambda: rig.responses == [b"ok"], 1.5)  # the stray reply is queued
    assert tello.send_command_with_return("battery?", timeout=1) == "ok"  # shifted by one
    assert wait_until(lambda: len(rig.responses) == 1, 1.0)
    assert rig.responses.pop(0).decode().isdigit()  # drain the battery value that is now stale
    assert tello.query_battery() == emu.battery


def test_auto_land_and_two_drone_routing(rig: Rig) -> None:
    """A second drone on 127.0.1.3: state is routed by source IP; it lands alone after auto_land_s."""
    emu2 = TelloEmulator(
        "127.0.1.3",
        state_port=Tello.STATE_UDP_PORT,  # djitellopy's state socket (the fixture picked its port)
        video_port=free_udp_port(),
        takeoff_s=0.2,
        land_s=0.2,
        auto_land_s=1.0,
        faults=TelloFaults(battery_pct=42),
    ).start()
    tello2 = None
    try:
        tello2 = Tello("127.0.1.3", retry_count=1, vs_udp=emu2.video_port)
        tello2.address = emu2.address
        tello2.connect()
        assert tello2.get_battery() == 42
        assert rig.tello.get_battery() == rig.emu.battery
        tello2.takeoff()
        t_takeoff = time.monotonic()
        assert emu2.flying and not rig.emu.flying
        assert wait_until(lambda: emu2.landed_by_timeout and not emu2.flying, 3.0)
        assert time.monotonic() - t_takeoff >= 1.0
        assert wait_until(lambda: tello2.get_distance_tof() == 10, 1.0)

        tello2.takeoff()  # keepalive (any command) postpones the auto-land
        assert not emu2.landed_by_timeout
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.8:
            tello2.send_keepalive()
            time.sleep(0.3)
        assert emu2.phase == "flying" and not emu2.landed_by_timeout
        tello2.land()
        assert not emu2.flying
        assert "command" not in rig.emu.command_texts()[1:]  # nothing leaked to the first drone
    finally:
        if tello2 is not None:
            tello2.is_flying = tello2.stream_on = False
            tello2.end()
        emu2.close()
