"""One computer, one Wi-Fi adapter per Tello (docs/real-lab.md, "Choose a topology"): two access-point
Tellos, both 192.168.10.1 on the real ports 8889/8890/11111, each behind its own interface, flown by one
`flightstack run paper_experiment --rig LAB` whose lab file names the interfaces; and, the flight killed,
landed by its guardian, each through its own interface.

The set-up is made here in network namespaces (root and iproute2; skipped with the reason elsewhere,
failing under CI=true), with unique names, deleted in `finally` with every process left in them: the
computer's namespace (the flight, its guardian, the NatNet and rover emulators on its loopback) and one
per drone, joined to the computer's by a veth pair whose computer end plays the drone's Wi-Fi adapter
(each 192.168.10.2/24, as two Tellos' DHCP would each give), the drone's end 192.168.10.1. Nothing leaves
the namespaces. A third test measures what a strict reverse-path filter does to the second adapter, and
that preflight names it. Drone 1 is a Tello EDU (SDK 3.0: the downward camera), drone 2 a Tello on SDK 2.0
(forward camera); their batteries differ (BATTERY), so that a state datagram given to the wrong drone
would show in the other's recorded traffic. A datagram sent through the wrong interface reaches the other
drone: each drone's landing after the kill proves the guardian's socket for it left through its own.

The lab side (`lab_side`) runs inside the computer's namespace in a child process and writes what the
emulators saw as JSON; the tests judge it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.conftest import REPO, Bound, skip_or_fail_in_ci

BATTERY = {1: 92, 2: 61}
"""Each emulated drone's battery at the start (%): far enough apart that a drain of a few % during the
flight keeps them told apart."""
SDK = {1: "30", 2: "20"}
"""Each emulated drone's `sdk?` answer: drone 1 a Tello EDU on SDK 3.0, drone 2 a Tello on SDK 2.0."""
PURSUIT_S = 4.0
"""The flown pursuit of the normal flight (s; mode none)."""
KILL_AFTER_S = 1.0
"""The flight is killed this long after the pursuit started (s)."""
LAB_TIMEOUT_S = 260.0
"""Bound on the lab side's child process (s), above the sum of its own bounded waits (90 s for the
pursuit, 100 s for the flight's exit, 30 s for the landing and the guardian): killed after it, with
everything left in the namespaces."""


# ---- the namespaces ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Net:
    """The namespaces and interfaces of one test: the computer's namespace, and per drone its namespace
    and the computer's interface into it."""

    computer: str
    drones: dict[int, str]
    interfaces: dict[int, str]


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        skip_or_fail_in_ci(f"cannot set up network namespaces here: ip {' '.join(args)}: {r.stderr.strip()}")


def _kill_all_in(ns: str) -> None:
    """SIGKILL every process still in namespace `ns` (the lab side's children if it was cut short)."""
    r = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=10)
    for pid in r.stdout.split():
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)


@contextlib.contextmanager
def namespaces() -> Iterator[Net]:
    """The computer's namespace and one per drone, joined by veth pairs (module docstring); every process
    left in them is killed and they are deleted on exit."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        skip_or_fail_in_ci("needs root and iproute2's `ip netns` to create network namespaces")
    tag = uuid.uuid4().hex[:6]
    net = Net(f"fsc_{tag}", {i: f"fst{i}_{tag}" for i in (1, 2)}, {i: f"fsa{i}{tag}" for i in (1, 2)})
    made: list[str] = []
    try:
        for ns in (net.computer, *net.drones.values()):
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        for i, ns in net.drones.items():
            inside = f"fsd{tag}"  # the drone's end: the same name in each drone's namespace
            _ip("-n", net.computer, "link", "add", net.interfaces[i], "type", "veth", "peer", "name", inside,
                "netns", ns)  # fmt: skip
            _ip("-n", ns, "addr", "add", "192.168.10.1/24", "dev", inside)
            _ip("-n", ns, "link", "set", inside, "up")
            _ip("-n", net.computer, "addr", "add", "192.168.10.2/24", "dev", net.interfaces[i])
            _ip("-n", net.computer, "link", "set", net.interfaces[i], "up")
        yield net
    finally:
        for ns in made:
            _kill_all_in(ns)
        for ns in made:  # deleting a namespace deletes its veth ends (and so their peers)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


# ---- the lab side (inside the computer's namespace) -------------------------------------------------------
def _traffic_batteries(path: Path) -> list[int]:
    """The `bat` values of every state record in a drone's raw traffic file (drivers/tello/traffic.py)."""
    out = []
    if path.is_file():
        for line in path.read_text(errors="replace").splitlines()[1:]:
            with contextlib.suppress(ValueError, KeyError, TypeError):
                rec = json.loads(line)
                if rec.get("kind") == "state":
                    fields = dict(f.split(":", 1) for f in rec["text"].strip().split(";") if ":" in f)
                    out.append(int(fields["bat"]))
    return out


