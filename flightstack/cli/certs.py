"""`flightstack certs MISSION --out DIR`: the mission CA and a certificate per participant (issue 16).

Prints where each file goes: every computer of the mission gets `ca.pem` and the pair of the
participant(s) it runs, into the directory the mission's `bus.zenoh.certs` names (README "Securing the
bus"). `ca.key` stays where it was made.
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
from flightstack.config.mission import MissionError, load_mission


def cmd_certs(args: argparse.Namespace) -> int:
    mission = load_mission(args.mission, check_files=False, rig=args.rig)
    out = Path(args.out)
    ids = [d.id for d in mission.drones]
    try:
        create_mission_certs(mission.name, ids, out, days=args.days)
    except CertError as exc:
        raise MissionError(f"certs: {exc}") from None
    except OSError as exc:
        raise MissionError(f"certs: cannot write {out}: {exc.strerror or exc}") from None
    z = mission.bus.zenoh
    where = mission.bus.certs
    n = len(ids) + 4
    print(f"mission {mission.name!r}: CA and {n} participant certificates in {out} ({args.days} days)")
    print(f"copy to each computer, into the mission's bus.certs directory ({where!r}):")
    rows = [(agent_name(i), f"flightstack agent MISSION --id {i}") for i in ids]
    rows += [
        (AGENTS, "flightstack fly/sim with every agent in one process"),
        (WORLD, "flightstack world (served simulation)"),
        (OPERATOR, "flightstack abort / status"),
        (GUARD, "flightstack guard"),
    ]
    for name, what in rows:
        print(f"  ca.pem {name}.pem {name}.key   -> the computer running {what}")
    print("keep ca.key on this computer only (it signs; no participant needs it)")
    if mission.simulated and (z is None or z.security != "mtls"):
        print("note: this simulated mission runs plaintext on loopback; it does not need them")
    return 0


def register(sub: Any) -> None:
    c = sub.add_parser("certs", help="create the mission CA and a certificate for each participant")
    c.add_argument("mission")
    c.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    c.add_argument("--out", required=True, help="directory for the CA and the participants' keys (new files)")
    c.add_argument("--days", type=int, default=90, help="validity in days (1..3650, default 90)")
    c.set_defaults(func=cmd_certs)
