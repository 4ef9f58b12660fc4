"""`flightstack guard MISSION` (drivers/lab/guard.py) against loopback Tello emulators and Zenoh.

A station-topology mission on 127.0.0.8/.9 (Tello emulators in this process) with one Zenoh endpoint per
agent on free loopback ports. Each agent is a fake agent process (AGENT below): it joins the bus as agent
N (liveliness token), flies its emulated Tello with flightstack.drivers.tello.TelloDriver (connect, takeoff,
rc every
20 ms) and publishes a status (`flying`) every 0.5 s, like flightstack/runtime/runner.py. `flightstack guard`
runs as its own process; the test kills, stops or lets the agents finish, and judges at the emulators:
which datagrams came from guard's socket (its ports are in its first line), and when. Times are
time.monotonic() s (one clock for every process of this machine). Every process and thread here ends by
itself (bounded loops, --duration, timeouts); all traffic is on 127.0.0.x.
"""

from __future__ import annotations

import io
import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from flightstack.comms.control import ControlEvent
from flightstack.config.mission import load_mission
from flightstack.config.rig import resolved_document
from flightstack.drivers.guardian.process import Log
from flightstack.drivers.lab.guard import Guard
from flightstack.events import Event
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.net import wait_until
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from tests.conftest import Bound, secured_bus
from tests.conftest import status_payload as status

REPO = Path(__file__).resolve().parents[1]
IPS = {1: "127.0.0.8", 2: "127.0.0.9"}

AGENT = r"""
import dataclasses, json, os, sys, threading, time
from flightstack.drivers.lab.hardware import tello_config
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.comms.factory import make_bus
from flightstack.config.mission import load_mission

a = json.loads(sys.argv[1])
i = a["id"]
say = lambda *x: print(*x, flush=True)
mission = load_mission(a["mission"])
cfg = dataclasses.replace(tello_config(mission, i), state_port=a["state_port"])
bus = make_bus(mission, str(i), {i})
drv = TelloDriver(cfg)
drv.connect()
up = threading.Thread(target=drv.takeoff, daemon=True)
up.start()

def status():
    st = drv.state()
    bus.publish_control("status", {  # every field of runner.StatusPublisher's (control.StatusReport)
        "drone": i, "mode": "none", "t": time.monotonic(), "tick": 0, "battery_pct": st.battery_pct,
        "flying": st.flying, "link_alive": st.link_alive, "visible": False, "n_fused": 0,
        "pose_fresh": True, "rejection": None, "dropped": {}, "restarts": {},
    })

t_fly, t_next = None, 0.0
deadline = time.monotonic() + a["max_s"]
while time.monotonic() < deadline:
    now = time.monotonic()
    drv.send_rc((0, 20, 0, 0))
    if now >= t_next:
        t_next = now + 0.5
        status()
    if t_fly is None and not up.is_alive() and drv.state().flying:
        t_fly = now
        say("flying", now)
    if a["hold_s"] is not None and t_fly is not None and now - t_fly > a["hold_s"]:
        break
    if a["release"] is not None and t_fly is not None and os.path.exists(a["release"]):
        break
    time.sleep(0.02)
drv.land()
say("landed", time.monotonic(), drv.state().flying)
if a["final_status"]:
    status()
time.sleep(a["linger_s"])
drv.close()
bus.close()
say("bye", time.monotonic())
"""


