"""Mission schema: the shipped missions load; bad files name the key path and the reason."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from flightstack.config.mission import MissionError, load_mission, parse_mission
from flightstack.config.rig import resolved_document
from tests.conftest import MISSIONS, run_cli


def paper() -> dict:
    return resolved_document("paper_sim")


def test_paper_sim_loads_with_the_papers_values() -> None:
    m = load_mission(MISSIONS / "paper_sim.yaml")
    assert len(m.drones) == 3 and m.edge_index_pairs() == [(0, 1), (0, 2), (1, 2)]
    assert m.gains.k_c == [100] * 4 and m.gains.k_e == [100] * 4 and m.gains.k_s == 70
    assert m.gp.noise_var == 0.01 and m.gp.samples_per_region == 10
    assert m.target.initial_pose.p == (-0.3, -1.0, 0.0)
    assert m.compare_modes == ["none", "local", "dgp"]


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["drones"][1]["desired_pose"].update(foo=1), "drones.1.desired_pose.foo: unknown key"),
        (lambda d: d.update(gainz={}), "gainz: unknown key"),
        (lambda d: d["gains"].update(k_c=[1, 2, 3]), "gains.k_c"),
        (lambda d: d["gains"].update(k_s=-1), "gains.k_s"),
        (lambda d: d["gp"].update(fusion="mean"), "unknown fusion rule 'mean'"),
        (lambda d: d.update(compare_modes=["none", "magic"]), "unknown mode 'magic'"),
        (lambda d: d.pop("gains"), "gains: Field required"),
        (
            lambda d: d["drones"][0]["desired_pose"].update(p=[0, 0, -1]),
            "drones.0: desired_pose: the target must be in front of the drone's camera",
        ),
        (lambda d: d["gp"]["regions"].update(edges=[0.5]), "gp.regions.edges: 3 drones need 2 band edges"),
        (lambda d: d["gp"]["regions"].update(edges=[0.5, 0.1]), "strictly increasing"),
        (lambda d: d.update(graph={"kind": "edges", "edges": [[1, 9]]}), "names a drone id"),
        (lambda d: d.update(dt_s="fast"), "dt_s"),
        (lambda d: d.update(duration_s=float("nan")), "duration_s"),
        (lambda d: d["drones"][2].update(id=1), "ids must be unique"),
    ],
)
def test_invalid_missions_name_the_key(mutate, expected: str) -> None:
    d = paper()
    mutate(d)
    with pytest.raises(MissionError) as exc:
        parse_mission(d, "m.yaml")
    assert expected in str(exc.value)
    assert str(exc.value).startswith("m.yaml:")


def test_unreadable_and_non_yaml_files(tmp_path: Path) -> None:
    with pytest.raises(MissionError, match="cannot read"):
        load_mission(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(MissionError, match="not valid YAML"):
        load_mission(bad)
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n- 2\n")
    with pytest.raises(MissionError, match="mapping"):
        load_mission(lst)


def test_cli_reports_invalid_mission_and_writes_nothing(tmp_path: Path) -> None:
    d = paper()
    d["drones"][0]["speed"] = 3
    f = tmp_path / "m.yaml"
    f.write_text(yaml.safe_dump(d))
    out = tmp_path / "run"
    r = run_cli("sim", str(f), "--out", str(out), timeout=60)
    assert r.returncode == 2
    assert "drones.0.speed: unknown key" in r.stderr
    assert not out.exists()
