"""The bus a process uses, from the mission's `bus:` section (DESIGN §6).

`participant` names this process in `bus.zenoh.endpoints`: a drone id (one agent per process), `agents`
(every agent in one process), `world` (the served simulated world), or anything else for operator
tools, which only connect. Each participant listens on its own endpoint and connects to all others.

Time base (freshness.py): simulated missions keep comparing stamps on the one mission clock
(lock-step, bit-identical); real-time (hardware) missions on Zenoh measure each neighbour's message age on
the receiver's own clock through a per-sender offset learned when the sender joins. The in-process bus
has one clock for every agent and always compares stamps.

Operator channel (operator_link.py): an in-process bus on hardware (or with `bus.operator_port`
set) wraps a loopback UDP listener, so `flightstack abort` reaches a `flightstack fly` from another
terminal; `bus.control_events()` yields its aborts.

Security: a `security: mtls` Zenoh bus gets this participant's certificate files from
`bus.certs` (checked first: certs.check_participant) and the access control generated from the
mission's participants (`mission_participants`, acl.py); a participant the mission does not have (say
`agents` when its endpoints do not name it) is refused before it opens, even when an older `certs` run
left its pair in `bus.certs`. A hardware mission refuses plaintext Zenoh, and its loopback listener
verifies the operator's signature (`operator_key`). Participant names map to certificate common names:
a drone id N → "agent-N"; "agents", "world", "operator", "guard" as they are.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from flightstack.comms.acceptance import AcceptanceBounds
from flightstack.comms.acl import access_control
from flightstack.comms.bus import Bus, InProcBus
from flightstack.comms.certs import (
    CertError,
    ParticipantFiles,
    check_participant,
    files_of,
    participant_name,
    participants,
)
from flightstack.config.mission import Mission, MissionError
from flightstack.ports import free_tcp_port

if TYPE_CHECKING:
    from flightstack.comms.operator_link import LoopbackOperatorListener
    from flightstack.comms.zenoh_config import ZenohBusConfig


def mission_participants(mission: Mission) -> list[str]:
    """The certificate common names of `mission`'s participants (certs.participants): `agent-<id>` per
    drone, `agents` and `world` when `bus.zenoh.endpoints` names them, `operator`, `guard`."""
    z = mission.bus.zenoh
    return participants([d.id for d in mission.drones], None if z is None else list(z.endpoints))


def zenoh_bus_config(mission: Mission, participant: str, self_ids: set[int]) -> ZenohBusConfig:
    """The ZenohBusConfig of `participant` (a drone id, "agents", "world", "operator", "guard").

    `security: mtls`: the participant's certificate files (certs.check_participant: present, key mode
    0600, signed by the mission CA, issued to this participant and mission, not expired) and the
    generated access control; MissionError naming `bus.zenoh.certs` and the reason otherwise."""
    from flightstack.comms.zenoh_config import ZenohBusConfig

    z = mission.bus.zenoh
    if z is None:
        raise ValueError("bus.zenoh: the mission has no zenoh section")
    listen = [z.endpoints[participant]] if participant in z.endpoints else []
    connect = [ep for name, ep in z.endpoints.items() if name != participant]
    ids = {d.id for d in mission.drones}
    name = participant_name(participant)
    if not mission.simulated and z.security != "mtls":
        raise MissionError(
            "bus.zenoh.security: real drones fly only on an authenticated bus (security: mtls with the "
            "certificates of `flightstack certs`); plaintext is for simulations on one computer"
        )
    tls = acl = None
    if z.security == "mtls":
        names = mission_participants(mission)
        if name not in names:
            raise MissionError(
                f"bus.zenoh.endpoints: this mission has no participant {name!r} (it has {', '.join(names)});"
                f" name it in the endpoints to run it (and make its certificate with `flightstack certs`)"
            )
        tls = mtls_settings(mission, name)
        acl = access_control(z.key_prefix, mission.name, ids, names)
    return ZenohBusConfig(
        mission=mission.name,
        self_ids=set(self_ids),
        known_senders=ids,
        listen=listen,
        connect=connect,
        lease_ms=z.lease_ms,
        key_prefix=z.key_prefix,
        tls=tls,
        acl=acl,
        participant=name,
        allow_all_interfaces=z.allow_all_interfaces,
        bounds=acceptance_bounds(mission),
        reliable=mission.simulated,  # lock-step waits for every message: a dropped one would stall a tick
        time_base="stamps" if mission.simulated else "receiver",
    )


def mtls_settings(mission: Mission, name: str) -> dict[str, str | bool]:
    """Zenoh's transport/link/tls keys for participant `name` (a certificate CN) of a `security: mtls`
    mission: mutual TLS against the mission CA; host names are not verified (certs.py: the common name
    and the ACL decide who is who)."""
    z = mission.bus.zenoh
    assert z is not None
    directory = mission.resolve(mission.bus.certs)
    try:
        check_participant(directory, name, mission.name)
    except CertError as exc:
        raise MissionError(
            f"bus.certs: {exc} (create them with `flightstack certs MISSION --out DIR`; docs/security.md)"
        ) from None
    return tls_settings(files_of(directory, name))


def tls_settings(f: ParticipantFiles) -> dict[str, str | bool]:
    """Zenoh's transport/link/tls keys for these files: mutual TLS, names not verified (certs.py)."""
    return {
        "root_ca_certificate": str(f.ca),
        "listen_certificate": str(f.cert),
        "listen_private_key": str(f.key),
        "connect_certificate": str(f.cert),
        "connect_private_key": str(f.key),
        "enable_mtls": True,
        "verify_name_on_connect": False,
    }


