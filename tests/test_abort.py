"""Dependable abort: `flightstack abort` publishes at once, every agent process acknowledges as
soon as its bus has the abort, and the command exits 1 naming any agent that did not; in-process missions
listen on a loopback UDP operator channel. Measured: abort published → acknowledgement received (ms),
with agents in separate processes (Zenoh) and through the loopback listener of a running `flightstack
sim`. All traffic stays on 127.0.0.0/8; every process is bounded (timeouts, killed on exit)."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
import yaml

from flightstack.cli.app import main
from flightstack.comms.abort import send_abort
from flightstack.comms.certs import (
    create_mission_certs,
    operator_private_key,
    operator_public_key,
    participants,
)
from flightstack.comms.control import encode_control
from flightstack.comms.factory import free_loopback_endpoints, make_bus
from flightstack.comms.operator_link import (
    MAX_DATAGRAM_BYTES,
    LoopbackOperatorClient,
    LoopbackOperatorListener,
    default_operator_port,
    operator_port,
    signed_datagram,
)
from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import resolved_document
from flightstack.ports import free_udp_port
from flightstack.runtime.runner import OperatorAbortError, check_operator
from tests.conftest import MISSIONS, REPO

CLI = (sys.executable, "-m", "flightstack.cli.app")
ACK_LINE = re.compile(r"acknowledged by drones \[([\d, ]+)\] in ([\d.]+) ms \(pid \d+ on .+, (\w+)\)")


def acks_in(stdout: str) -> dict[int, tuple[float, str]]:
    """drone id → (time to ack in ms, channel) from `flightstack abort` output."""
    out = {}
    for ids, ms, via in ACK_LINE.findall(stdout):
        for i in ids.split(","):
            out[int(i)] = (float(ms), via)
    return out


def udp_bound(port: int) -> bool:
    """A socket is bound to 127.0.0.1:port/udp (Linux /proc/net/udp), without binding it ourselves."""
    table = Path("/proc/net/udp").read_text().splitlines()[1:]
    return any(line.split()[1] == f"0100007F:{port:04X}" for line in table)


# ------------------------------------------------------------------------------- loopback listener
def test_loopback_listener_acks_and_drops_malformed_messages() -> None:
    with LoopbackOperatorListener("lb_test", 0, {1, 2}) as lis:
        client = LoopbackOperatorClient("lb_test", lis.port)
        try:
            abort = encode_control("lb_test", "abort", {"reason": "test", "id": "a1"}, [])
            t0 = time.monotonic()
            client.send(abort)
            acks = client.receive(5.0)
            assert len(acks) == 1, client.dropped
            ack = acks[0]
            latency_ms = 1e3 * (ack.time - t0)
            print(f"loopback listener: abort sent -> ack received in {latency_ms:.2f} ms")
            assert ack.kind == "abort_ack" and ack.origin == (1, 2)
            assert ack.payload["abort_id"] == "a1" and ack.payload["drones"] == [1, 2]
            assert [(e.kind, e.payload["reason"]) for e in lis.control_events()] == [("abort", "test")]
            bad = [
                b"x" * (MAX_DATAGRAM_BYTES + 1),  # too large
                b"\xff\xfe not utf-8",
                b"{not json",
                b"[1, 2]",  # JSON, not an object
                b'{"mission": "lb_test", "kind": "abort", "payload": [1]}',
                b'{"mission": "lb_test", "kind": "abort", "payload": {"x": NaN}}',
                b'{"mission": "lb_test", "kind": "abort", "payload": {}, "origin": ["a"]}',
                b"[" * 3000 + b"]" * 1000,  # deeply nested
                encode_control("other", "abort", {"reason": "x"}, []),
                encode_control("lb_test", "status", {}, []),  # only aborts on this channel
                encode_control("lb_test", "abort_ack", {}, []),
                encode_control("lb_test", "abort", {"reason": "no id"}, []),  # control.AbortRequest
                encode_control("lb_test", "abort", {"reason": "x", "id": 2}, []),  # id not a str
            ]
            for data in bad:
                client.send(data)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as foreign:
                foreign.bind(("127.0.0.2", 0))  # loopback, but not 127.0.0.1
                foreign.sendto(abort, ("127.0.0.1", lis.port))
            expected = Counter(
                {
                    "operator: too large": 1,
                    "operator: malformed": 7,
                    "operator: other mission": 1,
                    "operator: unknown kind": 2,
                    "operator: bad abort": 2,
                    "operator: foreign sender": 1,
                }
            )
            deadline = time.monotonic() + 5.0
            while lis.dropped != expected and time.monotonic() < deadline:
                time.sleep(0.01)
            assert lis.dropped == expected
            assert client.receive(0.1) == []  # nothing acknowledged
            client.send(abort)  # still listening
            assert len(client.receive(5.0)) == 1
            deadline = time.monotonic() + 5.0
            while lis.acks_sent < 2 and time.monotonic() < deadline:  # counted just after sending
                time.sleep(0.01)
            # the same abort id again (the operator resends until acknowledged): acknowledged, queued once
            assert lis.acks_sent == 2 and lis.control_events() == [] and lis.repeats == 1
        finally:
            client.close()


def test_hardware_listener_accepts_only_aborts_signed_by_the_operator(tmp_path: Path) -> None:
    """On real drones any local process can reach the loopback port; only the holder of the
    mission's operator key can land them this way."""
    create_mission_certs("lb_test", participants([1, 2], None), tmp_path)
    other = tmp_path / "other"
    create_mission_certs("lb_test", participants([1, 2], None), other)  # same names, another CA
    pub = operator_public_key(tmp_path, "lb_test")
    key = operator_private_key(tmp_path, "lb_test")
    forged_key = operator_private_key(other, "lb_test")
    with LoopbackOperatorListener("lb_test", 0, {1, 2}, verifier=pub) as lis:
        client = LoopbackOperatorClient("lb_test", lis.port)
        try:
            abort = encode_control("lb_test", "abort", {"reason": "test", "id": "s1"}, [])
            client.send(abort)  # unsigned
            client.send(signed_datagram(abort, forged_key))  # signed by another mission's operator
            client.send(signed_datagram(abort, key)[:-3] + b"xyz")  # signature damaged
            tampered = encode_control("lb_test", "abort", {"reason": "forged", "id": "s1"}, [])
            client.send(tampered + signed_datagram(abort, key)[len(abort) :])  # body changed after signing
            expected = Counter({"operator: unsigned": 1, "operator: bad signature": 3})
            deadline = time.monotonic() + 5.0
            while lis.dropped != expected and time.monotonic() < deadline:
                time.sleep(0.01)
            assert lis.dropped == expected
            assert client.receive(0.1) == [] and lis.control_events() == []
            client.send(signed_datagram(abort, key))
            acks = client.receive(5.0)
            assert len(acks) == 1 and acks[0].payload["abort_id"] == "s1"
            assert [(e.kind, e.payload["reason"]) for e in lis.control_events()] == [("abort", "test")]
        finally:
            client.close()


