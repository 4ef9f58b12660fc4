"""The n-drone mission generator: flightstack.config.generate and `flightstack generate-mission`.

Unit tier (tests/conftest.py): pure functions, one in-process 0.05 s flight, the CLI called in-process.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from flightstack.cli.app import main
from flightstack.config.generate import (
    MAX_K_DT,
    GenerateError,
    generate,
    mission_lambda_max,
    n_drone_mission,
    ring_lambda_max,
    target_path_range,
    to_mission,
)
from flightstack.config.mission import Mission, load_mission
from flightstack.paper.gain_analysis import laplacian
from tests.conftest import MISSIONS


def paper() -> Mission:
    return load_mission("paper_sim")


def numpy_lambda_max(m: Mission) -> float:
    """λ_max of the mission's Laplacian, by numpy from its edges (independent of the generator's)."""
    return float(np.linalg.eigvalsh(laplacian(len(m.drones), m.edge_index_pairs()))[-1])


def fastest_k_dt(m: Mission) -> float:
    return (max(*m.gains.k_c, *m.gains.k_e) + m.gains.k_s * numpy_lambda_max(m)) * m.dt_s


def test_three_drones_reproduce_paper_sim() -> None:
    base, m = paper(), to_mission(n_drone_mission(3))
    assert [d.id for d in m.drones] == [d.id for d in base.drones] == [1, 2, 3]
    for d, b in zip(m.drones, base.drones, strict=True):
        assert d.desired_pose.p == pytest.approx(b.desired_pose.p, abs=1e-3)  # the file rounds to mm
        assert d.desired_pose.theta == b.desired_pose.theta == 0.0
    assert m.graph.kind == base.graph.kind == "complete"
    assert m.edge_index_pairs() == base.edge_index_pairs()
    assert m.gains.k_c == base.gains.k_c and m.gains.k_e == base.gains.k_e
    assert m.gains.k_s == pytest.approx(70.0, rel=1e-12)
    assert m.gp.regions.axis == "x"
    assert m.gp.regions.edges == pytest.approx(base.gp.regions.edges, abs=1e-9)  # [-0.7, 0.6]
    assert m.gp.samples_per_region == base.gp.samples_per_region
    assert (m.target, m.dt_s, m.duration_s, m.rig, m.backend) == (
        base.target,
        base.dt_s,
        base.duration_s,
        "ideal",
        "sim_ideal",
    )


def test_paper_sim_band_range_is_its_target_paths() -> None:
    """The range split into bands: paper_sim's target path over 40 s spans x ≈ [−2.02, 1.89] m."""
    g = generate(3)
    lo, hi = target_path_range(paper().target, 40.0, 0.002, "x")
    assert (lo, hi) == pytest.approx(g.path_range_m)
    assert -2.05 < lo < -1.95 and 1.85 < hi < 1.95
    assert g.band_range_m == (-2.0, 1.9)


def test_eleven_drones_circle_bands_and_consensus_gain() -> None:
    base, m = paper(), to_mission(n_drone_mission(11))
    assert [d.id for d in m.drones] == list(range(1, 12))
    p = np.array([d.desired_pose.p for d in m.drones])
    assert np.hypot(p[:, 0], p[:, 1]) == pytest.approx(np.full(11, 0.5), abs=2e-6)
    assert np.all(p[:, 2] == 1.5)
    phi = np.sort(np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * math.pi))
    assert np.diff(phi) == pytest.approx(np.full(10, 2 * math.pi / 11), abs=1e-5)  # distinct, evenly spaced
    edges = np.array(m.gp.regions.edges)
    assert edges.size == 10 and np.all(np.diff(edges) > 0)
    width = np.diff([-2.0, *edges, 1.9])  # 11 bands covering [-2.0, 1.9] m, each of equal width
    assert width == pytest.approx(np.full(11, 3.9 / 11), abs=2e-6)
    assert m.gp.samples_per_region == base.gp.samples_per_region
    assert m.gains.k_s * numpy_lambda_max(m) == pytest.approx(base.gains.k_s * numpy_lambda_max(base))
    assert m.gains.k_s == pytest.approx(70 * 3 / 11)
    assert fastest_k_dt(m) <= MAX_K_DT * (1 + 1e-9)


@pytest.mark.parametrize("n", [3, 4, 5, 8, 11, 31])
def test_ring_lambda_max_matches_numpy(n: int) -> None:
    m = to_mission(n_drone_mission(n, graph="ring"))
    assert m.graph.kind == "edges"
    assert all(len(m.neighbours(k)) == 2 for k in range(n))
    assert len(m.edge_index_pairs()) == n
    assert ring_lambda_max(n) == pytest.approx(numpy_lambda_max(m), abs=1e-12)
    assert mission_lambda_max(m) == pytest.approx(numpy_lambda_max(m), abs=1e-12)
    assert m.gains.k_s * numpy_lambda_max(m) == pytest.approx(70 * 3)
    assert fastest_k_dt(m) <= MAX_K_DT * (1 + 1e-9)


