"""Fly the Tello driver through each real-firmware scenario of the emulator and report what happened.

    python3 benchmarks/tello_scenarios.py            # all scenarios, ~1 min, loopback only

Per scenario: whether takeoff() and land() succeeded, the time each took to be confirmed from telemetry,
the replies the driver discarded or did not trust, the commands the drone rejected or ignored in its
phase (`emu.refused`, should be 0), and whether the driver's phase agreed with the drone's at the end.
tests/test_tello_driver.py asserts the same properties.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flightstack.drivers.tello.config import TelloConfig
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.rc import RcGains
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator

AS_DRIVER = {"landed": "ground", "takeoff": "taking_off", "flying": "flying", "landing": "landing"}
SCENARIOS: dict[str, dict[str, object]] = {
    "baseline": {},
    "duplicate late replies (0.4 s)": {"duplicate_reply_after_s": 0.4},
    "lost ok to takeoff": {"lost_replies": {"takeoff"}},
    "lost ok to land": {"lost_replies": {"land"}},
    "slow takeoff (11.5 s)": {"takeoff_s": 11.5},
    "firmware answers rc": {"rc_replies": True},
    "SDK 2.0 firmware": {"sdk_version": "20"},
}


def run(name: str, faults: dict[str, object]) -> dict[str, object]:
    emu = TelloEmulator("127.0.0.3", state_port=free_udp_port(), video_port=free_udp_port(), takeoff_s=3.9)
    emu.land_s = 1.7  # a real Tello: ok ~3.9 s after takeoff, ~1.7 s landing (Tello-Python #88)
    for k, v in faults.items():
        setattr(emu.faults, k, v)
    emu.start()
    cfg = TelloConfig(
        host=emu.ip,
        control_port=emu.address[1],
        video_port=emu.video_port,
        state_port=emu.state_port,
        rc_gains=RcGains(0.01, 0.01, 0.0175),
    )
    d = TelloDriver(cfg)
    out: dict[str, object] = {"scenario": name}
    try:
        d.connect()
        t0 = time.monotonic()
        d.takeoff()
        out["takeoff_s"] = round(time.monotonic() - t0, 2)
        out["airborne_at_return"] = emu.phase == "flying"
        for k in range(60):  # 3 s of 20 Hz rc
            d.send_body_velocity(np.array([0.2 * np.sin(k / 5), 0.0, 0.0, 0.0]))
            time.sleep(0.05)
        t0 = time.monotonic()
        d.land()
        out["land_s"] = round(time.monotonic() - t0, 2)
    except Exception as exc:
        out["error"] = str(exc)
    finally:
        time.sleep(0.5)
        assert d.link.chan is not None
        out["replies_discarded"] = d.link.chan.counts["reply_discarded"]
        out["ok_not_trusted"] = d.counts["reply_not_trusted"]
        out["refused_by_drone"] = len(emu.refused)
        out["phase_agrees"] = d.phase.value == AS_DRIVER[emu.phase]
        out["auto_landed"] = emu.landed_by_timeout
        d.close()
        emu.close()
    return out


def main() -> int:
    rows = [run(n, f) for n, f in SCENARIOS.items()]
    keys = list(dict.fromkeys(k for r in rows for k in r))
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(str(r.get(k, "")) for k in keys))
    bad = [r for r in rows if r.get("refused_by_drone") or not r.get("phase_agrees") or "error" in r]
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
