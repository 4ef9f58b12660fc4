"""Real Tello recordings (../shared/data/peers/tello/, provenance in its README.md) replayed on loopback.

The recorded flight (xg590, an original Tello) is served by `TelloReplayer` (sim_backend/emulators/tello/
replay.py) to a raw UDP client, which checks the replayer against the recording (reply delays, state
bytes and times, unrecorded commands, `land` jumping to the landing), and to the real `TelloDriver`, which
must take off and land on it (issue acceptance: `takeoff()` returns; `land()` sends `land` within 1 s; also
with the takeoff `ok` 0.1 s later and with 25 % of the state lines dropped, seeded). Every H.264 dump goes
through the driver's video receiver (drivers/tello/camera.py) in the Tello's datagrams.

The recordings are read in place, never copied: without the folder every test skips with the reason, and
fails under CI=true (tests.conftest.skip_or_fail_in_ci). Each case that ran a recording records
`("replay_case", name)` in its report's user_properties, and the session's summary prints how many ran.
"""

from __future__ import annotations

import random
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from flightstack.drivers.tello.config import TelloCommandError, TelloConfig
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.traffic import TelloSession, TrafficWriter, read_traffic, read_xg590_db
from flightstack.drivers.tello.video_check import split_nals
from flightstack.hal import FlightPhase
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.tello.replay import (
    TelloReplayer,
    access_units,
    motor_time_on,
    video_datagrams,
)
from tests.conftest import PEERS, Bound, skip_or_fail_in_ci

pytestmark = pytest.mark.system  # loopback sockets and threads, real-time replays

TELLO = PEERS / "tello"
FLIGHT = "xg590_Tello_flight_log_20201018_052457.db"
IP = "127.0.0.38"  # the replayed drone (its own address: the driver routes state by source ip)
CASE = "replay_case"
"""The user_properties key of a case that ran a recording."""
TIME_TOL_S = 0.25
"""How late a datagram may leave after its recorded offset on a loaded 2-core machine (s; measured: up to
0.2 s at a load average of 8, the median a few ms). Never early."""
# What the recording holds (../shared/data/peers/README.md; times from the `takeoff` command, s)
TAKEOFF_OK_S = 8.70
LAND_OK_S = 4.23


def recording(request: pytest.FixtureRequest, name: str) -> Path:
    """The path of recording `name`; skip (fail under CI=true) without it; counts the case."""
    path = TELLO / name
    if not path.is_file():
        skip_or_fail_in_ci(f"{path} absent: the real recordings of ../shared/data/peers/ are read in place")
    request.node.user_properties.append((CASE, name))
    return path


@pytest.fixture(scope="module", autouse=True)
def replay_summary(request: pytest.FixtureRequest) -> Iterator[None]:
    """Print at the session's end how many replay cases ran (without xdist; under it, see the lead's
    conftest hook on the `replay_case` user_properties)."""

    class Summary:
        @staticmethod
        def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
            names = [
                value
                for reports in terminalreporter.stats.values()
                for report in reports
                if getattr(report, "when", None) == "call"
                for key, value in getattr(report, "user_properties", ())
                if key == CASE
            ]
            terminalreporter.write_line(
                f"real-recording replay cases run: {len(names)} ({', '.join(sorted(set(names))) or 'none'})"
            )

    pm = request.config.pluginmanager
    if not pm.has_plugin("tello-replay-summary"):
        pm.register(Summary(), "tello-replay-summary")
    yield


@pytest.fixture
def flight(request: pytest.FixtureRequest) -> TelloSession:
    return read_xg590_db(recording(request, FLIGHT))


def t_cmd(session: TelloSession, text: str) -> float:
    rec = session.first("sent", text)
    assert rec is not None, text
    return rec.t


def motor_time(line: bytes) -> int:
    """The `time` field (motor-on s) of a state line."""
    return int(line.split(b";time:")[1].split(b";")[0])


def t_reply(session: TelloSession, command: str) -> float:
    """The recorded delay of the first reply to `command` (s)."""
    t = t_cmd(session, command)
    return min(r.t for r in session.of("reply") if r.t > t) - t


