"""`flightstack certs MISSION --out DIR`: the mission CA and a certificate per participant.

Makes exactly the mission's participants (factory.mission_participants): `agent-<id>` per drone,
`operator` and `guard`, and `agents` / `world` only when `bus.zenoh.endpoints` names them, because the
`agents` certificate may publish every drone's keys. Refuses a DIR that holds any participant's files,
also of one this mission no longer has (a folder never mixes two CAs' pairs or keeps a stale `agents`).
Prints where each file goes: every computer of the mission gets `ca.pem` and the pair of the
participant(s) it runs, into the directory the mission's `bus.certs` names (docs/security.md).
`ca.key` stays where it was made.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from flightstack.comms.certs import (
    AGENTS,
    GUARD,
    OPERATOR,
    WORLD,
    CertError,
    agent_name,
    create_mission_certs,
)
from flightstack.comms.factory import mission_participants
from flightstack.config.mission import MissionError, load_mission

_RUNS = {
    AGENTS: "flightstack fly/sim with every agent in one process",
    WORLD: "flightstack world (served simulation)",
    OPERATOR: "flightstack abort / status",
    GUARD: "flightstack guard",
}


def cmd_certs(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission, check_files=False, rig=args.rig)
    out = Path(args.out)
    names = mission_participants(mission)
    try:
        create_mission_certs(mission.name, names, out, days=args.days)
    except CertError as exc:
        raise MissionError(f"certs: {exc}") from None
    except OSError as exc:
        raise MissionError(f"certs: cannot write {out}: {exc.strerror or exc}") from None
    z = mission.bus.zenoh
    print(
        f"mission {mission.name!r}: CA and {len(names)} participant certificates in {out} ({args.days} days)"
    )
    print(f"copy to each computer, into the mission's bus.certs directory ({mission.bus.certs!r}):")
    runs = {agent_name(d.id): f"flightstack agent MISSION --id {d.id}" for d in mission.drones} | _RUNS
    for name in names:
        print(f"  ca.pem {name}.pem {name}.key   -> the computer running {runs[name]}")
    if AGENTS not in names:
        print("no `agents` certificate: the mission's endpoints do not name one process flying every drone")
    print("keep ca.key on this computer only (it signs; no participant needs it)")
    if mission.simulated and (z is None or z.security != "mtls"):
        print("note: this simulated mission runs plaintext on loopback; it does not need them")
    return 0


def register(sub: Any) -> None:
    c = sub.add_parser("certs")
    c.add_argument(
        "mission",
        help="experiment (with --rig) or mission YAML file: its drones and `bus:` name the participants",
    )
    c.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    c.add_argument("--out", required=True, help="directory for the CA and the participants' keys (new files)")
    c.add_argument("--days", type=int, default=90, help="validity in days (1..3650, default 90)")
    c.set_defaults(func=cmd_certs)
