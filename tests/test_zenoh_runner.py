"""The runner over the Zenoh bus: the paper simulation with all agents in one process, lock-step,
gives the same result as over the in-process bus (issue 6 acceptance). Loopback only."""

from __future__ import annotations

import numpy as np
import pytest

from flightstack.analysis.metrics import mode_metrics
from flightstack.comms.factory import free_loopback_endpoints
from flightstack.config.mission import load_mission
from flightstack.paper.gp import GPExpert, GPHyperparameters
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity_batch
from tests.conftest import MISSIONS, fly_mode

pytest.importorskip("zenoh")


def experts(ids: list[int]) -> dict[int, GPExpert]:
    """One GP expert per drone on its own samples of the paper's target field (different per drone, so
    the fused prediction depends on every neighbour's message)."""
    out = {}
    for k, i in enumerate(ids):
        rng = np.random.default_rng(k)
        X = np.column_stack([rng.uniform(-1.5, 1.5, (40, 2)), np.zeros(40), rng.uniform(-np.pi, np.pi, 40)])
        Y = duffing_body_velocity_batch(X, DuffingParams()) + 0.05 * rng.normal(size=(40, 4))
        hyper = GPHyperparameters(np.full(4, 0.5), np.full((4, 4), 1.0), np.full(4, 0.01))
        out[i] = GPExpert.from_hyperparameters(X, Y, hyper)
    return out


def test_paper_sim_over_zenoh_equals_inproc() -> None:
    inproc = load_mission(MISSIONS / "paper_sim.yaml", {"duration_s": 2.0})
    bus = {
        "kind": "zenoh",
        "stale_after_s": inproc.bus.stale_after_s,
        "zenoh": {"endpoints": {"agents": free_loopback_endpoints()[0]}, "security": "plaintext"},
    }
    zen = load_mission(MISSIONS / "paper_sim.yaml", {"duration_s": 2.0, "bus": bus})
    preds = experts([d.id for d in inproc.drones])
    for mode in ("none", "dgp"):
        a = fly_mode(inproc, mode, preds)
        b = fly_mode(zen, mode, preds)
        assert a.ticks_done == b.ticks_done == 1000 and not b.error, b.error
        ea, eb = mode_metrics(a, inproc)["mean_sq_error"], mode_metrics(b, zen)["mean_sq_error"]
        assert eb == pytest.approx(ea, rel=1e-9), (mode, ea, eb)
        np.testing.assert_allclose(b.mu_used, a.mu_used, rtol=1e-12, atol=0)
        if mode == "dgp":
            assert np.all(b.n_fused == 3)  # every tick fused all three experts: no message was missed
            own = np.array([preds[inproc.drones[0].id].predict_one(x)[0] for x in b.g_bar_w[::100, 0]])
            assert not np.allclose(own, b.mu_used[::100, 0], atol=1e-3)  # neighbours changed the fused μ
        assert b.bus_dropped == {}


def test_cli_bus_override_and_too_little_training_data(tmp_path) -> None:
    """`--bus zenoh` runs a mission without a zenoh section on a loopback endpoint; a run too short to
    fill every expert region is refused before anything flies, naming the band (exit 2, nothing written;
    the check after the data run is tests/test_cli_run_options.py's)."""
    from tests.conftest import run_cli

    out = tmp_path / "run"
    args = ["sim", str(MISSIONS / "paper_sim.yaml"), "--out", str(out), "--duration", "1", "--bus", "zenoh"]
    r = run_cli(*args, "--no-progress", timeout=120)
    assert r.returncode == 2, r.stderr
    assert "too short to train" in r.stderr and "drone 3's band x >= 0.6: 0 ticks" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    r = run_cli(*args, "--modes", "none", "--no-progress", timeout=120)
    assert r.returncode == 0, r.stderr
    assert (out / "timeseries_none.npz").is_file()
    assert "kind: zenoh" in (out / "mission_resolved.yaml").read_text()