class Client:
    """A raw UDP client of the replayer: commands from its own socket, state on its own port."""

    def __init__(self) -> None:
        self.state_port = free_udp_port()
        self.cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.cmd.bind(("127.0.0.1", 0))
        self.state = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.state.bind(("127.0.0.1", self.state_port))
        self.state.setblocking(False)
        self.replies: list[tuple[float, bytes]] = []
        self.lines: list[tuple[float, bytes]] = []

    def send(self, rep: TelloReplayer, text: str) -> float:
        t = time.monotonic()
        self.cmd.sendto(text.encode(), rep.address)
        return t

    def pump(self, seconds: float) -> None:
        """Receive replies and state lines for `seconds`, stamping each on arrival."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            self.cmd.settimeout(min(0.01, left))
            try:
                data, _ = self.cmd.recvfrom(2048)
                self.replies.append((time.monotonic(), data))
            except TimeoutError:
                pass
            while True:
                try:
                    data, _ = self.state.recvfrom(2048)
                except BlockingIOError:
                    break
                self.lines.append((time.monotonic(), data))

    def close(self) -> None:
        self.cmd.close()
        self.state.close()


@pytest.fixture
def client() -> Iterator[Client]:
    c = Client()
    yield c
    c.close()


# ---------------------------------------------------------------------------------- the replayer itself
@pytest.mark.parametrize("extra_s", [0.0, 0.1])
def test_takeoff_segment_as_recorded(flight: TelloSession, client: Client, extra_s: float) -> None:
    """`command` and `takeoff` answered at their recorded delays (+ extra_s); the state lines after
    `takeoff` byte for byte the recorded ones at their recorded offsets; before it the drone holds its
    recorded ground line."""
    t_takeoff = t_cmd(flight, "takeoff")
    with TelloReplayer(flight, IP, state_port=client.state_port, reply_delay_extra_s=extra_s) as rep:
        sent = client.send(rep, "command")
        client.pump(1.0)
        assert [r for _, r in client.replies] == [b"ok"]
        assert 0 <= client.replies[0][0] - sent - (t_reply(flight, "command") + extra_s) <= TIME_TOL_S
        ground = [line for _, line in client.lines]
        assert ground and set(ground) == {rep.lines[0][1]}  # one recorded line, then its repeats
        sent = client.send(rep, "takeoff")
        client.pump(TAKEOFF_OK_S + extra_s + 0.5)
    assert t_reply(flight, "takeoff") == pytest.approx(TAKEOFF_OK_S, abs=0.005)
    assert [r for _, r in client.replies] == [b"ok", b"ok"]
    t_in, k_in = rep.received[1].t, rep.received[1].matched  # when the replayer took `takeoff`
    assert k_in is not None
    ok = [x.t - t_in for x in rep.sent if x.kind == "reply" and x.served > k_in]
    print(f"takeoff ok after {ok[0]:.3f} s (recorded {TAKEOFF_OK_S} s + {extra_s} s)")
    assert len(ok) == 1 and 0 <= ok[0] - (t_reply(flight, "takeoff") + extra_s) <= TIME_TOL_S
    assert [line for _, line in client.lines] == [x.data for x in rep.sent if x.kind == "state"]  # no loss
    after = [x for x in rep.sent if x.kind == "state" and x.served > k_in]  # decided after it: no race
    recorded = [(t - t_takeoff, line) for t, line in rep.lines if t >= t_takeoff]
    assert all(x.origin == "recorded" for x in after)
    assert [x.data for x in after] == [line for _, line in recorded[: len(after)]]
    late = sorted(x.t - t_in - r for x, (r, _) in zip(after, recorded, strict=False))
    median, most = late[len(late) // 2], late[-1]
    print(
        f"{len(after)} lines after takeoff, late {median * 1000:.0f} ms (median), {most * 1000:.0f} ms (most)"
    )
    assert len(after) >= 80  # 9.2 s of a ~10 Hz stream
    assert late[0] >= 0 and most <= TIME_TOL_S and median <= 0.05
    assert rep.errors == []


def test_unrecorded_commands_get_no_reply(flight: TelloSession, client: Client) -> None:
    """rc, queries, streamon, `land` on the ground (not before the recorded takeoff) and a second
    `command`: no reply, nothing served; the drone goes on holding its ground line."""
    with TelloReplayer(flight, IP, state_port=client.state_port) as rep:
        client.send(rep, "command")
        client.pump(0.5)
        for text in ("rc 0 0 0 0", "battery?", "sdk?", "sn?", "streamon", "land", "command", "forward 50"):
            client.send(rep, text)
        client.pump(1.5)
        assert [r for _, r in client.replies] == [b"ok"]  # the first `command`'s
        assert rep.served == 1 and rep.counts["unmatched"] == 8
        assert [r.matched for r in rep.received] == [0] + [None] * 8
        assert {line for _, line in client.lines} == {rep.lines[0][1]}
        assert rep.counts["state_synthesised"] >= 10


@pytest.mark.parametrize("after_end", ["repeat", "silence"])
def test_land_jumps_to_recorded_landing(flight: TelloSession, client: Client, after_end: str) -> None:
    """`land` 1 s into the climb (the recording still at `takeoff`) jumps to the recorded landing: the
    next lines are the landing's, its `ok` comes at +4.23 s, the takeoff's never; after the last line the
    landed drone repeats it (after_end="repeat") or falls silent."""
    t_land = t_cmd(flight, "land")
    with TelloReplayer(flight, IP, state_port=client.state_port, after_end=after_end) as rep:  # type: ignore[arg-type]
        client.send(rep, "command")
        client.send(rep, "takeoff")
        client.pump(1.0)
        n_before = len(client.lines)
        sent = client.send(rep, "land")
        client.pump(LAND_OK_S + 1.5)
        end = len(client.lines)
        client.pump(3.0)  # past the takeoff's recorded ok (+8.70 s): cancelled by the land
    assert [r for _, r in client.replies] == [b"ok", b"ok"] and rep.counts["replies_cancelled"] == 1
    ok = client.replies[-1][0] - sent
    print(f"land ok after {ok:.3f} s (recorded {t_reply(flight, 'land'):.3f} s)")
    assert 0 <= ok - t_reply(flight, "land") <= TIME_TOL_S and t_reply(flight, "land") == pytest.approx(
        LAND_OK_S, abs=0.005
    )
    landing = [line for t, line in rep.lines if t >= t_land]
    got = [line for t, line in client.lines[n_before:end] if t >= sent]
    assert got[: len(landing)] == landing  # the whole recorded landing, from its first line
    assert rep.served == len(rep.commands)
    synthesised = [s for s in rep.sent if s.origin == "synthesised" and s.rec_t == rep.lines[-1][0]]
    if after_end == "repeat":
        assert len(synthesised) >= 5 and all(s.data == rep.lines[-1][1] for s in synthesised)
        assert len(client.lines) > end
    else:
        assert synthesised == [] and len(client.lines) == end


def test_flight_plays_on_then_hovers_until_land(flight: TelloSession, client: Client) -> None:
    """After the takeoff's `ok` and no further command the recorded flight goes on (forward, left, back,
    right: their lines, not their replies) up to the recorded `land`, then the drone hovers on its last
    line, motor `time` counting on, until `land` comes; then the recorded landing."""
    t_land = t_cmd(flight, "land")
    with TelloReplayer(flight, IP, state_port=client.state_port) as rep:
        client.send(rep, "command")
        client.send(rep, "takeoff")
        client.pump(t_land - t_cmd(flight, "takeoff") + 2.5)
        t_takeoff = t_cmd(flight, "takeoff")
        states = [x for x in rep.sent if x.kind == "state"]
        hover = [x for x in states if x.origin == "synthesised" and x.rec_t > t_takeoff]
        flown = [x for x in states if x.origin == "recorded" and x.rec_t >= t_takeoff]
        client.send(rep, "land")
        client.pump(1.0)
    assert [x.data for x in flown] == [line for t, line in rep.lines if t_takeoff <= t < t_land]
    last = flown[-1]
    assert len(hover) >= 15 and {x.rec_t for x in hover} == {last.rec_t}
    times = [motor_time(x.data) for x in hover]
    print(
        f"{len(flown)} recorded lines to the land, then {len(hover)} repeats, time {times[0]}..{times[-1]} s"
    )
    assert times == sorted(times) and times[-1] >= times[0] + 1
    t0 = motor_time(last.data)
    assert all(x.data == motor_time_on(last.data, n - t0) for x, n in zip(hover, times, strict=True))
    assert [r for _, r in client.replies] == [b"ok", b"ok"]  # command, takeoff; not the manoeuvres'
    k_land = rep.received[-1].matched
    assert k_land is not None and rep.commands[k_land][1].strip().lower() == "land"
    landing = [x for x in rep.sent if x.kind == "state" and x.served > k_land]
    assert landing and landing[0].origin == "recorded" and landing[0].rec_t >= t_land


def test_drop_state_is_seeded(flight: TelloSession, client: Client) -> None:
    """drop_state=0.25 drops about a quarter of the state datagrams: exactly those random.Random(seed)
    picks, one draw per datagram due; the client receives the others."""
    with TelloReplayer(flight, IP, state_port=client.state_port, drop_state=0.25, seed=38) as rep:
        client.send(rep, "command")
        client.send(rep, "takeoff")
        client.pump(5.0)
    rng = random.Random(38)
    assert rep.drops == [rng.random() < 0.25 for _ in rep.drops]
    c = rep.counts
    dropped = c["state_dropped_recorded"] + c["state_dropped_synthesised"]
    share = dropped / len(rep.drops)
    print(f"dropped {dropped} of {len(rep.drops)} state datagrams ({100 * share:.0f} %), seed 38")
    assert dropped == sum(rep.drops) and len(rep.drops) >= 40 and 0.15 <= share <= 0.35  # seed 38: 20-26 %
    assert len(client.lines) == len(rep.drops) - dropped == c["state_recorded"] + c["state_synthesised"]


def test_refuses_other_addresses(flight: TelloSession) -> None:
    for kw in ({"ip": "192.168.10.1"}, {"client_ip": "10.0.0.2"}, {"drop_state": 1.0}):
        with pytest.raises(ValueError):
            TelloReplayer(flight, **kw)  # type: ignore[arg-type]


def test_replays_a_flight_own_traffic_file(tmp_path: Path, client: Client) -> None:
    """A TrafficWriter file (what every flight records) is served the same way: `takeoff` answered at
    its recorded 0.5 s, its state lines as written (this case needs no recording)."""
    w = TrafficWriter(tmp_path / "tello.jsonl", IP)
    lines = [
        b"mid:-1;h:%d;tof:%d;time:%d;\r\n" % (h, h + 10, 3 + k // 10) for k, h in enumerate(range(0, 40, 2))
    ]
    w.sent(100.0, "command")
    w.reply(100.02, "ok")
    w.state(100.05, lines[0])
    w.sent(100.1, "takeoff")
    for k, line in enumerate(lines[1:]):  # in time order, as a flight writes them
        w.state(100.15 + 0.1 * k, line)
        if k == 4:
            w.reply(100.6, "ok")
    w.sent(102.2, "land")
    w.reply(102.4, "ok")
    w.close()
    session = read_traffic(w.path)
    assert not session.dropped and len(session.records) == 26
    with TelloReplayer(session, IP, state_port=client.state_port) as rep:
        client.send(rep, "command")
        client.pump(0.3)
        sent = client.send(rep, "takeoff")
        client.pump(2.3)
    assert [r for _, r in client.replies] == [b"ok", b"ok"]
    assert 0.5 <= client.replies[1][0] - sent <= 0.5 + TIME_TOL_S
    got = [line for t, line in client.lines if t > sent]
    assert got[: len(lines) - 1] == lines[1:] and set(got[len(lines) - 1 :]) == {lines[-1]}  # then hovers


# ------------------------------------------------------------------------------ the real driver on it
@pytest.mark.parametrize(
    "replay",
    [{}, {"reply_delay_extra_s": 0.1}, {"drop_state": 0.25, "seed": 38}],
    ids=["as-recorded", "ok-0.1s-later", "25pc-state-dropped"],
)
def test_driver_takes_off_and_lands_on_recorded_flight(
    flight: TelloSession, safety_bound: Bound, replay: dict[str, float]
) -> None:
    """TelloDriver (its default thresholds) on the recorded flight: `takeoff()` returns; `land()`, called
    whatever takeoff() did, sends `land` within 1 s and only once, and the driver ends on the ground."""
    with TelloReplayer(flight, IP, state_port=free_udp_port(), **replay) as rep:  # type: ignore[arg-type]
        cfg = TelloConfig(
            host=rep.ip,
            control_port=rep.address[1],
            state_port=rep.state_port,
            video_port=free_udp_port(),
            connect_timeout_s=2.0,
            command_timeout_s=1.0,
        )
        d = TelloDriver(cfg)
        failed: dict[str, str] = {}
        try:
            d.connect()
            t0 = time.monotonic()
            try:
                d.takeoff()
            except TelloCommandError as exc:
                failed["takeoff"] = str(exc)
            took = time.monotonic() - t0
            t_call = time.monotonic()
            try:
                d.land()
            except TelloCommandError as exc:
                failed["land"] = str(exc)
            landed_in = time.monotonic() - t_call
        finally:
            d.close()
    events = [f"{e.kind}: {e.detail}" for e in d.events if e.kind not in ("state", "phase")][-10:]
    lands = [round(r.t - t_call, 2) for r in rep.received if r.text.strip() == "land" and r.t >= t_call]
    print(
        f"{replay}: takeoff() after {took:.2f} s, land() after {landed_in:.2f} s, failed {failed}; "
        f"land sent at {lands} s; {dict(rep.counts)}; events {events}"
    )
    assert "takeoff" not in failed, failed
    assert lands, (failed, events)
    safety_bound("land sent after land() was called, replayed real flight", lands[0] * 1000, 1000)
    assert len(lands) == 1 and "land" not in failed, (lands, failed, events)
    assert d.phase is FlightPhase.GROUND


# ------------------------------------------------------------------------------------------ the video
def dump(request: pytest.FixtureRequest, name: str) -> bytes:
    data = recording(request, name).read_bytes()
    return bytes.fromhex(data.decode("ascii").strip()) if name == "filippofinke_video.h264" else data


AUD = b"\x00\x00\x00\x01\x09\xf0"
"""An access unit delimiter: what starts the next frame, so that the parser completes the dump's last."""


