"""The guard of the compiled lock-step loop (flightstack.sim_backend.compiled_loop): on the ideal rig its
recordings equal the Agent path's bit for bit, in every mode and fusion rule; ticks it does not model go to
Python; it is used only where it applies; Ctrl-C between chunks stops the run and keeps what was flown."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightstack.config.mission import load_mission
from flightstack.paper.gp import GPExpert, GPHyperparameters
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity_batch
from flightstack.recording.timeseries import ARRAY_FIELDS, MACHINE_FIELDS, Recording
from flightstack.runtime.agent import TruthPredictor
from flightstack.runtime.fleet import assemble_fleet
from flightstack.sim_backend.compiled_loop import CHUNK_TICKS, CompiledLoop, why_not_compiled
from tests.conftest import fly_mode

COMPARED = tuple(f for f in ARRAY_FIELDS if f not in MACHINE_FIELDS)  # wall time: this computer


def _experts(mission, sizes: dict[int, int], scale: float = 1.0, seed: int = 0) -> dict[int, GPExpert]:
    """Experts on noisy samples of the true field, M_i points each (different M: the padded stacks)."""
    rng = np.random.default_rng(seed)
    prm = DuffingParams(**mission.target.duffing.model_dump())
    lo, hi = np.array([-2.0, -1.5, -0.05, -math.pi]), np.array([1.9, 1.5, 0.05, math.pi])
    out = {}
    for i, M in sizes.items():
        X = rng.uniform(lo, hi, size=(M, 4))
        Y = scale * duffing_body_velocity_batch(X, prm) + 0.1 * rng.normal(size=(M, 4))
        hyper = GPHyperparameters(
            np.full(4, 0.5 * scale), np.tile([0.8, 0.9, 1.0, 2.0], (4, 1)), np.full(4, 0.01)
        )
        out[i] = GPExpert.from_hyperparameters(X, Y, hyper)
    return out


def _both(mission, mode: str, predictors) -> tuple[Recording, Recording]:
    return fly_mode(mission, mode, predictors, compiled=True), fly_mode(
        mission, mode, predictors, compiled=False
    )


def _assert_identical(a: Recording, b: Recording) -> None:
    assert a.ticks_done == b.ticks_done > 0
    assert a.error == b.error and a.interrupted == b.interrupted
    for name in COMPARED:
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape, name
        assert np.array_equal(x, y), f"{name} differs: max |Δ| = {np.max(np.abs(x - y))}"
    assert a.bus_dropped == b.bus_dropped
    assert a.vision_rejections == b.vision_rejections
    kinds = {"neighbours", "end", "landed", "NOT LANDED"}
    ev_a = [e for e in a.events if e.get("event") in kinds]
    ev_b = [e for e in b.events if e.get("event") in kinds]
    assert ev_a == ev_b


def _compiled_event(rec: Recording) -> dict:
    (ev,) = [e for e in rec.events if e.get("event") == "compiled loop"]
    return ev


@pytest.fixture(scope="module")
def paper_sim():
    return load_mission("paper_sim", {"duration_s": 1.5})  # 750 ticks: two chunks and a partial one


@pytest.mark.parametrize("mode", ["none", "local", "dgp", "oracle"])
def test_compiled_recording_equals_the_agent_path(paper_sim, mode):
    m = paper_sim
    if mode == "oracle":
        preds = {d.id: TruthPredictor(DuffingParams(**m.target.duffing.model_dump())) for d in m.drones}
    elif mode == "none":
        preds = None
    else:
        preds = _experts(m, {1: 10, 2: 7, 3: 13})
    a, b = _both(m, mode, preds)
    _assert_identical(a, b)
    ev = _compiled_event(a)
    assert ev["ticks"] == a.ticks_done - 1 and ev["python_ticks"] == 1  # tick 0 in Python, the rest compiled
    assert not [e for e in b.events if e.get("event") == "compiled loop"]
    if mode != "none":
        assert np.any(a.mu_used != 0.0)


@pytest.mark.parametrize("rule", ["gpoe", "bcm", "rbcm"])
def test_every_fusion_rule_is_identical(rule):
    m = load_mission("paper_sim", {"duration_s": 0.4, "gp": {**_gp(), "fusion": rule}})
    a, b = _both(m, "dgp", _experts(m, {1: 10, 2: 10, 3: 10}))
    _assert_identical(a, b)
    assert a.n_fused[-1].tolist() == [3, 3, 3]


def _gp() -> dict:
    from flightstack.config.mission import mission_to_dict

    return mission_to_dict(load_mission("paper_sim"))["gp"]


def test_a_tick_the_bus_would_drop_goes_to_python_and_still_matches(paper_sim):
    """Experts predicting more than AcceptanceBounds' 10 m/s: their messages are dropped by the bus; the
    compiled loop hands each such tick to Python, and the recording still matches."""
    m = load_mission("paper_sim", {"duration_s": 2.0})
    preds = _experts(m, {1: 10, 2: 10, 3: 10}, scale=20.0)  # some ticks over the bound, most not
    a, b = _both(m, "dgp", preds)
    assert sum(b.bus_dropped.values()) > 0  # the case happens
    _assert_identical(a, b)
    ev = _compiled_event(a)
    assert ev["python_ticks"] > 1 and ev["ticks"] > CHUNK_TICKS // 2  # both paths flew a good part
    assert ev["ticks"] + ev["python_ticks"] == a.ticks_done


def test_only_the_ideal_rig_is_compiled():
    lab = load_mission("paper_experiment", {"duration_s": 0.1}, rig="lab-sim")
    with assemble_fleet(lab, "none", None, backend=None, bus=None, agent_ids=None, writer=None) as f:
        assert why_not_compiled(f) == "not the ideal rig"
        assert CompiledLoop.plan(f) is None
        f.backend.close()
    square = load_mission("paper_experiment", {"duration_s": 0.1}, rig="ideal")
    with assemble_fleet(square, "none", None, backend=None, bus=None, agent_ids=None, writer=None) as f:
        assert why_not_compiled(f) == "safety layer or target driver present"  # the square law's driver
        f.backend.close()
    sim = load_mission("paper_sim", {"duration_s": 0.1})
    with assemble_fleet(sim, "none", None, backend=None, bus=None, agent_ids=[1, 2], writer=None) as f:
        assert why_not_compiled(f) == "not every drone flies in this process"
        f.backend.close()


def test_ctrl_c_between_chunks_stops_and_keeps_the_flown_ticks():
    m = load_mission("paper_sim", {"duration_s": 4.0})  # 2000 ticks
    seen = []

    def progress(n: int) -> None:
        seen.append(n)
        if len(seen) == 3:  # tick 0, one chunk, then Ctrl-C arrives
            raise KeyboardInterrupt

    rec = fly_mode(m, "none", None, progress)
    assert rec.interrupted
    assert rec.ticks_done == sum(seen) == 1 + 2 * CHUNK_TICKS
    assert np.all(np.diff(rec.t) > 0)
    assert [e for e in rec.events if e.get("event") == "landed"]
