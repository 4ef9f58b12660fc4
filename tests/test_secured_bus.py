"""The mutual-TLS bus built from a mission (factory.zenoh_bus_config), in one process.

Participants with the mission's certificates exchange predictions, status, aborts and acknowledgements
on their own keys; a participant publishing someone else's key is not heard (the access control of
flightstack/comms/acl.py, enforced by Zenoh on the receiving side); `flightstack certs` writes what the
docs/security.md promises (modes, names, refusal to overwrite); bad certificate directories are named.
"""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import numpy as np
import pytest

from flightstack.comms.certs import CertError, check_participant, create_mission_certs, participants
from flightstack.comms.control import ControlEvent
from flightstack.comms.factory import make_bus, zenoh_bus_config
from flightstack.comms.messages import PredictionMessage, encode
from flightstack.config.mission import MissionError, load_mission
from tests.conftest import MISSIONS, eventually, secured_bus

pytest.importorskip("zenoh")

SIM = MISSIONS / "paper_sim.yaml"


def _msg(mission: str, sender: int, seq: int) -> PredictionMessage:
    z = np.zeros(4)
    return PredictionMessage(mission, sender, seq, 0.01 * seq, True, z, z, np.ones(4), np.ones(4))


def test_secured_participants_hear_each_other_and_only_on_their_keys(tmp_path: Path) -> None:
    name = load_mission(SIM).name
    bus = secured_bus(tmp_path / "certs", name, [1, 2, 3], ("1", "2"))
    mission = load_mission(SIM, {"bus": bus})
    a1 = make_bus(mission, "1", {1})
    a2 = make_bus(mission, "2", {2})
    op = make_bus(mission, "operator", set())
    guard = make_bus(mission, "guard", set())
    try:
        assert eventually(lambda: a1.alive() >= {1, 2} and op.alive() >= {1, 2}), (a1.alive(), op.alive())
        time.sleep(0.5)  # subscriber declarations propagated
        a2.publish(_msg(name, 2, 1))
        assert a1.wait_for({2: 1}, 5.0) == set()
        # the guard holds a valid certificate of this mission, but may publish nothing: its forgeries on
        # pred/2 and on the abort key are not heard by anyone
        guard.publish_raw(encode(_msg(name, 2, 99)), 2)
        guard.publish_control("abort", {"reason": "forged by the guard", "id": "g1"})
        time.sleep(1.0)
        assert a1.latest(2, 0.01, 1.0).seq == 1  # type: ignore[union-attr]
        assert [e for e in a1.control_events() if e.kind == "abort"] == []
        assert a1.dropped.total() == 0  # not even dropped: refused by the access control
        # the operator's abort reaches both agents, and both acknowledgements reach the operator
        op.publish_control("abort", {"reason": "operator", "id": "o1"})
        acks: list[ControlEvent] = []
        deadline = time.monotonic() + 10.0
        while len(acks) < 2 and time.monotonic() < deadline:
            acks += [e for e in op.control_events() if e.kind == "abort_ack"]
            time.sleep(0.01)
        assert sorted(tuple(e.payload["drones"]) for e in acks) == [(1,), (2,)]
        assert any(e.kind == "abort" for e in a2.control_events())
    finally:
        for b in (guard, op, a2, a1):
            b.close()


def test_certs_command_writes_private_keys_0600_and_never_overwrites(tmp_path: Path) -> None:
    from flightstack.cli.app import main

    out = tmp_path / "c"
    assert main(["certs", str(SIM), "--out", str(out), "--days", "30"]) == 0
    names = {p.name for p in out.iterdir()}
    # paper_sim runs in one process (no zenoh section): its Zenoh form is `--bus zenoh`, named `agents`
    expected = ("ca", "agent-1", "agent-2", "agent-3", "agents", "operator", "guard")
    assert names == {f"{n}{ext}" for n in expected for ext in (".pem", ".key")}
    for n in expected:
        assert stat.S_IMODE(os.stat(out / f"{n}.key").st_mode) == 0o600
    st = check_participant(out, "agent-2", load_mission(SIM).name)
    assert 29.9 < st.days_left <= 30.0
    before = (out / "agent-1.key").read_bytes()
    assert main(["certs", str(SIM), "--out", str(out)]) == 2  # refuses: files exist
    assert (out / "agent-1.key").read_bytes() == before
    assert main(["certs", str(SIM), "--out", str(tmp_path / "d"), "--days", "0"]) == 2