def test_inproc_bus_on_hardware_yields_the_abort_to_the_runner(tmp_path: Path) -> None:
    """`flightstack fly` with the in-process bus: make_bus wraps a loopback listener on the mission's
    operator port; `flightstack abort` (send_abort, signed with the operator's key) gets every drone's
    ack; the runner's `check_operator(bus)` raises on its next call. A second process of the mission
    cannot bind it. Without the mission's certificates the bus refuses to start."""
    port = free_udp_port()
    nocerts = {"bus": {"operator_port": port, "certs": str(tmp_path / "none")}}
    with pytest.raises(MissionError, match=r"bus\.certs: .*none/ca\.pem: cannot read"):
        make_bus(load_mission(MISSIONS / "paper_experiment.yaml", nocerts, rig="lab"), "agents", {1, 2})
    bus_spec = {"operator_port": port, "certs": str(tmp_path / "certs")}
    mission = load_mission(MISSIONS / "paper_experiment.yaml", {"bus": bus_spec}, rig="lab")
    create_mission_certs(mission.name, participants([1, 2], None), tmp_path / "certs")
    assert not mission.simulated and mission.bus.kind == "inproc"
    bus = make_bus(mission, "agents", {1, 2})
    try:
        check_operator(bus)  # nothing yet
        with pytest.raises(RuntimeError, match=r"bus\.operator_port"):
            make_bus(mission, "agents", {1, 2})
        rep = send_abort(mission, "from another terminal", timeout_s=5.0)
        assert rep.missing == [] and rep.channels == [f"loopback 127.0.0.1:{port}"]
        assert all(a.via == "loopback" for a in rep.acks.values())
        print(f"loopback: abort -> ack {rep.latency_ms(1):.2f} ms")
        with pytest.raises(OperatorAbortError, match="from another terminal"):
            check_operator(bus)
    finally:
        bus.close()
    assert not udp_bound(port)  # closed with the bus
    sim = load_mission(MISSIONS / "paper_sim.yaml")
    assert make_bus(sim, "agents", {1, 2, 3}).operator is None  # type: ignore[attr-defined]


