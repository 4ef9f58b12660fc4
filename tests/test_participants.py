"""Which participants a mission has, and that only they get certificates and grants (docs/security.md):
the shared `agents` certificate, which may publish every drone's keys, and `world` exist only
where the mission's endpoints name them. Pure functions, the generated access-control section, the
`certs` command in-process and the bus factory's refusal; no Zenoh session is opened here (the keys
tried on a live mutual-TLS network: tests/test_key_ownership.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from flightstack.comms.acl import access_control
from flightstack.comms.certs import CertError, create_mission_certs, participants
from flightstack.comms.factory import mission_participants, zenoh_bus_config
from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import resolved_document
from tests.conftest import MISSIONS, secured_bus

SIM = MISSIONS / "paper_sim.yaml"
IDS = [1, 2, 3]


def _mission_file(tmp: Path, endpoint_names: list[str]) -> Path:
    """paper_sim as a mutual-TLS Zenoh mission whose endpoints name `endpoint_names` (loopback)."""
    m = resolved_document("paper_sim")
    eps = {n: f"tls/127.0.0.1:{17500 + k}" for k, n in enumerate(endpoint_names)}  # never opened here
    m["bus"] = {"kind": "zenoh", "certs": "certs", "zenoh": {"endpoints": eps}}
    path = tmp / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    return path


def test_the_shared_and_the_world_participant_exist_only_where_the_endpoints_name_them() -> None:
    agents_each = ["agent-1", "agent-2", "agent-3"]
    assert participants(IDS, ["1", "2", "3", "world"]) == [*agents_each, "world", "operator", "guard"]
    assert participants(IDS, ["1", "2", "3"]) == [*agents_each, "operator", "guard"]
    assert participants(IDS, ["agents", "world"]) == [*agents_each, "agents", "world", "operator", "guard"]
    # no zenoh section: the mission runs in one process; its only Zenoh form is `--bus zenoh` (`agents`)
    assert participants(IDS, None) == [*agents_each, "agents", "operator", "guard"]
    assert participants({3, 1}, ["agents"]) == ["agent-1", "agent-3", "agents", "operator", "guard"]


def _grants(acl: dict) -> dict[str, set[str]]:
    """certificate common name → the key expressions it may put (from the policies it is subject of)."""
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s.get("cert_common_names", []) for s in acl["subjects"]}
    out: dict[str, set[str]] = {}
    for pol in acl["policies"]:
        for rid in pol["rules"]:
            r = rules[rid]
            if r["flows"] == ["ingress"] and "put" in r["messages"]:
                for s in pol["subjects"]:
                    for cn in subjects[s]:
                        out.setdefault(cn, set()).update(r["key_exprs"])
    return out


def test_a_mission_of_one_agent_each_grants_each_drone_key_only_to_its_agent() -> None:
    names = participants(IDS, ["1", "2", "3", "world"])
    acl = access_control("fs", "m", IDS, names)
    assert "agents" not in json.dumps(acl)  # no subject, rule or key names the shared certificate
    grants = _grants(acl)
    for i in IDS:
        own = {
            f"fs/m/pred/{i}",
            f"fs/m/control/status/{i}",
            f"fs/m/control/ack/agent-{i}",
            f"fs/m/world/cmd/{i}",
        }
        assert grants[f"agent-{i}"] == own
        for key in own:  # nobody else may put any of them
            assert [cn for cn, keys in grants.items() if key in keys] == [f"agent-{i}"]
    assert grants["world"] == {f"fs/m/world/tick/{i}" for i in IDS}
    assert grants["operator"] == {"fs/m/control/abort"}
    assert "guard" not in grants
    read = next(s for s in acl["subjects"] if s["id"] == "participants")["cert_common_names"]
    assert sorted(read) == sorted(names)


def test_the_shared_agents_participant_is_granted_every_drone_only_where_named() -> None:
    acl = access_control("fs", "m", IDS, participants(IDS, ["agents"]))
    grants = _grants(acl)
    assert grants["agents"] == {f"fs/m/{k}/{i}" for i in IDS for k in ("pred", "control/status")} | {
        "fs/m/control/ack/agents"
    }
    assert "world" not in grants and "world/tick" not in json.dumps(acl)  # not named: no tick grant
    tokens = [r for r in acl["rules"] if r["id"] == "tokens:agents"]
    assert tokens and set(tokens[0]["key_exprs"]) == {f"fs/m/alive/{i}" for i in IDS}


def test_certs_makes_no_agents_pair_for_a_mission_of_one_agent_each(tmp_path: Path, capsys) -> None:
    from flightstack.cli.app import main

    path = _mission_file(tmp_path, ["world", "1", "2", "3"])
    assert main(["certs", str(path), "--out", str(tmp_path / "certs")]) == 0
    out = capsys.readouterr().out
    stems = {p.name.rsplit(".", 1)[0] for p in (tmp_path / "certs").iterdir()}
    assert stems == {"ca", "agent-1", "agent-2", "agent-3", "world", "operator", "guard"}
    assert "CA and 6 participant certificates" in out and "agents.pem" not in out
    shared = tmp_path / "shared"
    shared.mkdir()
    path = _mission_file(shared, ["agents"])
    assert main(["certs", str(path), "--out", str(shared / "certs")]) == 0
    stems = {p.name.rsplit(".", 1)[0] for p in (shared / "certs").iterdir()}
    assert stems == {"ca", "agent-1", "agent-2", "agent-3", "agents", "operator", "guard"}


def test_certs_refuses_a_folder_holding_any_participant_pair(tmp_path: Path) -> None:
    out = tmp_path / "c"
    out.mkdir()
    (out / "agents.pem").write_text("left by an older run")
    (out / "notes.txt").write_text("not a certificate: ignored")
    with pytest.raises(CertError, match=r"already holds agents\.pem"):
        create_mission_certs("m", participants(IDS, ["1", "2", "3"]), out)
    assert sorted(p.name for p in out.iterdir()) == ["agents.pem", "notes.txt"]  # nothing written
    with pytest.raises(CertError, match=r"'\.\./x' is not a participant"):
        create_mission_certs("m", ["../x"], tmp_path / "d")
    assert not (tmp_path / "d").exists()


def test_a_participant_the_mission_does_not_have_is_refused_even_with_a_stale_pair(tmp_path: Path) -> None:
    name = load_mission(SIM).name
    # an older `certs` run (the mission then named `agents`) left a valid `agents` pair of the same CA
    bus = secured_bus(tmp_path / "certs", name, IDS, ("agents", "1", "2", "3"))
    del bus["zenoh"]["endpoints"]["agents"]  # the mission now runs one agent per process
    mission = load_mission(SIM, {"bus": bus})
    assert mission_participants(mission) == ["agent-1", "agent-2", "agent-3", "operator", "guard"]
    assert (tmp_path / "certs" / "agents.key").is_file()
    with pytest.raises(MissionError, match="this mission has no participant 'agents'"):
        zenoh_bus_config(mission, "agents", set(IDS))
    with pytest.raises(MissionError, match="no participant 'world'"):
        zenoh_bus_config(mission, "world", set())
    cfg = zenoh_bus_config(mission, "1", {1})  # its own participants open as before
    assert cfg.acl is not None and "agents" not in json.dumps(cfg.acl)