def acceptance_bounds(mission: Mission) -> AcceptanceBounds:
    """What a received prediction of `mission` may claim (acceptance.py), with the mission's bounds on
    the target's velocity."""
    return AcceptanceBounds(
        max_speed_mps=mission.bus.max_target_speed_mps, max_yaw_rate_rps=mission.bus.max_target_yaw_rate
    )


def make_bus(mission: Mission, participant: str, self_ids: set[int], kind: str | None = None) -> Bus:
    """InProcBus or ZenohBus for the agents `self_ids` of this process; `kind` overrides the mission's.

    An in-process bus listens for the operator on loopback (`operator_listener`) on hardware, or when the
    mission sets `bus.operator_port`; RuntimeError when that port cannot be bound."""
    kind = kind or mission.bus.kind
    if kind == "inproc":
        return InProcBus(
            mission.name,
            {d.id for d in mission.drones},
            operator=operator_listener(mission, self_ids),
            bounds=acceptance_bounds(mission),
        )
    from flightstack.comms.zenoh_bus import ZenohBus

    return ZenohBus(zenoh_bus_config(mission, participant, self_ids))


def operator_listener(mission: Mission, self_ids: set[int]) -> LoopbackOperatorListener | None:
    """The loopback operator listener of an in-process run of `mission` hosting `self_ids`, or None when
    it needs none (simulated, no `bus.operator_port`)."""
    if mission.simulated and mission.bus.operator_port is None:
        return None
    from flightstack.comms.operator_link import LoopbackOperatorListener, operator_port

    verifier = None if mission.simulated else operator_key(mission, private=False)
    return LoopbackOperatorListener(mission.name, operator_port(mission), set(self_ids), verifier)


def operator_key(mission: Mission, private: bool) -> Any:
    """The operator's public key (to verify loopback aborts) or private key (to sign them) from the
    mission's `bus.certs`; MissionError naming `bus.certs` and the reason when it cannot be used."""
    from flightstack.comms.certs import operator_private_key, operator_public_key

    directory = mission.resolve(mission.bus.certs)
    try:
        if private:
            return operator_private_key(directory, mission.name)
        return operator_public_key(directory, mission.name)
    except CertError as exc:
        raise MissionError(
            f"bus.certs: {exc} (real drones accept only aborts signed by the operator's key; create the "
            "certificates with `flightstack certs MISSION --out DIR`, docs/security.md)"
        ) from None


def free_loopback_endpoints(n: int = 1) -> list[str]:
    """n endpoints `tcp/127.0.0.1:PORT` on distinct ports that are free now (`flightstack.ports`)."""
    return [f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(n)]
