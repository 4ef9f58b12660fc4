"""The rows of `flightstack faults` played on the bus with real Zenoh sessions on 127.0.0.1:
`flightstack abort` with one agent absent (`abort_agent_missing`) and senders whose clocks are ±10 min
off (`clock_skew`). FaultRows (mission file, work directory) -> FaultResult, listed in rows_lab.ROWS;
nothing flies, so all_safe and recording_complete hold unless the row crashed. Times: time.monotonic() s;
details in ms.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from flightstack.config.rig import resolved_document
from flightstack.faults.lab_flight import lab_result
from flightstack.faults.result import Checks, FaultResult
from flightstack.faults.rows_cli import run_cli
from flightstack.faults.rows_lab_cli import abort_args, acks_in, cli_abort
from flightstack.sim_backend.emulated_lab import LabUnavailableError, ms


# ---- abort_agent_missing -----------------------------------------------------------------------------------
def _zenoh_modules() -> Any:
    """flightstack.comms.zenoh_bus, or LabUnavailableError without eclipse-zenoh."""
    try:
        from flightstack.comms import zenoh_bus
    except ImportError as exc:  # pragma: no cover - zenoh is a core dependency
        raise LabUnavailableError(f"this row needs eclipse-zenoh: {exc}") from exc
    return zenoh_bus


def abort_agent_missing(mission_path: Path, workdir: Path) -> FaultResult:
    """`flightstack abort` (a child process) with agents 1 and 2 on the Zenoh bus and agent 3 absent."""
    wall0 = time.perf_counter()
    name = "abort_agent_missing"
    root = workdir / name
    root.mkdir(parents=True, exist_ok=True)
    zb = _zenoh_modules()
    from flightstack.comms.factory import free_loopback_endpoints, zenoh_bus_config
    from flightstack.config.mission import load_mission

    m = resolved_document("paper_sim")
    ids = [int(d["id"]) for d in m["drones"]]
    *present, absent = ids  # every agent but the last is on the bus
    endpoints = dict(zip(map(str, ids), free_loopback_endpoints(len(ids)), strict=True))
    m["name"] = "abort_agent_missing"
    m["bus"] = {"kind": "zenoh", "zenoh": {"endpoints": endpoints, "lease_ms": 500, "security": "plaintext"}}
    path = root / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    mission = load_mission(path)
    agents: dict[int, Any] = {}
    c = Checks()
    crashed = None
    details: dict[str, Any] = {}
    observed = ""
    try:
        for i in present:
            agents[i] = zb.ZenohBus(zenoh_bus_config(mission, mission.identity(i).agent, {i}))
        t0 = time.monotonic()
        r = run_cli("abort", str(path), "--timeout", "1")
        elapsed = time.monotonic() - t0
        acks = acks_in(r.stdout)
        crashed = f"`flightstack abort` traceback: {r.stderr[-800:]}" if "Traceback" in r.stderr else None
        c.check(r.returncode == 1, f"exit {r.returncode} with agent {absent} absent")
        c.check(
            f"agents [{absent}] did not acknowledge" in r.stderr,
            f"stderr does not name agent {absent}: {r.stderr[-300:]}",
        )
        c.check(sorted(acks) == present, f"acknowledged by {sorted(acks)}")
        c.check(elapsed < 20.0, f"`flightstack abort --timeout 1` took {elapsed:.1f} s")
        agents[absent] = zb.ZenohBus(zenoh_bus_config(mission, mission.identity(absent).agent, {absent}))
        code2, out2, _err2 = cli_abort(abort_args(path, 5.0))
        acks2 = acks_in(out2)
        c.check(code2 == 0 and sorted(acks2) == ids, f"with agent {absent} back: exit {code2}, acks {acks2}")
        details = {
            "exit_code": r.returncode,
            "ack_ms": {str(i): v for i, v in acks.items()},
            "command_wall_ms": ms(elapsed),
            "control_exit_code": code2,
            "control_ack_ms": {str(i): v for i, v in acks2.items()},
        }
        named = next((ln for ln in r.stderr.splitlines() if "did not acknowledge" in ln), "")
        observed = (
            f"agent {absent} absent: exit {r.returncode} in {elapsed:.2f} s, acks (ms) {acks}, stderr: "
            f"{named.strip()!r}; agent {absent} back: exit {code2}, acks (ms) {acks2}"
        )
    except Exception as exc:
        crashed = f"{type(exc).__name__}: {exc}"
    finally:
        for bus in agents.values():
            bus.close()
    expected = (
        "`flightstack abort --timeout 1` exits 1 naming agent 3 (agents 1 and 2 acknowledge); with agent 3 "
        "on the bus it exits 0 with every ack"
    )
    return lab_result(name, expected, observed, wall0, c, [], [], details, crashed)


# ---- clock_skew --------------------------------------------------------------------------------------------
SKEWS = {0: 0.0, 1: +600.0, 2: -600.0}
"""Sender id -> its clock minus the receiver's (s): the same, 10 min ahead, 10 min behind."""
PERIOD_S = 0.02
STALE_AFTER_S = 0.3