def receive(
    units: list[bytes], drop: Callable[[int, int, int], bool] | None = None, tags: list[bool] | None = None
) -> Counter[str]:
    """`units` sent in the Tello's datagrams to a VideoReceiver, each datagram after the receiver took
    the one before (no loss on loopback), then an AUD; the receiver's counts, "published_at_splice"
    (frames published when the first 60 units were in), "alive" and "dropped". drop(k, j, n): leave out
    datagram j of the n of unit k. tags: filled with each published frame's `damaged`, in order."""
    pytest.importorskip("av")
    from flightstack.drivers.tello.camera import VideoReceiver

    port = free_udp_port()
    rx = VideoReceiver(port, "127.0.0.1")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind((IP, 0))
    try:
        n, at_60, dropped, seen = 0, -1, 0, 0
        for k, unit in enumerate([*units, AUD]):
            if k == 61:  # unit 61 began: the parser completed unit 60
                at_60 = rx.counts["frames"]
            datagrams = video_datagrams(unit)
            for j, datagram in enumerate(datagrams):
                if drop is not None and k < len(units) and drop(k, j, len(datagrams)):
                    dropped += 1
                    continue
                tx.sendto(datagram, ("127.0.0.1", port))
                n += 1
                deadline = time.monotonic() + 10.0
                while rx.counts["datagrams"] < n and time.monotonic() < deadline:
                    time.sleep(0.0005)
                item = rx.latest()
                if tags is not None and item is not None and item.seq > seen:  # one frame per unit at most
                    seen = item.seq
                    tags.append(item.damaged)
        deadline = time.monotonic() + 10.0
        while rx.counts["datagrams"] < n and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.3)  # the last decode
        out = {**rx.counts, "published_at_splice": at_60, "alive": int(rx.alive()), "sent": n}
        return Counter({**out, "dropped": dropped})
    finally:
        tx.close()
        rx.close()