def test_operator_port_default_and_validation() -> None:
    p = default_operator_port("paper_experiment")
    assert 20000 <= p < 30000 and p == default_operator_port("paper_experiment")
    assert operator_port(load_mission(MISSIONS / "paper_experiment.yaml", rig="lab")) == p
    for bad in (80, 70000, "x"):
        with pytest.raises(MissionError, match="operator_port"):
            load_mission(MISSIONS / "paper_experiment.yaml", {"bus": {"operator_port": bad}}, rig="lab")


def test_abort_with_nobody_listening_names_every_agent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mission = _mission_file(tmp_path, free_udp_port())
    t0 = time.monotonic()
    code = main(["abort", str(mission), "--timeout", "0.3"])
    elapsed = time.monotonic() - t0
    out, err = capsys.readouterr()
    assert code == 1, out + err
    assert "agents [1, 2, 3] did not acknowledge the abort within 0.3 s" in err
    print(f"abort with nobody listening gave up after {elapsed:.2f} s (--timeout 0.3)")


def _mission_file(tmp: Path, port: int) -> Path:
    """paper_sim on the in-process bus with a loopback operator port (a simulated run listens too)."""
    m = resolved_document("paper_sim")
    m["bus"] = {"kind": "inproc", "operator_port": port}
    m["compare_modes"] = ["none"]
    path = tmp / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    return path