def _write_lab_file(lab: Any, path: Path) -> Path:
    """The shipped lab template with this lab's devices: the interfaces, the emulators' motion capture and
    robot, measured calibrations, the operator channel and certificates of `paper_experiment`."""
    from flightstack.comms.certs import create_mission_certs, participants
    from flightstack.config.rig import MISSION_CONFIGS

    rig = yaml.safe_load((MISSION_CONFIGS / "rigs" / "lab.yaml").read_text())
    written = yaml.safe_load(lab.mission_path.read_text())  # the lab's mission: its devices as they run
    certs = path.parent / "lab-certs"
    create_mission_certs("paper_experiment", participants([1, 2], None), certs)
    rig["rig"] = "adapter-per-tello"
    rig["drones"] = [
        {"id": d["id"], "camera": d["camera"]["calibration"], "rc_gains": d["rc_gains"]}
        for d in written["drones"]
    ]
    rig["bus"] = {**rig["bus"], "operator_port": written["bus"]["operator_port"], "certs": str(certs)}
    rig["hardware"] = written["hardware"]
    path.write_text(yaml.safe_dump(rig, sort_keys=False))
    return path


def lab_side(config_path: str) -> None:
    """In the computer's namespace: the emulated lab with each Tello in its own namespace, the lab file,
    `flightstack run` on it (killed KILL_AFTER_S into the pursuit when the config says so); writes what
    happened as JSON (`result`). Every wait is bounded; the flight is killed at the end if still running."""
    from flightstack.faults.rows_lab_process import guardian_pids
    from flightstack.sim_backend.emulated_lab import (
        EmulatedLab,
        TelloPlace,
        command_times,
        first,
        phase_times,
        rc_times,
    )
    from flightstack.sim_backend.emulators.tello.faults import TelloFaults

    cfg = json.loads(Path(config_path).read_text())
    work = Path(cfg["workdir"])
    kill = bool(cfg["kill"])
    places = {int(i): TelloPlace(ns, cfg["interfaces"][i]) for i, ns in cfg["drones"].items()}
    tello = {i: {"faults": TelloFaults(sdk_version=SDK[i], battery_pct=BATTERY[i])} for i in places}
    out: dict[str, Any] = {"drones": {}}
    with EmulatedLab(work / "lab", tello_netns=places, tello=tello) as lab:
        lab_file = _write_lab_file(lab, work / "lab.yaml")
        run_dir = work / "run"
        duration = 60.0 if kill else PURSUIT_S
        cmd = [sys.executable, "-m", "flightstack", "run", "paper_experiment", "--rig", str(lab_file),
               "--out", str(run_dir), "--yes", "--modes", "none", "--duration", f"{duration:g}",
               "--no-progress"]  # fmt: skip
        with open(work / "run.out", "wb") as so, open(work / "run.err", "wb") as se:
            proc = subprocess.Popen(cmd, stdout=so, stderr=se)
        t_kill, guardians = None, []
        try:
            t_pursuit = lab.wait_for_pursuit(90.0)
            out["pursuit_started"] = t_pursuit is not None
            if kill and t_pursuit is not None:
                guardians = guardian_pids(proc.pid)
                time.sleep(KILL_AFTER_S)
                t_kill = time.monotonic()
                proc.send_signal(signal.SIGKILL)
            out["exit"] = proc.wait(timeout=100.0)
            t_end = time.monotonic() + 20.0  # the guardian lands them; the Tello's own auto-land is 15 s
            while time.monotonic() < t_end and any(e.flying for e in lab.tellos.values()):
                time.sleep(0.05)
            for pid in guardians:  # it exits once every drone is down (give_up_s at the latest)
                while time.monotonic() < t_end + 10.0 and Path(f"/proc/{pid}").exists():
                    time.sleep(0.05)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10.0)
        out["guardians"] = guardians
        out["guardians_left"] = [pid for pid in guardians if Path(f"/proc/{pid}").exists()]
        for i, e in lab.tellos.items():
            after = -float("inf") if t_kill is None else t_kill
            t_land = first(command_times(e, "land", after=after))
            t_rc0 = first(rc_times(e, after=after, value=(0, 0, 0, 0)))
            t_down = first(phase_times(e, "landed", after=after))
            flying = first(phase_times(e, "flying"))
            out["drones"][str(i)] = {
                "phases": [p for _, p in list(e.phase_log)],
                "rc_moving": len(rc_times(e, after=flying or float("inf"), nonzero=True)),
                "flying_at_end": e.flying,
                "landed_by_timeout": e.landed_by_timeout,
                "rejected": list(e.rejected),
                "errors": list(e.errors),
                "land_s": None if t_land is None or t_kill is None else t_land - t_kill,
                "rc0_s": None if t_rc0 is None or t_kill is None else t_rc0 - t_kill,
                "down_s": None if t_down is None or t_kill is None else t_down - t_kill,
                "batteries": _traffic_batteries(run_dir / "devices" / f"tello-{i}_none.jsonl"),
            }
    out["stdout"] = (work / "run.out").read_text(errors="replace")
    err = (work / "run.err").read_text(errors="replace")
    out["stderr"] = err[-4000:]
    out["guardian_log"] = "\n".join(ln for ln in err.splitlines() if ln.split(" ", 2)[1:2] == ["guardian"])
    Path(cfg["result"]).write_text(json.dumps(out))