def kinds(unit: bytes) -> list[int]:
    return [nal[0] & 0x1F for nal in split_nals(unit) if nal]


def test_devconx_test_60_intact_frames_then_the_splice(request: pytest.FixtureRequest) -> None:
    """960×720 Main: SPS, PPS, one IDR, 119 P frames; frame_num 0..59 then 7..66 (two dumps spliced):
    the 60 frames before the splice are published clean, the splice is found (a frame_num gap) and what
    FFmpeg decodes after it (8 of the 60 units: it decodes no more of them, with or without error
    detection) is published tagged concealed: nothing waits for a keyframe that never comes."""
    units = access_units(dump(request, "devconx_test.h264"))
    assert len(units) == 120 and kinds(units[0]) == [7, 8, 5]
    assert sum(5 in kinds(u) for u in units) == 1  # no second IDR: a keyframe interval > 2 s at 30 fps
    c = receive(units)
    print({k: v for k, v in c.items() if v})
    assert c["published_at_splice"] == 60 and c["frames"] == 68 and c["concealed"] == 8
    assert c["frame_gap"] == 1 and c["damaged_units"] == 60 and c["resync"] == 1
    assert c["datagrams"] == c["sent"] and c["alive"] and c["reader_error"] == 0


def _first_60(request: pytest.FixtureRequest) -> list[bytes]:
    """devconx_test's intact part: its IDR and the 59 P frames before the splice (~9 datagrams each)."""
    return access_units(dump(request, "devconx_test.h264"))[:60]


