"""The mission's `bus:` section (DESIGN §6): in-process or Zenoh, endpoints, transport security."""

from __future__ import annotations

import re
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from flightstack.config.types import Strict as _Strict

_LOOPBACK_HOST = re.compile(r"^(127\.\d{1,3}\.\d{1,3}\.\d{1,3}|localhost|\[::1\])$")
_ENDPOINT = re.compile(r"^(tcp|tls)/(\[[^\]\s]+\]|[^\s:/\[\]]+):(\d{1,5})$")
SECURITY_MODES = ("mtls", "plaintext")


def endpoint_host(endpoint: str) -> str:
    """The host part of `proto/host:port` ("" when it is not such an endpoint)."""
    m = _ENDPOINT.match(endpoint)
    return m.group(2) if m else ""


class ZenohSpec(_Strict):
    """The mission's Zenoh network (flightstack/comms/zenoh_bus.py), peer mode, full mesh.

    `endpoints`: participant → the endpoint it listens on; every participant connects to all the others.
    Participants: a drone id (`flightstack agent --id N`), `agents` (all agents in one process:
    `flightstack sim`/`fly` with bus kind zenoh), `world` (`flightstack world`, the simulated world served
    to agent processes). Operator tools (`abort`, `status`) and `guard` only connect.
    `lease_ms`: a hung peer is declared gone after this (a killed one at once, its TCP links close).
    `lockstep_timeout_s`: on a simulated clock, how long phase 2 waits for a neighbour's message of the
    same tick. `start_timeout_s`: how long every participant waits for the others to appear.

    Security (docs/security.md). `security: mtls` (the default): every endpoint is
    `tls/host:port`, every link is mutual TLS with the certificates `flightstack certs` made for this
    mission (directory `bus.certs`; each computer needs `ca.pem` and its own participant's pair), and
    Zenoh's access control, generated from the mission's participants (flightstack/comms/acl.py), lets
    each participant publish only its own keys. The keys of `endpoints` say which participants the
    mission has: `agents` (whose certificate may publish every drone's keys) and `world` get a
    certificate and a grant only when named here (certs.participants). `security: plaintext`:
    `tcp/` endpoints on loopback (127.0.0.0/8, localhost, [::1]) only, for simulations on one computer;
    refused on real hardware. Listening on every interface (0.0.0.0, [::]) is refused unless
    `allow_all_interfaces: true`. There is no raw `tls` or `access_control` section: both are generated."""

    endpoints: dict[str, str] = Field(min_length=1, max_length=1024)
    security: Literal["mtls", "plaintext"] = "mtls"
    allow_all_interfaces: bool = False
    lease_ms: int = Field(default=500, ge=100, le=60000)
    lockstep_timeout_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = 2.0
    start_timeout_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = 15.0
    key_prefix: str = Field(default="flightstack", max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")

    @model_validator(mode="before")
    @classmethod
    def _no_raw_sections(cls, data: object) -> object:
        if isinstance(data, dict):
            for key in ("tls", "access_control"):
                if key in data:
                    raise ValueError(
                        f"{key}: no longer written by hand; `security: mtls` uses the certificates"
                        " of `flightstack certs` and generates the access control from the participants"
                    )
        return data

    @field_validator("endpoints")
    @classmethod
    def _endpoints(cls, v: dict[str, str]) -> dict[str, str]:
        for name, ep in v.items():
            if not (name in ("agents", "world") or (name.isdigit() and len(name) <= 5)):
                raise ValueError(f"{name}: participant must be a drone id, 'agents' or 'world'")
            m = _ENDPOINT.match(ep)
            if not m or not 1 <= int(m.group(3)) <= 65535:
                raise ValueError(f"{name}: {ep!r} is not an endpoint like tls/192.168.1.20:7447")
        if len(set(v.values())) != len(v):
            raise ValueError("two participants listen on the same endpoint")
        return v

    @model_validator(mode="after")
    def _security(self) -> ZenohSpec:
        proto = "tls" if self.security == "mtls" else "tcp"
        for name, ep in self.endpoints.items():
            if not ep.startswith(f"{proto}/"):
                raise ValueError(
                    f"endpoints.{name}: {ep!r} must be {proto}/ with security {self.security!r}"
                    + (" (a tcp/ link beside TLS would run in plaintext)" if proto == "tls" else "")
                )
            host = endpoint_host(ep)
            if self.security == "plaintext" and not _LOOPBACK_HOST.match(host):
                raise ValueError(
                    f"endpoints.{name}: {ep!r} is not on loopback; plaintext is for one computer only "
                    "(use security: mtls between computers)"
                )
            if host in ("0.0.0.0", "[::]", "*") and not self.allow_all_interfaces:
                raise ValueError(
                    f"endpoints.{name}: {ep!r} listens on every interface; name the lab interface's "
                    "address, or set allow_all_interfaces: true"
                )
        return self


class BusSpec(_Strict):
    """`operator_port`: the loopback UDP port (127.0.0.1) on which an in-process mission listens for
    `flightstack abort` (flightstack/comms/operator_link.py); default: derived from the mission name,
    listening on hardware only. Setting it also makes a simulated in-process run listen.

    `certs`: the directory (relative to the mission file) of this mission's certificates,
    made by `flightstack certs`. On real hardware the bus is authenticated: Zenoh runs mutual TLS with
    them (ZenohSpec), and the loopback listener of an in-process flight accepts only aborts signed with
    the operator's key (`ca.pem` + `operator.pem` checked at start; `flightstack abort` signs with
    `operator.key`). Simulated missions need them only with `security: mtls`."""

    kind: Literal["inproc", "zenoh"] = "inproc"
    certs: str = Field(default="certs", min_length=1, max_length=4096)
    # what a neighbour's prediction may claim (flightstack/comms/acceptance.py): the target's body
    # velocity μ per component (m/s, rad/s); a message beyond is dropped ("mu out of bounds")
    max_target_speed_mps: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] = 10.0
    max_target_yaw_rate: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] = 10.0
    stale_after_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 0.5
    zenoh: ZenohSpec | None = None
    operator_port: int | None = Field(default=None, ge=1024, le=65535)

    @model_validator(mode="after")
    def _zenoh(self) -> BusSpec:
        if self.kind == "zenoh" and self.zenoh is None:
            raise ValueError("zenoh: bus kind 'zenoh' needs the zenoh section (endpoints)")
        return self