def fly(tmp_path: Path, kill: bool) -> dict[str, Any]:
    """The lab side in fresh namespaces; what it wrote (module docstring)."""
    with namespaces() as net:
        cfg = {
            "workdir": str(tmp_path),
            "kill": kill,
            "drones": {str(i): ns for i, ns in net.drones.items()},
            "interfaces": {str(i): name for i, name in net.interfaces.items()},
            "result": str(tmp_path / "result.json"),
        }
        (tmp_path / "cfg.json").write_text(json.dumps(cfg))
        code = "import sys; from tests.test_tello_interfaces import lab_side; lab_side(sys.argv[1])"
        env = dict(os.environ, PYTHONPATH=str(REPO))
        cmd = ["ip", "netns", "exec", net.computer, sys.executable, "-c", code, str(tmp_path / "cfg.json")]
        try:
            r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=LAB_TIMEOUT_S)
        except subprocess.TimeoutExpired as exc:
            pytest.fail(f"the lab side did not end within {LAB_TIMEOUT_S:g} s: {exc.stderr!r}"[-3000:])
        assert r.returncode == 0, r.stderr[-4000:]
        result: dict[str, Any] = json.loads((tmp_path / "result.json").read_text())
        result["interfaces"] = {str(i): name for i, name in net.interfaces.items()}
        return result


def rp_probe(interfaces: str) -> None:
    """In the computer's namespace: preflight's row of each interface (comma-separated names) for a drone at
    192.168.10.1, and how many datagrams arrive within 2 s on a socket bound to it at port 8890; prints
    JSON."""
    from flightstack.drivers.lab.preflight import check_interface
    from flightstack.drivers.netif import udp_socket

    names = interfaces.split(",")
    socks = {}
    for name in names:
        socks[name] = udp_socket(name)
        socks[name].bind(("", 8890))
        socks[name].setblocking(False)
    print("ready", flush=True)
    got = dict.fromkeys(names, 0)
    t_end = time.monotonic() + 2.0
    while time.monotonic() < t_end:
        for name, sock in socks.items():
            with contextlib.suppress(BlockingIOError):
                while sock.recv(64):
                    got[name] += 1
        time.sleep(0.01)
    rows = {name: check_interface("drone", name, "192.168.10.1") for name in names}
    print(
        json.dumps({n: {"status": r.status, "detail": r.detail, "received": got[n]} for n, r in rows.items()})
    )


def test_a_strict_reverse_path_filter_drops_one_adapters_drone_and_preflight_says_so() -> None:
    """Two adapters on one subnet: with rp_filter 1 the kernel drops what arrives on the one its route
    back does not leave through, and preflight FAILs that interface naming the fix; loose (2), both pass
    and both drones are heard."""
    import socket

    from flightstack.sim_backend.emulators.netns import in_netns

    with namespaces() as net:
        senders = {
            i: in_netns(ns, lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            for i, ns in net.drones.items()
        }
        seen = {}
        try:
            for rp in (1, 2):
                sysctl = [
                    "ip",
                    "netns",
                    "exec",
                    net.computer,
                    "sysctl",
                    "-qw",
                    f"net.ipv4.conf.all.rp_filter={rp}",
                ]
                subprocess.run(sysctl, check=True, timeout=10)
                code = "import sys; from tests.test_tello_interfaces import rp_probe; rp_probe(sys.argv[1])"
                names = ",".join(net.interfaces.values())
                cmd = ["ip", "netns", "exec", net.computer, sys.executable, "-c", code, names]
                env = dict(os.environ, PYTHONPATH=str(REPO))
                with subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, text=True) as probe:
                    assert probe.stdout is not None and probe.stdout.readline().strip() == "ready"
                    t_end = time.monotonic() + 10.0
                    while probe.poll() is None and time.monotonic() < t_end:
                        for sock in senders.values():
                            sock.sendto(b"state", ("192.168.10.2", 8890))
                        time.sleep(0.02)
                    out, _ = probe.communicate(timeout=10)
                seen[rp] = json.loads(out.strip().splitlines()[-1])
        finally:
            for sock in senders.values():
                sock.close()
    print(json.dumps(seen, indent=1))
    strict = sorted(seen[1].values(), key=lambda row: row["status"])
    assert [row["status"] for row in strict] == ["FAIL", "PASS"], seen
    dropped, heard = strict
    assert dropped["received"] == 0 and heard["received"] > 10, seen
    assert (
        "strict reverse-path filter (rp_filter 1)" in dropped["detail"] and "rp_filter=2" in dropped["detail"]
    )
    assert all(row["status"] == "PASS" and row["received"] > 10 for row in seen[2].values()), seen


