"""The mission's `bus:` section (DESIGN §6): in-process or Zenoh, endpoints, transport security."""

from __future__ import annotations

import re
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from flightstack.schema_types import Positive
from flightstack.schema_types import Strict as _Strict


class ZenohSpec(_Strict):
    """The mission's Zenoh network (flightstack/comms/zenoh_bus.py), peer mode, full mesh.

    `endpoints`: participant → the endpoint it listens on; every participant connects to all the others.
    Participants: a drone id (`flightstack agent --id N`), `agents` (all agents in one process:
    `flightstack sim`/`fly` with bus kind zenoh), `world` (`flightstack world`, the simulated world served
    to agent processes). Operator tools (`abort`, `status`) only connect.
    `lease_ms`: a hung peer is declared gone after this (a killed one at once, its TCP links close).
    `lockstep_timeout_s`: on a simulated clock, how long phase 2 waits for a neighbour's message of the
    same tick. `start_timeout_s`: how long every participant waits for the others to appear.
    `tls`: zenoh's transport/link/tls keys (certificate paths, enable_mtls); `access_control`: zenoh's
    ACL section (rules, subjects, policies), both checked by zenoh when the session opens."""

    endpoints: dict[str, str] = Field(min_length=1)
    lease_ms: int = Field(default=500, ge=100, le=60000)
    lockstep_timeout_s: Positive = 2.0
    start_timeout_s: Positive = 15.0
    key_prefix: str = Field(default="flightstack", pattern=r"^[A-Za-z0-9_\-]+$")
    tls: dict[str, str | bool] | None = None
    access_control: dict[str, object] | None = None  # zenoh's `access_control` section, passed as is

    @field_validator("endpoints")
    @classmethod
    def _endpoints(cls, v: dict[str, str]) -> dict[str, str]:
        for name, ep in v.items():
            if not (name in ("agents", "world") or name.isdigit()):
                raise ValueError(f"{name}: participant must be a drone id, 'agents' or 'world'")
            if not re.fullmatch(r"(tcp|udp|tls|quic)/[^\s]+:\d+", ep):
                raise ValueError(f"{name}: {ep!r} is not an endpoint like tcp/127.0.0.1:7447")
        if len(set(v.values())) != len(v):
            raise ValueError("two participants listen on the same endpoint")
        return v


class BusSpec(_Strict):
    """`operator_port`: the loopback UDP port (127.0.0.1) on which an in-process mission listens for
    `flightstack abort` (flightstack/comms/operator_link.py); default: derived from the mission name,
    listening on hardware only. Setting it also makes a simulated in-process run listen."""

    kind: Literal["inproc", "zenoh"] = "inproc"
    stale_after_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 0.5
    zenoh: ZenohSpec | None = None
    operator_port: int | None = Field(default=None, ge=1024, le=65535)

    @model_validator(mode="after")
    def _zenoh(self) -> BusSpec:
        if self.kind == "zenoh" and self.zenoh is None:
            raise ValueError("zenoh: bus kind 'zenoh' needs the zenoh section (endpoints)")
        return self
