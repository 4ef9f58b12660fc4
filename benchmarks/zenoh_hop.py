"""Hop latency of one PredictionMessage: Zenoh between two processes on loopback vs the in-process bus.

    python benchmarks/zenoh_hop.py [N]        # prints p50/p99 in microseconds (default N = 2000)

Zenoh: ping-pong between this process (ZenohBus hosting agent 0) and an echo subprocess (ZenohBus hosting
agent 1, `--echo`), full mesh on two free 127.0.0.1 ports, multicast scouting off. Each round trip is
publish (encode) -> Zenoh -> decode -> wait_for wakes -> publish reply -> ... ; hop = round trip / 2, so
it includes encode + decode + thread wake-ups on both sides, i.e. what an agent sees. In-process: one
publish (encode + decode) + one latest() on InProcBus. 50 warm-up rounds are not counted.

`measure_zenoh_hop(n)` and `measure_inproc_hop(n)` return {"p50_us", "p99_us", "mean_us", "max_us", "n"}.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from flightstack.comms.bus import InProcBus  # noqa: E402
from flightstack.comms.factory import free_loopback_endpoints  # noqa: E402
from flightstack.comms.messages import PredictionMessage  # noqa: E402
from flightstack.comms.zenoh_bus import ZenohBus, ZenohBusConfig  # noqa: E402

MISSION = "hop_bench"
WARMUP = 50
TIMEOUT_S = 10.0  # per round trip; the echo peer also gives up after this long without a ping


def _msg(sender: int, seq: int) -> PredictionMessage:
    rng = np.random.default_rng(seq)
    return PredictionMessage(
        MISSION,
        sender,
        seq,
        seq * 0.05,
        True,
        rng.normal(size=4),
        rng.normal(size=4),
        rng.uniform(0.1, 1.0, size=4),
        np.ones(4),
    )


def _stats(hops_s: list[float]) -> dict[str, float]:
    us = np.asarray(hops_s) * 1e6
    return {
        "p50_us": float(np.percentile(us, 50)),
        "p99_us": float(np.percentile(us, 99)),
        "mean_us": float(us.mean()),
        "max_us": float(us.max()),
        "n": float(len(us)),
    }


def _echo(listen: str, connect: str, rounds: int) -> int:
    """Subprocess side: answer ping seq k of agent 0 with pong seq k of agent 1."""
    cfg = ZenohBusConfig(MISSION, {1}, {0, 1}, [listen], [connect])
    with ZenohBus(cfg) as bus:
        for seq in range(1, rounds + 1):
            if bus.wait_for({0: seq}, TIMEOUT_S):
                return 1
            bus.publish(_msg(1, seq))
        time.sleep(0.2)  # let the last pong leave before closing
    return 0


def measure_zenoh_hop(n: int = 2000) -> dict[str, float]:
    """p50/p99 one-hop latency (µs) of ZenohBus between two processes on loopback (round trip / 2)."""
    ep_here, ep_echo = free_loopback_endpoints(2)
    rounds = n + WARMUP
    pings = [_msg(0, seq) for seq in range(1, rounds + 1)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    bus = ZenohBus(ZenohBusConfig(MISSION, {0}, {0, 1}, [ep_here], [ep_echo]))
    proc = subprocess.Popen(
        [sys.executable, str(Path(__file__).resolve()), "--echo", ep_echo, ep_here, str(rounds)],
        cwd=REPO,
        env=env,
    )
    try:
        if bus.wait_alive({1}, 30.0):
            raise RuntimeError("echo peer did not come up")
        hops: list[float] = []
        for k, msg in enumerate(pings):
            t0 = time.perf_counter()
            bus.publish(msg)
            if bus.wait_for({1: msg.seq}, TIMEOUT_S):
                raise RuntimeError(f"no pong for seq {msg.seq}")
            if k >= WARMUP:
                hops.append((time.perf_counter() - t0) / 2)
        return _stats(hops)
    finally:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        bus.close()


def measure_inproc_hop(n: int = 2000) -> dict[str, float]:
    """p50/p99 latency (µs) of publish + latest on InProcBus (encode + decode, same message)."""
    bus = InProcBus(MISSION, {0, 1})
    msgs = [_msg(0, seq) for seq in range(1, n + WARMUP + 1)]
    hops: list[float] = []
    for k, msg in enumerate(msgs):
        t0 = time.perf_counter()
        bus.publish(msg)
        got = bus.latest(0, msg.stamp, 1.0)
        dt = time.perf_counter() - t0
        assert got is not None and got.seq == msg.seq
        if k >= WARMUP:
            hops.append(dt)
    return _stats(hops)


def main(argv: list[str]) -> int:
    if argv[:1] == ["--echo"]:
        return _echo(argv[1], argv[2], int(argv[3]))
    n = int(argv[0]) if argv else 2000
    runs = (("zenoh (2 processes, loopback)", measure_zenoh_hop), ("in-process", measure_inproc_hop))
    for name, fn in runs:
        r = fn(n)
        print(f"{name:32s} hop p50 {r['p50_us']:8.1f} µs   p99 {r['p99_us']:8.1f} µs   (n={int(r['n'])})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