def table(stdout: str) -> dict[tuple[str, str], tuple[str, str]]:
    """The preflight table in `stdout`: (device, check) -> (status, detail), cut at the header's columns."""
    lines = stdout.splitlines()
    head = next(k for k, line in enumerate(lines) if line.startswith("device "))
    cols = [lines[head].index(name) for name in ("check", "status", "detail")]
    rows = {}
    for line in lines[head + 2 :]:
        if line.startswith("preflight:"):
            break
        device, check, status = (line[a:b].strip() for a, b in zip([0, *cols[:2]], cols, strict=True))
        rows[(device, check)] = (status, line[cols[2] :])
    return rows


def test_one_run_flies_two_access_point_tellos_at_one_address_each_through_its_own_interface(
    tmp_path: Path,
) -> None:
    r = fly(tmp_path, kill=False)
    out = r["stdout"]
    print(out, r["stderr"], sep="\n")
    assert r["pursuit_started"] and r["exit"] == 0, r["stderr"]
    rows = table(out)
    assert [k for k, (status, _) in rows.items() if status == "FAIL"] == [], out
    assert rows[("computer", "interface binding")][0] == "PASS"
    for i in (1, 2):
        name = r["interfaces"][str(i)]
        dev = f"drone {i} (192.168.10.1 via {name})"
        assert rows[(dev, f"interface {name}")] == ("PASS", f"{name} up, 192.168.10.2/24, rp_filter off")
        assert rows[(dev, "firmware")][1].startswith(f"SDK {SDK[i][0]}.0"), rows[(dev, "firmware")]
        assert rows[(dev, "battery")][1].startswith(f"{BATTERY[i]} %"), rows[(dev, "battery")]
        d = r["drones"][str(i)]
        assert d["phases"][:5] == ["landed", "takeoff", "flying", "landing", "landed"], d["phases"]
        assert d["rc_moving"] >= 20 and not d["flying_at_end"] and not d["landed_by_timeout"], d
        assert not d["rejected"] and not d["errors"], d
        # its own state only: the other drone's battery never reached it, though both are 192.168.10.1
        assert d["batteries"] and all(BATTERY[i] - 5 <= b <= BATTERY[i] for b in d["batteries"]), d


def test_the_guardian_lands_each_drone_through_its_own_interface_when_the_flight_is_killed(
    tmp_path: Path, safety_bound: Bound
) -> None:
    from flightstack.faults.rows_lab_process import DOWN_S, KILL_HOVER_S, KILL_LAND_S

    r = fly(tmp_path, kill=True)
    print(r["stdout"][-3000:], r["stderr"], r["guardian_log"], sep="\n")
    assert r["pursuit_started"] and r["exit"] == -signal.SIGKILL, r["stderr"]
    assert len(r["guardians"]) == 1 and not r["guardians_left"], r
    assert "TAKEOVER" in r["guardian_log"] and "takeover complete" in r["guardian_log"], r["guardian_log"]
    for i in (1, 2):
        d = r["drones"][str(i)]
        print(f"drone {i}: rc 0 0 0 0 +{d['rc0_s']} s, land +{d['land_s']} s, down +{d['down_s']} s")
        assert d["land_s"] is not None and d["down_s"] is not None, d
        assert not d["flying_at_end"] and not d["landed_by_timeout"] and not d["rejected"], d
        # its telemetry, read on its own interface, showed it down
        assert f"192.168.10.1 via {r['interfaces'][str(i)]}: down" in r["guardian_log"], r["guardian_log"]
        via = f"drone {i} (via {r['interfaces'][str(i)]})"
        safety_bound(f"{via}: the guardian's rc 0 0 0 0 after the kill", 1e3 * d["rc0_s"], 1e3 * KILL_HOVER_S)
        safety_bound(f"{via}: the guardian's land after the kill", 1e3 * d["land_s"], 1e3 * KILL_LAND_S)
        safety_bound(f"{via}: down after the kill", 1e3 * d["down_s"], 1e3 * DOWN_S)