def test_unusable_certificates_are_named(tmp_path: Path) -> None:
    name = load_mission(SIM).name
    bus = secured_bus(tmp_path / "certs", name, [1, 2, 3], ("1",))
    mission = load_mission(SIM, {"bus": bus})
    zenoh_bus_config(mission, "1", {1})  # fine as made
    os.chmod(tmp_path / "certs" / "agent-1.key", 0o644)
    with pytest.raises(MissionError, match=r"agent-1\.key: readable by others"):
        zenoh_bus_config(mission, "1", {1})
    os.chmod(tmp_path / "certs" / "agent-1.key", 0o600)
    with pytest.raises(CertError, match="issued for mission"):
        check_participant(tmp_path / "certs", "agent-1", "another_mission")
    other = tmp_path / "other"
    create_mission_certs(name, participants([1, 2, 3], ["1"]), other)
    (tmp_path / "certs" / "ca.pem").write_bytes((other / "ca.pem").read_bytes())  # CA swapped
    with pytest.raises(MissionError, match="not signed by the mission CA"):
        zenoh_bus_config(mission, "1", {1})
    with pytest.raises(MissionError, match=r"bus\.certs: .*cannot read"):
        zenoh_bus_config(load_mission(SIM, {"bus": {**bus, "certs": str(tmp_path / "nowhere")}}), "1", {1})


def test_insecure_zenoh_sections_are_refused() -> None:
    plain = {"kind": "zenoh", "zenoh": {"endpoints": {"1": "tcp/127.0.0.1:7451"}}}  # mtls by default
    cases = [
        (plain, "must be tls/ with security 'mtls'"),
        ({"kind": "zenoh", "zenoh": {"endpoints": {"1": "tcp/10.0.0.2:7451"}, "security": "plaintext"}},
         "not on loopback"),
        ({"kind": "zenoh", "zenoh": {"endpoints": {"1": "tls/0.0.0.0:7451"}}}, "listens on every interface"),
        ({"kind": "zenoh", "zenoh": {"endpoints": {"1": "tls/10.0.0.2:7451"}, "tls": {}}},
         "no longer written"),
        ({"kind": "zenoh", "zenoh": {"endpoints": {"1": "tls/10.0.0.2:7451"}, "access_control": {}}},
         "no longer written"),
    ]  # fmt: skip
    for bus, why in cases:
        with pytest.raises(MissionError, match=why):
            load_mission(SIM, {"bus": bus})
    wide = {"kind": "zenoh", "zenoh": {"endpoints": {"1": "tls/0.0.0.0:7451"}, "allow_all_interfaces": True}}
    load_mission(SIM, {"bus": wide})
    hw_plain = {"kind": "zenoh", "zenoh": {"endpoints": {"1": "tcp/127.0.0.1:7451"}, "security": "plaintext"}}
    with pytest.raises(MissionError, match="real drones fly only on an authenticated bus"):
        load_mission(MISSIONS / "paper_experiment.yaml", {"bus": hw_plain}, rig="lab")


def test_preflight_checks_the_certificate_this_computer_needs(tmp_path: Path) -> None:
    from flightstack.drivers.lab.preflight import check_certs

    hw = MISSIONS / "paper_experiment.yaml"
    name = load_mission(hw, rig="lab").name
    missing = load_mission(hw, {"bus": {"certs": str(tmp_path / "none")}}, rig="lab")
    [row] = check_certs(missing, [1, 2], all_in_one=True)
    assert (row.check, row.status) == ("certificate operator", "FAIL") and "cannot read" in row.detail
    create_mission_certs(name, participants([1, 2], None), tmp_path / "soon", days=3)
    [row] = check_certs(
        load_mission(hw, {"bus": {"certs": str(tmp_path / "soon")}}, rig="lab"), [1, 2], all_in_one=True
    )
    assert row.status == "WARN" and "(3 days)" in row.detail  # expires within WARN_DAYS
    bus = secured_bus(tmp_path / "certs", name, [1, 2], ("1", "2"))
    zen = load_mission(hw, {"bus": bus}, rig="lab")
    assert [(r.check, r.status) for r in check_certs(zen, [1])] == [("certificate agent-1", "PASS")]
    # `fly` with every agent in one process: refused where the endpoints do not name `agents`
    [row] = check_certs(zen, [1, 2], all_in_one=True)
    assert (row.check, row.status, row.detail) == (
        "certificate agents",
        "FAIL",
        "bus.zenoh.endpoints do not name it",
    )
    shared = load_mission(hw, {"bus": secured_bus(tmp_path / "shared", name, [1, 2], ("agents",))}, rig="lab")
    assert [(r.check, r.status) for r in check_certs(shared, [1, 2], all_in_one=True)] == [
        ("certificate agents", "PASS")
    ]