def test_abort_a_running_inproc_sim_from_another_terminal(tmp_path: Path) -> None:
    """`flightstack sim` (in-process bus, bus.operator_port set) runs; `flightstack abort` from another
    process: acknowledged by drones 1-3 over loopback, the run ends as an operator abort."""
    port = free_udp_port()
    mission = _mission_file(tmp_path, port)
    sim = subprocess.Popen(
        [*CLI, "sim", str(mission), "--out", str(tmp_path / "run"), "--duration", "600", "--no-progress"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60.0
        while not udp_bound(port) and sim.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert udp_bound(port), "the sim never listened"
        time.sleep(0.5)  # in the control loop
        t0 = time.monotonic()
        abort = subprocess.run(
            [sys.executable, "-m", "flightstack.cli.app", "abort", str(mission), "--timeout", "5"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
        _, sim_err = sim.communicate(timeout=60)
        print(f"abort to the sim's end: {time.monotonic() - t0:.2f} s")
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.communicate(timeout=10)
    assert abort.returncode == 0, abort.stdout + abort.stderr
    acks = acks_in(abort.stdout)
    print(abort.stdout)
    assert set(acks) == {1, 2, 3} and all(via == "loopback" for _, via in acks.values())
    assert sim.returncode == 1 and "operator abort" in sim_err, sim_err
    events = (tmp_path / "run" / "events.jsonl").read_text()
    assert '"reason": "operator abort"' in events


# ----------------------------------------------------------------------------------------- Zenoh
zenoh = pytest.importorskip("zenoh")

from flightstack.comms.factory import zenoh_bus_config  # noqa: E402
from flightstack.comms.zenoh_bus import ZenohBus  # noqa: E402
from flightstack.faults.rows_processes import ServedRun, served_ids, served_mission  # noqa: E402

IDS = served_ids()
"""The served mission's drones (its agents)."""


def test_abort_names_the_agent_that_did_not_acknowledge(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Agents 1 and 2 on the bus, agent 3 absent: exit 1 naming 3; with 3 there: exit 0."""
    m = resolved_document("paper_sim")
    endpoints = dict(zip(("1", "2", "3"), free_loopback_endpoints(3), strict=True))
    m["bus"] = {"kind": "zenoh", "zenoh": {"endpoints": endpoints, "lease_ms": 500, "security": "plaintext"}}
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    mission = load_mission(path)
    agents = {i: ZenohBus(zenoh_bus_config(mission, str(i), {i})) for i in (1, 2)}
    try:
        code = main(["abort", str(path), "--timeout", "1"])
        out, err = capsys.readouterr()
        assert code == 1, out + err
        assert "agents [3] did not acknowledge the abort within 1 s" in err
        assert set(acks_in(out)) == {1, 2}
        for bus in agents.values():
            assert [e.kind for e in bus.control_events() if e.kind == "abort"]
        agents[3] = ZenohBus(zenoh_bus_config(mission, "3", {3}))
        code = main(["abort", str(path), "--timeout", "5"])
        out, err = capsys.readouterr()
        assert code == 0, out + err
        assert set(acks_in(out)) == {1, 2, 3} and "every agent acknowledged: drones [1, 2, 3]" in out
    finally:
        for bus in agents.values():
            bus.close()


def exit_codes(run: ServedRun, timeout_s: float) -> dict[int, int]:
    """Each agent process's exit code, waiting up to timeout_s (s) for each; a test failure with the
    agent's output when one has not exited (a loaded CI machine once took over 30 s)."""
    codes = {}
    for i, agent in run.agents.items():
        try:
            codes[i] = agent.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            pytest.fail(
                f"agent {i} still runs {timeout_s:g} s after the abort: {run.agent_lines[i].rest()[-3000:]}"
            )
    return codes


def test_abort_acknowledged_by_agent_processes(tmp_path: Path) -> None:
    """Three `flightstack agent` processes fly the served simulation. An operator already connected
    publishes the abort: each agent process acknowledges (latency measured here: published → ack
    received), lands and exits as an operator abort."""
    mission_path = served_mission(tmp_path, duration_s=120.0)
    mission = load_mission(mission_path)
    with ServedRun(mission_path, tmp_path) as run:
        assert run.world_lines.wait_for("tick 200", 60), run.world_lines.rest()
        op: ZenohBus = make_bus(mission, "operator", set())  # type: ignore[assignment]
        try:
            assert op.wait_alive(set(IDS), 20.0) == set()
            time.sleep(0.2)
            rep = send_abort(mission, "test", timeout_s=5.0, zenoh_bus=op)
        finally:
            op.close()
        codes = exit_codes(run, 90.0)
        run.world.wait(timeout=30)
    ms = {i: round(rep.latency_ms(i), 2) for i in rep.acks}
    print(f"separate processes, connected operator: abort published -> ack received (ms): {ms}")
    assert rep.missing == [] and rep.sends == 1, rep
    assert {a.pid for a in rep.acks.values()} == {p.pid for p in run.agents.values()}
    assert codes == {1: 1, 2: 1, 3: 1}
    for i in IDS:
        assert "operator abort" in json.loads((tmp_path / f"agent{i}" / "summary.json").read_text())["error"]


def test_cli_abort_of_agent_processes(tmp_path: Path) -> None:
    """`flightstack abort` from a fresh process (its session connects after the first send, so the
    abort is re-sent as each agent appears): every agent acknowledges, with the time printed."""
    mission_path = served_mission(tmp_path, duration_s=120.0)
    with ServedRun(mission_path, tmp_path) as run:
        assert run.world_lines.wait_for("tick 200", 60), run.world_lines.rest()
        abort = subprocess.run(
            [sys.executable, "-m", "flightstack.cli.app", "abort", str(mission_path), "--timeout", "5"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
        codes = exit_codes(run, 90.0)
    print(abort.stdout)
    assert abort.returncode == 0, abort.stdout + abort.stderr
    acks = acks_in(abort.stdout)
    assert set(acks) == set(IDS) and all(via == "zenoh" for _, via in acks.values())
    assert "agents present [1, 2, 3], absent []" in abort.stdout
    assert codes == {1: 1, 2: 1, 3: 1}
