"""A peer that is not a participant tries every forgery that once worked, on loopback.

The paper simulation is served by `flightstack world` to three `flightstack agent` processes (lock-step,
deterministic), once undisturbed and once with attackers connecting to every endpoint throughout the
flight (tests/attacker_peer.py, separate processes). Each attacker puts, every 20 ms: a prediction
that once took over sender 2's slot (seq 2³²−1, stamp 1e300), one with variance 5e-324 (once made the
fused μ NaN), one with μ = 1e6, an abort, a malformed status, world commands (emergency stop, 50 m/s, an
unhashable call) and a world tick with an empty state.

Secured (security: mtls): the attackers are a process without a certificate, one with a certificate of
another CA naming itself agent-2, and one holding the mission's own `guard` certificate (a participant
that may read but publish nothing). Nothing they send is accepted: each agent's recording is
bit-identical to the undisturbed run and its drop counters are unchanged.

Plaintext (simulations on loopback): nothing authenticates, so what the bounded-acceptance rules do is
shown with the prediction forgeries, each wearing the session label its real sender put on its last
prediction (so the one-session rule, flightstack/comms/identity.py, does not stop them): no slot
takeover, no NaN fusion; the recording again equals the undisturbed run, and the forgeries are counted
by reason.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flightstack.comms.certs import create_mission_certs, files_of, participants
from flightstack.comms.factory import tls_settings
from flightstack.faults.rows_processes import ServedRun, served_ids, served_mission
from tests.conftest import REPO

IDS = served_ids()
"""The served mission's drones (its agents)."""

pytest.importorskip("zenoh")

NAME = "attacked"
DURATION_S = 6.0  # simulated seconds (600 lock-step ticks)
PRED_FORGERIES = ["pred slot takeover", "pred tiny variance", "pred huge mean"]
ALL_FORGERIES = [
    *PRED_FORGERIES,
    "abort",
    "status",
    "world cmd stop",
    "world cmd 50 m/s",
    "world tick",
    "world cmd crash",
]
FIELDS = ("t", "g_wi", "g_bar_w", "V_cmd", "mu_used", "n_fused")


def _mission(workdir: Path, security: str) -> Path:
    return served_mission(workdir, DURATION_S, name=NAME, security=security)


def _endpoints(mission: Path) -> list[str]:
    import yaml

    return list(yaml.safe_load(mission.read_text())["bus"]["zenoh"]["endpoints"].values())


def _tls(directory: Path, participant: str) -> dict[str, object]:
    return dict(tls_settings(files_of(directory, participant)))


