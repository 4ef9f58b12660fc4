"""Access-point topology on one host: two drones with the SAME address and default ports, one per network
namespace, each flown by its own process at the same time (docs/real-lab.md).

In the lab every access-point Tello is 192.168.10.1 and talks to UDP 8889/8890/11111 of its own computer;
two such set-ups on one host only work if each lives in its own network namespace. Each namespace here
gets only its loopback; the emulated drone is 127.0.0.2 inside it with the real default ports. No
traffic leaves a namespace. Needs root and `ip netns`; skipped with the reason otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def child() -> None:
    """Inside one namespace: an emulated Tello on the default ports and a driver flying it; prints JSON."""
    import numpy as np

    from flightstack.drivers.tello.config import TelloConfig
    from flightstack.drivers.tello.driver import TelloDriver
    from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
    from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator

    emu = TelloEmulator(
        "127.0.0.2",
        port=8889,
        state_port=8890,
        video_port=11111,
        takeoff_s=FAST_TAKEOFF_S,  # about the ports
    ).start()
    d = TelloDriver(TelloConfig(host="127.0.0.2", connect_timeout_s=3.0))
    out: dict[str, object] = {}
    try:
        d.connect()
        d.takeoff()
        out["airborne_at_return"] = emu.phase == "flying"
        for _ in range(20):
            d.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
            time.sleep(0.05)
        d.land()
        out.update(
            landed=emu.phase == "landed",
            phase=d.phase.value,
            rc_received=len(emu.rc_history),
            refused=len(emu.refused),
            sdk=d.sdk_version,
        )
    finally:
        d.close()
        emu.close()
    print(json.dumps(out), flush=True)


def _netns_or_skip() -> list[str]:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2's `ip netns` to create network namespaces")
    names = [f"fs_ap_{uuid.uuid4().hex[:6]}" for _ in range(2)]
    made = []
    for ns in names:
        r = subprocess.run(["ip", "netns", "add", ns], capture_output=True, text=True, timeout=10)
        if r.returncode != 0:
            for m in made:
                subprocess.run(["ip", "netns", "del", m], capture_output=True, timeout=10)
            pytest.skip(f"cannot create a network namespace here: {r.stderr.strip()}")
        made.append(ns)
        subprocess.run(["ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up"], check=True, timeout=10)
    return names


def test_two_access_point_drones_with_one_address_fly_at_once_from_their_own_namespaces() -> None:
    names = _netns_or_skip()
    try:
        code = "from tests.test_tello_access_point import child; child()"
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        procs = [
            subprocess.Popen(
                ["ip", "netns", "exec", ns, sys.executable, "-c", code],
                cwd=ROOT,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for ns in names
        ]
        results = []
        for p in procs:
            try:
                out, err = p.communicate(timeout=90)
            except subprocess.TimeoutExpired:
                p.kill()
                out, err = p.communicate()
            assert p.returncode == 0, err[-2000:]
            results.append(json.loads(out.strip().splitlines()[-1]))
        for r in results:
            assert r["airborne_at_return"] and r["landed"] and r["phase"] == "ground", r
            assert r["rc_received"] >= 19 and r["refused"] == 0 and r["sdk"] == "3.0", r
    finally:
        for ns in names:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
