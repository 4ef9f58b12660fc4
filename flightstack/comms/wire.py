"""The bus's wire format in one table: every key expression the project publishes or subscribes to, who
does, what its payload is and the Zenoh encoding set on publish. docs/wire-format.md is generated from it
(docs/hooks/generated.py) and tests/test_wire_format.py checks the page and the code against each other.

Keys are built by flightstack/comms/acl.py (where the access control that says who may publish them is
made); `CHANNELS` names each builder, so a key pattern here is the builder's own output for placeholder
arguments. Encodings are Zenoh encodings as text (`zenoh.Encoding(text)`): a publisher declares its
channel's one, every sample it puts carries it. A receiver never looks at the encoding (a peer of an older
version sends none: `zenoh/bytes`); it decodes the payload and refuses what does not decode.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from flightstack.comms import acl

PRED_ENCODING = "application/octet-stream;flightstack-pred"
"""A prediction message (flightstack/comms/messages.py): binary, its layout named by the schema suffix."""
CONTROL_ENCODING = "application/json"
"""An operator-channel message (flightstack/comms/control.py): UTF-8 JSON."""
WORLD_TICK_ENCODING = "application/octet-stream;flightstack-world-tick"
"""A served world's tick (sim_backend/served/messages.py): length-prefixed JSON header, optional image."""
WORLD_CMD_ENCODING = "application/octet-stream;flightstack-world-cmd"
"""An agent's command to the served world: length-prefixed JSON header, no trailing bytes."""

SESSION_LABEL = "session label"
"""The attachment of predictions and world commands: "<zid> pid <pid> on <host>" (identity.py)."""


@dataclass(frozen=True)
class Channel:
    """One key expression of a mission's key space `{prefix}/{mission}` (prefix: `bus.zenoh.key_prefix`,
    default "flightstack"; mission: the mission's name). builder: the acl.py function that builds the key,
    called with (prefix, mission, *placeholders); encoding: None for a liveliness token (no payload)."""

    name: str
    builder: Callable[..., str]
    placeholders: tuple[str, ...]
    publisher: str
    subscribers: str
    payload: str
    encoding: str | None
    attachment: str

    @property
    def pattern(self) -> str:
        """The key with its placeholders, e.g. "{prefix}/{mission}/pred/{i}"."""
        return self.builder("{prefix}", "{mission}", *self.placeholders)


CHANNELS: tuple[Channel, ...] = (
    Channel(
        "prediction",
        acl.pred_key,
        ("{i}",),
        "agent i (each tick, `ZenohBus.publish`)",
        "every bus: agent processes, `flightstack status` (`pred/*`)",
        "binary prediction message, below",
        PRED_ENCODING,
        SESSION_LABEL,
    ),
    Channel(
        "presence",
        acl.alive_key,
        ("{i}",),
        "agent i's process (a liveliness token, declared after its subscribers)",
        "every bus (liveliness subscriber on `alive/*`, with history)",
        "none: a token's appearance and disappearance are the message",
        None,
        "none",
    ),
    Channel(
        "abort",
        acl.abort_key,
        (),
        "`flightstack abort` (participant operator)",
        "every process hosting agents (`control/**`)",
        "control JSON, kind abort",
        CONTROL_ENCODING,
        "none",
    ),
    Channel(
        "status",
        acl.status_key,
        ("{i}",),
        "agent i's process, about twice a second (`StatusPublisher`, flightstack/runtime/fleet.py)",
        "`flightstack status`, `flightstack guard` (drivers/lab/guard.py) and every bus (`control/**`)",
        "control JSON, kind status",
        CONTROL_ENCODING,
        "none",
    ),
    Channel(
        "acknowledgement",
        acl.ack_key,
        ("{name}",),
        "every process hosting agents, once per abort received (name: its certificate's common name)",
        "`flightstack abort` (`control/**`)",
        "control JSON, kind abort_ack",
        CONTROL_ENCODING,
        "none",
    ),
    Channel(
        "world tick",
        acl.tick_key,
        ("{i}",),
        "`flightstack world` (the served simulation), each tick",
        "agent i's process",
        "world message: length, JSON tick header, optional image",
        WORLD_TICK_ENCODING,
        "the session label of the agent the world serves drone i to (none before its hello)",
    ),
    Channel(
        "world command",
        acl.cmd_key,
        ("{i}",),
        "agent i's process, each tick (k = -1: its hello)",
        "`flightstack world` (`world/cmd/*`)",
        "world message: length, JSON cmd header",
        WORLD_CMD_ENCODING,
        SESSION_LABEL,
    ),
)
"""Every key expression of the bus, in the order of docs/wire-format.md."""


def channel(name: str) -> Channel:
    """The channel called `name` (KeyError if none)."""
    for c in CHANNELS:
        if c.name == name:
            return c
    raise KeyError(name)


__all__ = [
    "CHANNELS",
    "CONTROL_ENCODING",
    "PRED_ENCODING",
    "SESSION_LABEL",
    "WORLD_CMD_ENCODING",
    "WORLD_TICK_ENCODING",
    "Channel",
    "channel",
]
