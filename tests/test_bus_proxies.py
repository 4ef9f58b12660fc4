"""The Zenoh links between agent processes through a lossy network (sim_backend/emulators/bus_proxies.py):
each participant's endpoint behind a TcpImpairProxy, the others connecting to the proxy, as the
multi-process harness (flightstack/faults/rows_processes.py, `ServedRun(network=...)`) runs them.
Free loopback ports; every bus and proxy is closed in `finally`."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.comms.factory import zenoh_bus_config
from flightstack.comms.messages import PredictionMessage
from flightstack.config.mission import load_mission
from flightstack.faults.rows_processes import mission_view, served_mission
from flightstack.netem import PROFILES
from flightstack.sim_backend.emulators.bus_proxies import impaired_bus, split_endpoint
from tests.conftest import eventually

pytestmark = pytest.mark.system
zenoh_bus = pytest.importorskip("flightstack.comms.zenoh_bus")


def _msg(mission: str, seq: int) -> PredictionMessage:
    z = np.zeros(4)
    return PredictionMessage(mission, 1, seq, time.monotonic(), True, z, z, np.ones(4), np.ones(4))


def _left(bus, sender: int) -> bool:
    return any(e.kind == "left" and e.drone == sender for e in bus.presence_events)


def _arrival(bus, seq: int, timeout_s: float = 5.0) -> float:
    """time.monotonic() when drone 1's message `seq` is the newest the bus holds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = bus.latest(1, time.monotonic(), 60.0)
        if m is not None and m.seq >= seq:
            return time.monotonic()
        time.sleep(0.0002)
    raise AssertionError(f"message {seq} never arrived")


def _first_arrival(sender, receiver, timeout_s: float) -> int:
    """Publish drone 1's messages 1, 2, ... every 50 ms until `receiver` holds one; returns the last seq
    published."""
    deadline = time.monotonic() + timeout_s
    seq = 0
    while time.monotonic() < deadline:
        seq += 1
        sender.publish(_msg("bus_proxy", seq))
        t_next = time.monotonic() + 0.05
        while time.monotonic() < t_next:
            if receiver.latest(1, time.monotonic(), 60.0) is not None:
                return seq
            time.sleep(0.001)
    raise AssertionError(f"none of {seq} warm-up messages arrived in {timeout_s:.0f} s")


def test_a_prediction_stream_through_the_crowded_bus_is_late_by_its_latency_and_complete(
    tmp_path: Path,
) -> None:
    """Agents 1 and 2 of the served mission, each reaching the other through its proxy under `crowded`
    (bus: 2 ms + exponential jitter of mean 5 ms): every message is at least 2 ms late, on average at
    least 2 + 5/2 ms (more than 4 standard errors below the expected 7 ms), and none of a 200 Hz stream
    is lost; when the proxies die, each agent sees the other leave (no wait hangs on them)."""
    link = PROFILES["crowded"].link("bus")
    path = served_mission(tmp_path, duration_s=5.0, name="bus_proxy")
    endpoints = yaml.safe_load(path.read_text())["bus"]["zenoh"]["endpoints"]
    buses = []
    with impaired_bus(endpoints, "crowded", seed=0) as proxies:
        try:
            assert proxies.view("1")["1"] == endpoints["1"] and proxies.view("1")["2"] != endpoints["2"]
            for i in (1, 2):
                m = load_mission(mission_view(path, proxies, str(i)))
                buses.append(zenoh_bus.ZenohBus(zenoh_bus_config(m, str(i), {i})))
            a, b = buses
            assert b.wait_alive({1, 2}, 20.0) == set(), "the agents did not meet through the proxies"
            assert a.wait_alive({1, 2}, 20.0) == set(), "the agents did not meet through the proxies"
            # b's token reaching a does not mean a's route to b's subscriber exists yet: a message
            # published before it is dropped at the publisher (seen on a loaded CI machine: "message 1
            # never arrived"). Warm up until one arrives; the measured stream starts after it.
            first = _first_arrival(a, b, 20.0)
            delays = []
            for seq in range(first + 1, first + 41):
                msg = _msg("bus_proxy", seq)
                a.publish(msg)
                delays.append(_arrival(b, seq) - msg.stamp)
                time.sleep(0.01)
            before = b.delivered
            for seq in range(first + 41, first + 241):  # a stream at 200 Hz: in order, nothing lost
                a.publish(_msg("bus_proxy", seq))
                time.sleep(0.005)
            _arrival(b, first + 240)
            streamed = b.delivered - before
            dropped = dict(b.dropped)
            counts = proxies.counts()
            t_dead = time.monotonic()  # the proxies die: each agent sees the other leave, nothing hangs
            proxies.close()
            assert eventually(lambda: _left(b, 1) and _left(a, 2), 5.0), "a dead proxy went unnoticed"
            left_after = time.monotonic() - t_dead
        finally:
            for bus in buses:
                bus.close()
    mean = statistics.fmean(delays)
    print(
        f"crowded bus through the proxy: delay min {1e3 * min(delays):.1f} ms, median "
        f"{1e3 * statistics.median(delays):.1f} ms, mean {1e3 * mean:.1f} ms (model: "
        f"{1e3 * link.latency_s:.0f} ms + mean {1e3 * link.jitter_s:.0f} ms); stream {streamed}/200 "
        f"delivered, dropped {dropped}; {counts}; proxies closed: the other agent left after "
        f"{1e3 * left_after:.0f} ms"
    )
    assert min(delays) >= link.latency_s, delays
    assert link.latency_s + link.jitter_s / 2 <= mean <= link.latency_s + link.jitter_s + 0.030, delays
    assert streamed == 200 and not dropped
    assert sum(c.get("chunks", 0) for c in counts.values()) > 0


def test_the_served_simulation_flies_through_crowded_proxies(tmp_path: Path) -> None:
    """`flightstack world` + three agents, each process with its own view of the endpoints (the others'
    proxies): every process ends by itself, every drone lands, every agent flew every tick and lost no
    message, and every pair's link passed a proxy."""
    from flightstack.faults.rows_processes import ServedRun

    mission = served_mission(tmp_path, duration_s=1.5)
    t0 = time.monotonic()
    with ServedRun(mission, tmp_path, network="crowded") as run:
        codes, world = run.wait()
        out = run.world_lines.rest()
        assert run.proxies is not None
        counts = run.proxies.counts()
    wall = time.monotonic() - t0
    print(f"served run through crowded proxies: {wall:.1f} s wall; {out.splitlines()[-1]}")
    assert codes == {1: 0, 2: 0, 3: 0} and world == 0, out
    assert "1: landed, 2: landed, 3: landed; dropped none" in out, out
    assert {name for name, c in counts.items() if c.get("chunks", 0) > 0} == {"1", "2", "3", "world"}
    for i in (1, 2, 3):
        assert (tmp_path / f"mission_{i}.yaml").is_file()
        metrics = json.loads((tmp_path / f"agent{i}" / "metrics.json").read_text())
        assert metrics["modes"]["dgp"]["ticks"] == 150 and not metrics["modes"]["dgp"]["bus_dropped"]


def test_split_endpoint() -> None:
    assert split_endpoint("tls/127.0.0.1:7447") == ("tls", "127.0.0.1", 7447)
    for bad in ("127.0.0.1:7447", "udp/127.0.0.1:1", "tcp/127.0.0.1"):
        with pytest.raises(ValueError):
            split_endpoint(bad)