@pytest.mark.parametrize("where", ["middle", "tail", "head"])
def test_a_lost_datagram_damages_frames_but_drops_none(request: pytest.FixtureRequest, where: str) -> None:
    """One datagram of frame 10 left out (its middle one, its last, its first): every frame the decoder
    makes is published (nothing waits for a keyframe). A lost head or tail breaks the Tello's framing and
    is found: the 50 frames from there on are tagged concealed (no IDR follows; with a lost head frame 10
    itself is not decoded, and frame 11 on counts, 49 + the frame gap's own). A lost middle datagram
    breaks no framing rule: how many frames the decoder's checks tag is printed, not asserted (the gate
    downstream does not rely on it)."""
    units = _first_60(request)

    def drop(k: int, j: int, n: int) -> bool:
        return k == 10 and j == {"middle": n // 2, "tail": n - 1, "head": 0}[where]

    assert len(video_datagrams(units[10])) >= 3
    tags: list[bool] = []
    c = receive(units, drop, tags)
    print(where, {k: v for k, v in c.items() if v}, f"tagged {sum(tags)} of {len(tags)}")
    assert c["dropped"] == 1 and c["alive"] and c["reader_error"] == 0
    # a frame whose head (its slice header) is lost cannot be decoded: 59 frames then, else 60
    assert c["frames"] == (59 if where == "head" else 60)
    if where != "middle":
        assert c["lost_tail" if where == "tail" else "lost_head"] == 1
        assert c["concealed"] == 50 and not any(tags[:9]) and all(tags[11:])


def test_bursty_datagram_loss_keeps_the_frames_coming(request: pytest.FixtureRequest) -> None:
    """The 60 intact frames through a seeded bursty loss of their datagrams (5 % in bursts of 3, the
    simple Gilbert chain of flightstack.netem; the IDR's kept, or nothing is a picture): frames keep being
    published after every loss, tagged from the first detected loss on, and nothing is dropped but what
    the decoder could not decode."""
    from flightstack.netem import LinkModel, LinkProfile

    units = _first_60(request)
    chain = LinkModel(LinkProfile.bursty(0.05, 3.0), 4, "tello1", "video")

    def drop(k: int, j: int, n: int) -> bool:
        return k > 0 and not chain.decide(0.0, 1460)

    tags: list[bool] = []
    c = receive(units, drop, tags)
    print({k: v for k, v in c.items() if v}, f"tagged {sum(tags)} of {len(tags)}")
    assert c["dropped"] >= 5 and c["alive"] and c["reader_error"] == 0
    assert c["frames"] + c["decode_error"] >= 55, c  # a unit that lost all its datagrams makes no frame
    first = tags.index(True)  # (tags: the frames seen between datagrams; one may be missed)
    assert all(tags[first:]) and c["concealed"] >= len(tags) - first and c["frames"] >= len(tags)


def test_devconx_temp_4_access_units(request: pytest.FixtureRequest) -> None:
    """SPS, PPS, IDR; P; P; IDR: 4 access units, 4 frames published, no damage."""
    units = access_units(dump(request, "devconx_temp.h264"))
    assert [kinds(u) for u in units] == [[7, 8, 5], [1], [1], [5]]
    c = receive(units)
    print({k: v for k, v in c.items() if v})
    assert c["frames"] == 4 and c["concealed"] == 0 and c["damaged_units"] == 0 and c["decode_error"] == 0


@pytest.mark.parametrize("name", ["devconx_file.h264", "filippofinke_video.h264"])
def test_dump_without_idr_publishes_nothing(request: pytest.FixtureRequest, name: str) -> None:
    """A dump starting mid-GOP (devconx_file: 60 P frames) and the hex P slices of filippofinke (7 slices,
    each a picture's first: first_mb_in_slice 0): no frame published, the receiver alive, no crash."""
    units = access_units(dump(request, name))
    assert units and all(kinds(u) == [1] for u in units)
    c = receive(units)
    print(name, len(units), {k: v for k, v in c.items() if v})
    assert c["frames"] == 0 and c["damaged_units"] == len(units)
    assert c["alive"] and c["reader_error"] == 0 and c["datagrams"] == c["sent"]


def test_hover_repeats_count_motor_time_on() -> None:
    """While the replayer holds a flying drone before `land`, its repeats' `time` (motor-on s) counts on
    in whole seconds; every other byte is the recorded line's."""
    line = b"pitch:0;roll:0;yaw:-26;h:40;bat:33;time:66;agx:11.00;\r\n"
    assert motor_time_on(line, 2.7) == line.replace(b"time:66;", b"time:68;")
    assert motor_time_on(line, 0.9) == line and motor_time_on(b"h:40;", 5.0) == b"h:40;"


def _slices(unit: bytes) -> int:
    return sum(kind in (1, 5) for kind in kinds(unit))


def test_the_emulator_encodes_one_slice_a_picture_as_the_tello_does(request: pytest.FixtureRequest) -> None:
    """Every picture of the recorded stream is one slice (a lost datagram spoils the rest of its picture);
    the emulator's encoder makes one too, whatever the machine's core count (x264's zerolatency cuts a
    picture into one slice per thread: two on a 2-core machine, where a loss spoiled only half a picture)."""
    pytest.importorskip("av")
    import numpy as np

    from flightstack.sim_backend.emulators.tello.video import frame_datagrams, make_encoder

    recorded = [_slices(u) for u in access_units(dump(request, "devconx_test.h264"))]
    assert set(recorded) == {1}, recorded
    encoder = make_encoder((960, 720), 30.0, 30)
    rng = np.random.default_rng(0)
    emulated = [
        _slices(b"".join(frame_datagrams(encoder, rng.integers(0, 256, (720, 960, 3), dtype=np.uint8), k)))
        for k in range(3)
    ]
    assert emulated == [1, 1, 1], emulated