def test_an_unstable_consensus_gain_is_refused() -> None:
    # paper_sim's k_s = 70 unscaled on 11 drones: (100 + 70·11)·0.002 = 1.74 > 0.62
    with pytest.raises(GenerateError, match=r"stability: .* exceeds 0.62.*largest k_s that passes is 19.09"):
        n_drone_mission(11, k_s=70.0)
    reduced = generate(11, k_s=70.0, reduce_k_s=True)
    assert reduced.k_s_reduced and reduced.k_s == pytest.approx(210 / 11)
    assert fastest_k_dt(to_mission(reduced.doc)) == pytest.approx(MAX_K_DT)
    # k·dt alone exceeds the bound: no k_s helps
    with pytest.raises(GenerateError, match="even without consensus"):
        n_drone_mission(11, dt_s=0.01, reduce_k_s=True)
    # a longer dt with the scaled gain: refused, not silently flown
    with pytest.raises(GenerateError, match="stability"):
        n_drone_mission(11, dt_s=0.003)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n": 1}, "n must be an integer in 2..1000"),
        ({"n": 3, "graph": "star"}, "unknown kind 'star'"),
        ({"n": 2, "graph": "ring"}, "a ring needs at least 3 drones"),
        ({"n": 3, "radius_m": 0.0}, "radius_m"),
        ({"n": 3, "base": "paper_experiment"}, "the base's drones have cameras"),
        ({"n": 3, "base": "no_such_experiment"}, "not a built-in experiment"),
    ],
)
def test_bad_requests_are_refused(kwargs: dict, match: str) -> None:
    rest = {k: v for k, v in kwargs.items() if k != "n"}
    with pytest.raises(GenerateError, match=match):
        n_drone_mission(kwargs["n"], **rest)


def test_eleven_drones_fly_a_short_run() -> None:
    from tests.conftest import fly_mode

    m = to_mission(n_drone_mission(11), duration_s=0.05)
    rec = fly_mode(m, "none")
    assert rec.error is None and not rec.interrupted
    assert rec.drone_ids == list(range(1, 12)) and rec.g_wi.shape[1] == 11
    assert rec.ticks_done == round(0.05 / m.dt_s)
    assert np.all(np.isfinite(rec.g_wi[: rec.ticks_done]))


def test_cli_writes_a_loadable_file_and_refuses_to_overwrite(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "m11.yaml"
    assert main(["generate-mission", "--drones", "11", "--out", str(out)]) == 0
    m = load_mission(out)
    assert len(m.drones) == 11 and m.name == "paper_sim_complete_11"
    assert m.gains.k_s == pytest.approx(210 / 11)
    text = out.read_text()
    assert text.startswith("# Generated by `flightstack generate-mission --drones 11 --graph complete")
    assert main(["validate", str(out)]) == 0
    capsys.readouterr()
    out.write_text(text + "# edited\n")
    assert main(["generate-mission", "--drones", "5", "--out", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert out.read_text() == text + "# edited\n"  # untouched
    assert main(["generate-mission", "--drones", "5", "--graph", "ring", "--out", str(out), "--force"]) == 0
    assert len(load_mission(out).drones) == 5 and load_mission(out).graph.kind == "edges"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m11.yaml"]  # no temporary file left behind


def test_cli_stdout_and_refusal(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["generate-mission", "--drones", "4"]) == 0
    doc = yaml.safe_load(capsys.readouterr().out)
    assert len(doc["drones"]) == 4 and to_mission(doc).gains.k_s == pytest.approx(52.5)
    assert main(["generate-mission", "--drones", "11", "--k-s", "70"]) == 2
    assert "largest k_s that passes" in capsys.readouterr().err


@pytest.mark.parametrize("n", [11, 31])
def test_shipped_scaling_files_are_the_generators_output(n: int, capsys: pytest.CaptureFixture[str]) -> None:
    """mission_configs/scaling_N.yaml is exactly what its header's command prints, and loads by name."""
    shipped = (MISSIONS / f"scaling_{n}.yaml").read_text()
    command = shipped.splitlines()[0].removeprefix("# Generated by `").removesuffix("`")
    assert (
        command
        == f"flightstack generate-mission --drones {n} --graph complete --base paper_sim --name scaling_{n}"
    )
    assert main(command.split()[1:]) == 0
    assert capsys.readouterr().out == shipped
    m = load_mission(f"scaling_{n}")
    assert m.name == f"scaling_{n}" and len(m.drones) == n and m.gains.k_s == pytest.approx(210 / n)
    assert main(["validate", f"scaling_{n}"]) == 0