class Lines:
    """A process's stdout lines, read on a thread; waits are bounded."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.q.put(line)

    def _drain(self, timeout: float) -> None:
        try:
            self.seen.append(self.q.get(timeout=timeout))
            while True:
                self.seen.append(self.q.get_nowait())
        except queue.Empty:
            pass

    def find(self, pattern: str, timeout: float) -> re.Match[str]:
        """The first line so far matching `pattern` (regex), waiting ≤ timeout s; fails the test else."""
        deadline = time.monotonic() + timeout
        while True:
            for line in self.seen:
                if m := re.search(pattern, line):
                    return m
            if time.monotonic() > deadline:
                pytest.fail(f"no line matching {pattern!r} in {timeout} s:\n{self.text()}")
            self._drain(0.05)

    def text(self) -> str:
        self._drain(0.05)
        return "".join(self.seen)


def start(*args: str) -> tuple[subprocess.Popen[str], Lines]:
    proc = subprocess.Popen(
        [sys.executable, *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    return proc, Lines(proc)


def stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.kill()
    proc.wait(timeout=10)


def write_mission(tmp: Path, emus: dict[int, TelloEmulator], state_port: int) -> Path:
    """The shipped hardware mission re-pointed at the emulators: station topology, Zenoh on loopback."""
    m = resolved_document("paper_experiment", "lab")
    m["name"] = f"guard_{tmp.name}"[:60]
    cal = REPO / "mission_configs" / "cameras" / "tello_down_template.yaml"
    for d in m["drones"]:
        d["camera"]["calibration"] = str(cal)
    # a hardware mission on Zenoh is mutual TLS with the mission's certificates
    bus = secured_bus(tmp / "certs", m["name"], [d["id"] for d in m["drones"]], ("1", "2"), lease_ms=500)
    m["bus"] = {**bus, "stale_after_s": 0.5}
    m["hardware"]["topology"] = "station"
    m["hardware"]["state_port"] = state_port
    m["hardware"]["drones"] = [
        {
            "id": i,
            "ip": e.ip,
            "control_port": e.address[1],
            "video_port": e.video_port,
            "connect_timeout_s": 3.0,
            "command_timeout_s": 1.0,
        }
        for i, e in emus.items()
    ]
    path = tmp / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    return path


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[dict[str, Any]]:
    """Two emulated Tellos (.8 sends state to the mission's state port, .9 to its own) and the mission."""
    ports = {1: free_udp_port(), 2: free_udp_port()}
    emus = {
        i: TelloEmulator(
            IPS[i],
            state_port=ports[i],
            video_port=free_udp_port(),
            takeoff_s=FAST_TAKEOFF_S,  # not about takeoff
        ).start()
        for i in IPS
    }
    try:
        yield {"emus": emus, "ports": ports, "mission": write_mission(tmp_path, emus, ports[1])}
    finally:
        for e in emus.values():
            e.close()


def agent(lab: dict[str, Any], i: int, **kw: Any) -> tuple[subprocess.Popen[str], Lines]:
    a = {"id": i, "mission": str(lab["mission"]), "state_port": lab["ports"][i], "max_s": 20.0}
    a |= {"hold_s": None, "release": None, "final_status": True, "linger_s": 0.0} | kw
    return start("-c", AGENT, json.dumps(a))


def guard(lab: dict[str, Any], *args: str) -> tuple[subprocess.Popen[str], Lines]:
    return start("-m", "flightstack.cli.app", "guard", str(lab["mission"]), *args)


def guard_ports(lines: Lines) -> dict[int, int]:
    """Drone id -> the local UDP port guard sends that drone's commands from (its first line)."""
    m = lines.find(r"watching mission .*", 10.0)
    return {int(i): int(p) for i, p in re.findall(r"drone (\d+) at [\d.:]+ \(from local port (\d+)\)", m[0])}


def from_port(emu: TelloEmulator, port: int) -> list[tuple[float, str]]:
    """(time, text) of every datagram the emulator received from local UDP port `port`."""
    return [(t, text) for t, text, addr in list(emu.senders) if addr[1] == port]


def test_guard_lands_a_killed_agents_drone_and_spares_the_live_one(
    lab: dict[str, Any], safety_bound: Bound
) -> None:
    emus = lab["emus"]
    a1, l1 = agent(lab, 1)  # flies until killed
    a2, l2 = agent(lab, 2, hold_s=7.0)  # flies 7 s, lands, says "not flying", exits normally
    g, gl = guard(lab, "--duration", "20")
    try:
        ports = guard_ports(gl)
        l1.find(r"^flying", 10.0)
        l2.find(r"^flying", 10.0)
        gl.find(r"agent 1: status flying", 15.0)
        gl.find(r"agent 2: status flying", 15.0)
        time.sleep(0.5)
        assert emus[1].flying and emus[2].flying
        t_kill = time.monotonic()
        a1.send_signal(signal.SIGKILL)
        assert wait_until(lambda: any(x == "land" for _, x in from_port(emus[1], ports[1])), 3.0)
        sent = from_port(emus[1], ports[1])
        assert all(t > t_kill for t, _ in sent), "guard sent to drone 1 while its agent was alive"
        t_rc = min(t for t, x in sent if x == "rc 0 0 0 0")
        t_land = min(t for t, x in sent if x == "land")
        print(f"kill -> rc 0 0 0 0 {1000 * (t_rc - t_kill):.0f} ms, land {1000 * (t_land - t_kill):.0f} ms")
        safety_bound("guard: rc 0 0 0 0 after an agent's kill", 1000 * (t_rc - t_kill), 500.0)
        safety_bound("guard: land after an agent's kill", 1000 * (t_land - t_kill), 500.0)
        assert t_rc <= t_land
        assert wait_until(lambda: emus[1].phase == "landed", 5.0)
        m = gl.find(r"drone 1: takeover ended \(down\) ([\d.]+) s", 6.0)
        print(f"kill -> drone 1 seen down by guard: {m[1]} s")
        # drone 2 flies on, its agent alive: nothing from guard
        assert emus[2].flying
        assert from_port(emus[2], ports[2]) == []
        assert len({addr for _, _, addr in emus[2].senders}) == 1  # its agent's socket only
        # agent 2 lands and exits normally: nothing from guard either
        l2.find(r"^bye", 15.0)
        gl.find(r"agent 2 left: last status not flying", 5.0)
        time.sleep(0.3)
        assert from_port(emus[2], ports[2]) == []
        assert emus[2].phase == "landed"
        g.send_signal(signal.SIGINT)  # Ctrl-C ends the watch
        assert g.wait(timeout=10) == 0, gl.text()
        assert "guard ends: takeovers drone 1: down" in gl.text()
    finally:
        for p in (a1, a2, g):
            stop(p)


def test_guard_ignores_an_agent_that_lands_and_exits_without_a_final_status(lab: dict[str, Any]) -> None:
    """As the runner does today: statuses stop when the landing starts; the token goes seconds later."""
    emus = lab["emus"]
    release = lab["mission"].parent / "release-agent-1"
    a1, l1 = agent(lab, 1, release=str(release), final_status=False, linger_s=2.5)
    g, gl = guard(lab, "--duration", "14")
    try:
        ports = guard_ports(gl)
        l1.find(r"^flying", 10.0)
        gl.find(r"agent 1: status flying", 15.0)
        release.touch()  # lands only once guard has seen it fly (a loaded machine may start guard late)
        l1.find(r"^bye", 10.0)
        gl.find(r"agent 1 left: last status flying but [\d.]+ s old", 5.0)
        assert g.wait(timeout=30) == 0, gl.text()  # --duration ends it
        assert from_port(emus[1], ports[1]) == []
        assert emus[1].phase == "landed"
        assert "guard ends: takeovers none; departures not in flight 1" in gl.text()
    finally:
        for p in (a1, g):
            stop(p)


def test_guard_lands_a_stopped_agents_drone_after_the_lease(lab: dict[str, Any], safety_bound: Bound) -> None:
    """SIGSTOP: the process keeps its TCP links, its token goes when the 0.5 s Zenoh lease expires."""
    emus = lab["emus"]
    a1, l1 = agent(lab, 1)
    g, gl = guard(lab, "--duration", "12", "--give-up", "4")
    try:
        ports = guard_ports(gl)
        l1.find(r"^flying", 10.0)
        gl.find(r"agent 1: status flying", 15.0)
        time.sleep(0.3)
        t_stop = time.monotonic()
        a1.send_signal(signal.SIGSTOP)
        assert wait_until(lambda: any(x == "land" for _, x in from_port(emus[1], ports[1])), 3.0)
        sent = from_port(emus[1], ports[1])
        t_rc = min(t for t, x in sent if x == "rc 0 0 0 0")
        t_land = min(t for t, x in sent if x == "land")
        print(f"stop -> rc 0 0 0 0 {1000 * (t_rc - t_stop):.0f} ms, land {1000 * (t_land - t_stop):.0f} ms")
        safety_bound(
            "guard: rc 0 0 0 0 after an agent's SIGSTOP (0.5 s lease)", 1000 * (t_rc - t_stop), 1500.0
        )
        safety_bound("guard: land after an agent's SIGSTOP (0.5 s lease)", 1000 * (t_land - t_stop), 1500.0)
        assert wait_until(lambda: emus[1].phase == "landed", 5.0)
        # the stopped agent holds the state port: no telemetry, guard re-sends until --give-up
        m = gl.find(r"drone 1: takeover ended \(gave up\) ([\d.]+) s after agent 1 vanished, (\d+) send", 8.0)
        assert 3 <= int(m[2]) <= 6
        assert g.wait(timeout=30) == 0, gl.text()
    finally:
        for p in (a1, g):
            stop(p)


class FakeBus:
    """The two things guard reads of a ZenohBus, filled by the test."""

    def __init__(self) -> None:
        self.presence: list[Event] = []
        self.controls: list[ControlEvent] = []

    @property
    def presence_events(self) -> list[Event]:
        return list(self.presence)

    def control_events(self) -> list[ControlEvent]:
        out, self.controls = self.controls, []
        return out


def test_guard_stops_sending_when_the_agent_is_back(lab: dict[str, Any]) -> None:
    """In process, with a fake bus: a takeover ends at once when the agent's token reappears."""
    emu, bus, out = lab["emus"][1], FakeBus(), io.StringIO()
    log = Log(None, name="guard", stream=out)
    with Guard(load_mission(lab["mission"]), bus, log, land_resend_s=0.1) as g:
        port = g.local_port(1)

        def steps(seconds: float) -> None:
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                g.step(time.monotonic())
                time.sleep(0.01)

        bus.presence.append(Event(time.monotonic(), 1, "joined", source="bus", clock="monotonic"))
        bus.controls.append(ControlEvent(time.monotonic(), "status", status(1, flying=True), (1,)))
        bus.controls.append(ControlEvent(time.monotonic(), "status", status(2, flying=True), (1,)))
        malformed = {"drone": 1, "flying": False}  # not a full status: ignored, 1 is still flying
        bus.controls.append(ControlEvent(time.monotonic(), "status", malformed, (1,)))
        steps(0.1)
        assert from_port(emu, port) == []
        bus.presence.append(Event(time.monotonic(), 1, "left", source="bus", clock="monotonic"))
        steps(0.35)
        sent = [x for _, x in from_port(emu, port)]
        assert sent[:2] == ["rc 0 0 0 0", "land"] and len(sent) >= 6  # re-sent every 0.1 s
        bus.presence.append(Event(time.monotonic(), 1, "joined", source="bus", clock="monotonic"))
        steps(0.05)
        n = len(from_port(emu, port))
        steps(0.4)
        assert len(from_port(emu, port)) == n  # nothing more once the agent is back
        assert [t.result for t in g.summary.takeovers] == ["agent back"]
        assert g.local_port(1) != port  # a fresh lander for its next flight
        assert 2 not in g.agents or g.agents[2].flying is None  # a status about 2 from 1's process: ignored
    log.close()
    assert "agent 1 is back: nothing more is sent to drone 1" in out.getvalue()


def test_guard_refuses_access_point_topology(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from flightstack.cli.app import main

    assert main(["guard", str(REPO / "mission_configs" / "paper_experiment.yaml"), "--rig", "lab"]) == 2
    err = capsys.readouterr().err
    assert "hardware.topology is 'access_point'" in err and "topology: station" in err