def _start_attacker(workdir: Path, label: str, spec: dict[str, object]) -> subprocess.Popen[str]:
    path = workdir / f"attacker_{label}.json"
    path.write_text(json.dumps({"mission": NAME, "prefix": "flightstack", "period_s": 0.02, **spec}))
    return subprocess.Popen(
        [sys.executable, "-m", "tests.attacker_peer", str(path)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _fly(workdir: Path, mission: Path, attackers: dict[str, dict[str, object]]) -> dict[str, object]:
    """One served flight with `attackers` (label → spec) running throughout; what everybody reported."""
    procs: dict[str, subprocess.Popen[str]] = {}
    try:
        with ServedRun(mission, workdir) as run:
            # from the moment every agent is present (all listeners up, the flight about to start)
            assert run.world_lines.wait_for("present", 60), run.world_lines.rest()
            procs = {label: _start_attacker(workdir, label, spec) for label, spec in attackers.items()}
            codes, world = run.wait()
            world_out = run.world_lines.rest()
    finally:
        reports = {}
        for label, p in procs.items():
            try:
                out, err = p.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                out, err = p.communicate()
            reports[label] = (
                json.loads(out.strip().splitlines()[-1]) if out.strip() else {"error": err[-2000:]}
            )
    recs = {}
    for i in IDS:
        with np.load(workdir / f"agent{i}" / "timeseries_dgp.npz") as z:
            recs[i] = {f: z[f].copy() for f in FIELDS}
    metrics = {i: json.loads((workdir / f"agent{i}" / "metrics.json").read_text()) for i in IDS}
    return {"codes": codes, "world": world, "world_out": world_out, "reports": reports, "recs": recs,
            "metrics": metrics}  # fmt: skip


def _same_flight(clean: dict[str, object], attacked: dict[str, object]) -> None:
    assert attacked["codes"] == {1: 0, 2: 0, 3: 0} and attacked["world"] == 0, attacked["world_out"]
    assert "1: landed, 2: landed, 3: landed" in str(attacked["world_out"])
    for i in IDS:
        a, b = clean["recs"][i], attacked["recs"][i]  # type: ignore[index]
        for f in FIELDS:
            assert np.array_equal(a[f], b[f]), f"agent {i}: {f} differs from the undisturbed flight"
        assert np.all(np.isfinite(b["V_cmd"])) and np.max(np.abs(b["g_wi"][:, :, :3])) < 10.0


def test_a_secured_mission_accepts_nothing_from_outside(tmp_path: Path) -> None:
    clean = _fly(tmp_path / "clean", _mission(tmp_path / "clean", "mtls"), {})
    work = tmp_path / "attacked"
    mission = _mission(work, "mtls")
    eps = _endpoints(mission)
    create_mission_certs(NAME, participants(IDS, None), work / "foreign")  # another CA, same names
    common = {"duration_s": 12.0, "forgeries": ALL_FORGERIES}
    attackers = {
        "no certificate": {**common, "connect": [e.replace("tls/", "tcp/") for e in eps], "tls": None},
        "foreign CA as agent-2": {**common, "connect": eps, "tls": _tls(work / "foreign", "agent-2")},
        "participant guard": {**common, "connect": eps, "tls": _tls(work / "certs", "guard")},
    }
    attacked = _fly(work, mission, attackers)
    reports = attacked["reports"]
    print("secured mission, attempts:", json.dumps(reports))
    for label in attackers:
        rep = reports[label]  # type: ignore[index]
        assert "sent" in rep, rep
        assert sum(rep["sent"].values()) >= len(ALL_FORGERIES) * 100, rep  # ≥ 100 rounds each (2 s)
    # only the guard's certificate opens links; the others never reach anybody
    assert reports["no certificate"]["max_peers"] == 0  # type: ignore[index]
    assert reports["foreign CA as agent-2"]["max_peers"] == 0  # type: ignore[index]
    assert reports["participant guard"]["max_peers"] >= 1  # type: ignore[index]
    _same_flight(clean, attacked)
    for i in IDS:  # not even a drop: the ACL stopped them before our decoders
        assert (
            attacked["metrics"][i]["modes"]["dgp"]["bus_dropped"]
            == clean["metrics"][i]["modes"]["dgp"]["bus_dropped"]
        )  # type: ignore[index]


def test_a_plaintext_simulation_bounds_what_it_accepts(tmp_path: Path) -> None:
    clean = _fly(tmp_path / "clean", _mission(tmp_path / "clean", "plaintext"), {})
    work = tmp_path / "attacked"
    mission = _mission(work, "plaintext")
    spec = {
        "duration_s": 12.0,
        "forgeries": PRED_FORGERIES,
        "connect": _endpoints(mission),
        "tls": None,
        "copy_labels": True,  # each forgery wears its real sender's session label (identity.py)
    }
    attacked = _fly(work, mission, {"plaintext peer": spec})
    rep = attacked["reports"]["plaintext peer"]  # type: ignore[index]
    print("plaintext mission, attempts:", json.dumps(rep))
    print(
        "plaintext mission, dropped:",
        json.dumps({i: attacked["metrics"][i]["modes"]["dgp"]["bus_dropped"] for i in IDS}),
    )  # type: ignore[index]
    assert rep["max_peers"] >= 1 and sum(rep["sent"][f] for f in PRED_FORGERIES) >= 300, rep
    assert rep["sent"].get("with a copied label", 0) >= 100, rep
    _same_flight(clean, attacked)  # no slot takeover, no NaN fusion: the flight is the undisturbed one
    for i in IDS:
        dropped = attacked["metrics"][i]["modes"]["dgp"]["bus_dropped"]  # type: ignore[index]
        assert sum(dropped.values()) > sum(clean["metrics"][i]["modes"]["dgp"]["bus_dropped"].values()), (
            dropped
        )  # type: ignore[index]
        # a copied label passes the one-session rule; the bounds refuse what it carries
        assert {"seq jump", "variance out of bounds", "mu out of bounds"} & set(dropped), dropped