def clock_skew(mission_path: Path, workdir: Path) -> FaultResult:
    """Three Zenoh senders on loopback stamping with time.monotonic() + (0, +600, -600) s publish at 50 Hz,
    then stop together; a receiver with the real-time time base (and, as the control, one comparing
    stamps)."""
    wall0 = time.perf_counter()
    name = "clock_skew"
    zb = _zenoh_modules()
    from flightstack.comms.factory import free_loopback_endpoints
    from flightstack.comms.messages import PredictionMessage

    mission = "clock_skew_row"
    c = Checks()
    crashed = None
    details: dict[str, Any] = {}
    observed = ""

    def msg(sender: int, seq: int, stamp: float) -> Any:
        one = np.ones(4)
        return PredictionMessage(mission, sender, seq, stamp, True, one * sender, one, one, one)

    eps = free_loopback_endpoints(2 + len(SKEWS))
    buses: list[Any] = []
    stop = threading.Event()
    thread: threading.Thread | None = None
    try:
        for k, base in enumerate(("receiver", "stamps")):
            others = [e for j, e in enumerate(eps) if j != k]
            cfg = zb.ZenohBusConfig(mission, set(), set(SKEWS), [eps[k]], others, time_base=base)
            buses.append(zb.ZenohBus(cfg))
        senders = {}
        for k, i in enumerate(SKEWS, start=2):
            others = [e for j, e in enumerate(eps) if j != k]
            senders[i] = zb.ZenohBus(zb.ZenohBusConfig(mission, {i}, set(SKEWS), [eps[k]], others))
            buses.append(senders[i])
        rx, rx_stamps = buses[0], buses[1]
        for b in buses:
            c.check(b.wait_alive(set(SKEWS), 20.0) == set(), "the Zenoh mesh did not come up")
        last_sent = [0.0]

        def publish_loop() -> None:
            seq, t_next = 0, time.monotonic()
            deadline = t_next + 10.0  # bounded whatever happens
            while not stop.is_set() and time.monotonic() < deadline:
                seq += 1
                for i, skew in SKEWS.items():
                    senders[i].publish(msg(i, seq, time.monotonic() + skew))
                last_sent[0] = time.monotonic()
                t_next += PERIOD_S
                time.sleep(max(0.0, t_next - time.monotonic()))

        thread = threading.Thread(target=publish_loop, name="clock-skew-senders", daemon=True)
        thread.start()
        c.check(rx.wait_for(dict.fromkeys(SKEWS, 1), 10.0) == set(), "not every sender heard")
        time.sleep(0.5)  # the join window (20 messages)
        checks, unfused = 0, {i: 0 for i in SKEWS}
        stamps_fused_behind = 0
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            now = time.monotonic()
            for i in SKEWS:
                unfused[i] += rx.latest(i, now, STALE_AFTER_S) is None
            stamps_fused_behind += rx_stamps.latest(2, now, STALE_AFTER_S) is not None
            checks += 1
            time.sleep(0.005)
        stop.set()
        thread.join(2.0)
        t_stop = last_sent[0]
        stale_at: dict[int, float] = {}
        while len(stale_at) < len(SKEWS) and time.monotonic() < t_stop + 3.0:
            now = time.monotonic()
            for i in SKEWS:
                if i not in stale_at and rx.latest(i, now, STALE_AFTER_S) is None:
                    stale_at[i] = now - t_stop
            time.sleep(0.001)
        # a stamp from the future of the receiver's clock is refused ("stamp ahead"): otherwise a sender
        # 10 min ahead would be fused forever
        ahead_refused = rx_stamps.latest(1, time.monotonic(), STALE_AFTER_S) is None
        ahead_refused = ahead_refused and rx_stamps.dropped.get("stamp ahead", 0) > 0
        c.check(checks > 50 and not any(unfused.values()), f"not fused on {unfused} of {checks} checks")
        c.check(set(stale_at) == set(SKEWS), f"stale: {sorted(stale_at)} of {sorted(SKEWS)}")
        if set(stale_at) == set(SKEWS):
            spread = max(stale_at.values()) - min(stale_at.values())
            c.check(spread < 0.03, f"stale times differ by {spread:.3f} s across skews (limit 0.03 s)")
            c.check(
                all(STALE_AFTER_S - 0.03 < s < STALE_AFTER_S + 0.1 for s in stale_at.values()),
                f"stale after {stale_at} s (stale_after {STALE_AFTER_S} s)",
            )
        c.check(rx.dropped.get("stamp ahead", 0) == 0, f"dropped {dict(rx.dropped)}")
        # the control: comparing stamps (the "stamps" time base) never fuses the sender behind, and
        # refuses the one ahead: both fail closed
        c.check(stamps_fused_behind == 0 and ahead_refused, "the stamp-comparing control did not fail closed")
        offsets = {SKEWS[i]: rx.freshness.offset(i) for i in SKEWS}
        details = {
            "stale_after_last_send_ms": {f"{SKEWS[i]:+g} s": ms(v) for i, v in stale_at.items()},
            "fused_checks": checks,
            "unfused": {f"{SKEWS[i]:+g} s": n for i, n in unfused.items()},
            "learned_offset_s": {f"{k:+g} s": None if v is None else round(v, 4) for k, v in offsets.items()},
            "control_behind_fused": stamps_fused_behind,
            "control_ahead_refused": ahead_refused,
        }
        observed = (
            f"fused on {checks - max(unfused.values())}/{checks} checks for every skew; stale after the last "
            f"send (ms) {details['stale_after_last_send_ms']}; offsets {details['learned_offset_s']}; stamp "
            f"comparison (control): behind fused {stamps_fused_behind}x, ahead refused "
            f"{ahead_refused}"
        )
    except Exception as exc:
        crashed = f"{type(exc).__name__}: {exc}"
    finally:
        stop.set()
        if thread is not None:
            thread.join(2.0)
        for b in buses:
            b.close()
    expected = (
        "senders ±10 min off are fused on every check and go stale within 30 ms of the same-clock sender, "
        f"{STALE_AFTER_S:g} s after their last message (−0.03/+0.1 s); nothing dropped as 'stamp ahead'; the "
        "stamp-comparing control never fuses the sender behind and never sees the one ahead go stale"
    )
    return lab_result(name, expected, observed, wall0, c, [], [], details, crashed)
