"""The Zenoh links between agent processes through a lossy network: one TcpImpairProxy in front of each
participant's listening endpoint, the others connecting to the proxy (flightstack.netem's `bus` link).

    with impaired_bus(mission.bus.zenoh.endpoints, "crowded", seed=mission.seed) as proxies:
        endpoints = proxies.view("1")   # what participant 1 uses: its own endpoint, the others' proxies
        ...                             # start each participant with its own view of the endpoints

Every participant listens on its own endpoint and connects to every other one's (full mesh,
comms/factory.py), so each pair's link passes exactly one proxy. With mutual TLS (`tls/` endpoints) the
proxy forwards the encrypted bytes: the certificates and the access control are those of the direct link
(host names are not verified, comms/certs.py). Loopback only (TcpImpairProxy). A proxy that dies closes
its connections: the participants see their link close, as when a peer's process ends (their lease,
start and lock-step timeouts bound every wait).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager

from flightstack.netem import NetworkProfile, profile
from flightstack.sim_backend.emulators.tcp_proxy import TcpImpairProxy


def split_endpoint(endpoint: str) -> tuple[str, str, int]:
    """(protocol, host, port) of "tcp/127.0.0.1:7447" (or tls/); ValueError otherwise."""
    proto, sep, rest = endpoint.partition("/")
    host, colon, port = rest.rpartition(":")
    if not sep or not colon or proto not in ("tcp", "tls") or not port.isdigit():
        raise ValueError(f"{endpoint!r} is not an endpoint like tcp/127.0.0.1:7447")
    return proto, host, int(port)


class BusProxies:
    """One started TcpImpairProxy per participant of `endpoints` (participant -> its listening
    endpoint), each seeded by (seed, "bus-<participant>") with the network profile's `bus` link."""

    def __init__(self, endpoints: Mapping[str, str], network: NetworkProfile | str, seed: int = 0) -> None:
        self.network = profile(network) if isinstance(network, str) else network
        self.endpoints = dict(endpoints)
        self.proxies: dict[str, TcpImpairProxy] = {}
        try:
            for name, ep in self.endpoints.items():
                _, host, port = split_endpoint(ep)
                proxy = TcpImpairProxy((host, port), self.network.link("bus"), seed, f"bus-{name}")
                self.proxies[name] = proxy.start()
        except BaseException:
            self.close()
            raise

    def endpoint(self, participant: str) -> str:
        """Where the others connect to reach `participant`: its proxy's endpoint (same protocol)."""
        proto, _, _ = split_endpoint(self.endpoints[participant])
        host, port = self.proxies[participant].address
        return f"{proto}/{host}:{port}"

    def view(self, participant: str | None = None) -> dict[str, str]:
        """The endpoints as `participant` uses them: its own listening endpoint, every other
        participant's proxy (None: a tool that only connects, e.g. `flightstack status`)."""
        return {
            name: ep if name == participant else self.endpoint(name) for name, ep in self.endpoints.items()
        }

    def counts(self) -> dict[str, dict[str, int]]:
        """Per participant, what its proxy did (TcpImpairProxy.counts)."""
        return {name: p.counts() for name, p in self.proxies.items()}

    def close(self) -> None:
        """Close every proxy (each bounded by about 1 s); idempotent."""
        for p in self.proxies.values():
            p.close()


@contextmanager
def impaired_bus(
    endpoints: Mapping[str, str], network: NetworkProfile | str, seed: int = 0
) -> Iterator[BusProxies]:
    """BusProxies for `endpoints` under `network` (a flightstack.netem profile or its name), closed when
    the block ends."""
    proxies = BusProxies(endpoints, network, seed)
    try:
        yield proxies
    finally:
        proxies.close()


__all__ = ["BusProxies", "impaired_bus", "split_endpoint"]
