"""The mission's key space and who may publish on each key: Zenoh access control, generated.

Keys (one mission = one key space `{prefix}/{mission}`):

    pred/{i}                 agent i's prediction                      publisher: agent-i (or agents*)
    alive/{i}                agent i's liveliness token                 declarer:  agent-i (or agents*)
    control/abort            an operator abort                          publisher: operator
    control/status/{i}       agent i's status report                    publisher: agent-i (or agents*)
    control/ack/{name}       abort acknowledgement of participant name publisher: that participant
    world/tick/{i}           what drone i's sensors see (served sim)    publisher: world
    world/cmd/{i}            what agent i did to drone i (served sim)   publisher: agent-i

(*) `agents`, the one certificate that speaks for every drone, and `world` are granted only to a mission
that has them, i.e. whose `bus.zenoh.endpoints` names them (certs.participants); otherwise no rule or
subject mentions them, and a drone's keys can be published only with that drone's own certificate.

`access_control(...)` turns that table into Zenoh's `access_control` section, with `default_permission:
deny`. Every node enforces it on *ingress*: a message that arrives on a link is accepted only if the
certificate common name of that link (flightstack/comms/certs.py) may publish its key. Every
participant may declare subscribers and liveliness subscribers on the mission's keys (to read is not
to act). Egress is allowed on the mission's keys to the mission's participants only: a link may also
come from a certificate of the same CA that the mission does not name (an older `certs` run), and a
Zenoh peer sends data to a new link before that link's subscriber declarations are settled, so only the
sender's egress filter keeps such a link from reading. Nothing outside `{prefix}/{mission}/**` passes
in either direction.

What the key alone cannot say is checked on receipt: the sender field of a prediction equals its key
(freshness.py), a status names the drone of its key, an acknowledgement names only drones its
participant hosts (zenoh_bus.py). A receiver cannot learn the certificate a message came with: a Zenoh
sample carries no link or certificate, and its optional `source_info` is an id the publishing session
declares about itself, not authenticated. So who may publish a key is decided by this ACL alone, on the
receiving node's ingress, before any subscriber sees the message (tests/test_key_ownership.py tries
every certificate on every key). Messages a participant's own session publishes reach its own
subscribers without passing a link (Zenoh's local delivery), i.e. without the ACL; a process only
publishes its own keys, so this admits nothing foreign.
"""

from __future__ import annotations

from typing import Any

from flightstack.comms.certs import AGENTS, OPERATOR, WORLD, agent_name

PUBLISH = ["put", "delete"]
READ = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
EVERY_MESSAGE = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


def space(prefix: str, mission: str) -> str:
    return f"{prefix}/{mission}"


def pred_key(prefix: str, mission: str, sender: int | str) -> str:
    return f"{space(prefix, mission)}/pred/{sender}"


def alive_key(prefix: str, mission: str, sender: int | str) -> str:
    return f"{space(prefix, mission)}/alive/{sender}"


def abort_key(prefix: str, mission: str) -> str:
    return f"{space(prefix, mission)}/control/abort"


def status_key(prefix: str, mission: str, drone: int | str) -> str:
    return f"{space(prefix, mission)}/control/status/{drone}"


def ack_key(prefix: str, mission: str, participant: str) -> str:
    return f"{space(prefix, mission)}/control/ack/{participant}"


def control_space(prefix: str, mission: str) -> str:
    """Every control key (the wildcard a control subscriber declares)."""
    return f"{space(prefix, mission)}/control/**"


def tick_key(prefix: str, mission: str, drone: int | str) -> str:
    return f"{space(prefix, mission)}/world/tick/{drone}"


def cmd_key(prefix: str, mission: str, drone: int | str) -> str:
    return f"{space(prefix, mission)}/world/cmd/{drone}"


def hosted_by(participant: str, drone_ids: set[int] | frozenset[int]) -> frozenset[int]:
    """The drones whose agents participant `participant` (a certificate CN) may host."""
    if participant == AGENTS:
        return frozenset(drone_ids)
    if participant.startswith("agent-") and participant[6:].isdigit():
        i = int(participant[6:])
        return frozenset({i}) if i in drone_ids else frozenset()
    return frozenset()


def _agent_keys(prefix: str, mission: str, ids: list[int], name: str) -> list[str]:
    keys = [ack_key(prefix, mission, name)]
    for i in ids:
        keys += [pred_key(prefix, mission, i), status_key(prefix, mission, i)]
    return keys


def access_control(
    prefix: str, mission: str, drone_ids: set[int] | list[int], names: list[str]
) -> dict[str, Any]:
    """Zenoh's `access_control` section for a mission with these drones and participants `names`
    (certs.participants; see the module docstring). `agents` and `world` are granted only when in
    `names`; every drone of `drone_ids` has its `agent-<id>`."""
    ids = sorted(drone_ids)
    names = list(dict.fromkeys([*(agent_name(i) for i in ids), *names]))
    everything = f"{space(prefix, mission)}/**"
    rules: list[dict[str, Any]] = [
        {"id": "egress", "messages": EVERY_MESSAGE, "flows": ["egress"], "permission": "allow",
         "key_exprs": [everything]},
        {"id": "read", "messages": READ, "flows": ["ingress"], "permission": "allow",
         "key_exprs": [everything]},
    ]  # fmt: skip
    subjects: list[dict[str, Any]] = [{"id": "participants", "cert_common_names": names}]
    policies: list[dict[str, Any]] = [
        {"id": "egress", "rules": ["egress"], "subjects": ["participants"]},
        {"id": "read", "rules": ["read"], "subjects": ["participants"]},
    ]

    def grant(name: str, puts: list[str], tokens: list[str]) -> None:
        rid = f"publish:{name}"
        rule: dict[str, Any] = {"id": rid, "messages": PUBLISH, "flows": ["ingress"], "permission": "allow"}
        rules.append({**rule, "key_exprs": puts})
        if tokens:
            rules.append(
                {**rule, "id": f"tokens:{name}", "messages": ["liveliness_token"], "key_exprs": tokens}
            )
        subjects.append({"id": f"cn:{name}", "cert_common_names": [name]})
        policies.append(
            {
                "id": f"cn:{name}",
                "rules": [rid, *([f"tokens:{name}"] if tokens else [])],
                "subjects": [f"cn:{name}"],
            }
        )

    for i in ids:
        grant(
            agent_name(i),
            [*_agent_keys(prefix, mission, [i], agent_name(i)), cmd_key(prefix, mission, i)],
            [alive_key(prefix, mission, i)],
        )
    if AGENTS in names:
        alive = [alive_key(prefix, mission, i) for i in ids]
        grant(AGENTS, _agent_keys(prefix, mission, ids, AGENTS), alive)
    if WORLD in names:
        grant(WORLD, [tick_key(prefix, mission, i) for i in ids], [])
    grant(OPERATOR, [abort_key(prefix, mission)], [])
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}  # fmt: skip


__all__ = [
    "abort_key",
    "access_control",
    "ack_key",
    "alive_key",
    "cmd_key",
    "control_space",
    "hosted_by",
    "pred_key",
    "status_key",
    "tick_key",
]
