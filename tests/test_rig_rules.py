"""What a rig allows (flightstack/config/rig_rules.py) holds whatever the source of a value: a rig file, an
experiment composed on it, `flightstack run --set` and `flightstack sweep --set`. Safety is off only on
the ideal rig; a fence or speed beyond any lab or Tello is no limit; a value set after the rig tightens
its safety, never loosens it. `--set` values go through the hardened loader, and a mission whose
`drones:` is not a list is named by the schema on every rig (each exits 2 with one line)."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
from pathlib import Path

import pytest
import yaml

from flightstack.cli import app
from flightstack.cli.run import with_sets
from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import MISSION_CONFIGS
from flightstack.config.rig_rules import FENCE, LOOSER_WHEN_LARGER, LOOSER_WHEN_SMALLER, loosened
from flightstack.safety.rules import MAX_FENCE_M, MAX_SPEED_MPS, SafetyLimits
from flightstack.sweep.plan import SweepError, build_plan, parse_grid

SAFE_RIGS = ("lab-sim", "emulated-lab", "lab")
"""The rigs that fly with safety on (`lab` is the real-lab template: everything here is refused before its
preflight, so nothing is sent to its placeholder addresses)."""


def run(tmp_path: Path, capsys: pytest.CaptureFixture[str], rig: str, *sets: str) -> tuple[int, str]:
    """`flightstack run paper_experiment --rig RIG --set ...` in process: (exit code, stderr)."""
    args = ["run", "paper_experiment", "--rig", rig, "--out", str(tmp_path / "run"), "--no-progress"]
    for s in sets:
        args += ["--set", s]
    code = app.main(args)
    return code, capsys.readouterr().err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and "Error:" not in err, err  # no bare exception name
    return lines[0]


# ---- the rules as functions --------------------------------------------------------------------------------
def test_every_direction_table_names_limits_of_safety_limits_once() -> None:
    fields = {f.name for f in dataclasses.fields(SafetyLimits)}
    tables = [*LOOSER_WHEN_LARGER, *LOOSER_WHEN_SMALLER, *FENCE]
    assert set(tables) <= fields and len(tables) == len(set(tables))


def test_loosened_refuses_every_limit_in_its_loose_direction_and_accepts_the_other() -> None:
    rig = {"enabled": True, **dataclasses.asdict(SafetyLimits())}
    assert loosened(rig, rig) == []
    for key in LOOSER_WHEN_LARGER:
        assert loosened(rig, {**rig, key: rig[key] * 2}) == [
            f"safety.{key}: {rig[key] * 2:g} is above the rig's {rig[key]:g}"
        ]
        assert loosened(rig, {**rig, key: rig[key] / 2}) == []
    for key in LOOSER_WHEN_SMALLER:
        assert loosened(rig, {**rig, key: rig[key] / 2}) != []
        assert loosened(rig, {**rig, key: min(100.0, rig[key] * 2)}) == []
    lo, hi = rig["fence_lo"], rig["fence_hi"]
    assert loosened(rig, {**rig, "fence_lo": (lo[0] - 0.1, lo[1], lo[2])}) != []
    assert loosened(rig, {**rig, "fence_hi": (hi[0], hi[1], hi[2] + 0.1)}) != []
    assert loosened(rig, {**rig, "fence_lo": (lo[0] + 1, lo[1], lo[2]), "fence_hi": (1.0, 1.0, 1.5)}) == []
    # a limit in no table is the rig's alone, either way
    flip = not rig["emergency_stop_if_land_fails"]
    assert loosened(rig, {**rig, "emergency_stop_if_land_fails": flip}) != []
    off_now = loosened(rig, {**rig, "enabled": False})
    assert off_now == ["safety.enabled: false (the rig flies with safety on)"]
    off = {**rig, "enabled": False}  # the ideal rig: nothing is looser than safety off
    assert loosened(off, {**rig, "max_speed_xy": 5.0}) == []


# ---- run --set: the rig's rules, on every rig --------------------------------------------------------------
REFUSED = [
    ("safety.enabled=false", "safety.enabled: false only on the ideal rig"),
    ("safety.fence_hi=[1e9,1e9,1e9]", f"within ±{MAX_FENCE_M:g} m"),
    ("safety.fence_lo=[-1e9,-2,0.3]", f"within ±{MAX_FENCE_M:g} m"),
    ("safety.max_speed_xy=1e9", f"max_speed_xy must be at most {MAX_SPEED_MPS:g}"),
    ("safety.max_speed_z=1e9", f"max_speed_z must be at most {MAX_SPEED_MPS:g}"),
    ("safety.hard_margin=1e9", f"within ±{MAX_FENCE_M:g} m"),
    ("safety.fence_hi=[3,2,2]", "safety.fence_hi: [3, 2, 2] is outside the rig's fence ([2, 2, 2])"),
    ("safety.max_speed_xy=0.8", "safety.max_speed_xy: 0.8 is above the rig's 0.5"),
    ("safety.command_timeout=5", "safety.command_timeout: 5 is above the rig's 0.5"),
    ("safety.land_battery=1", "safety.land_battery: 1 is below the rig's 15"),
    ("safety.emergency_stop_if_land_fails=true", "safety.emergency_stop_if_land_fails: the rig's own"),
    ("backend=sim_ideal", "backend"),  # the rig's own, or (a lab) hardware only on backend tello
    ("rig=ideal", "rig: the rig's own ('"),
]


@pytest.mark.parametrize("rig", SAFE_RIGS)
@pytest.mark.parametrize(("set_", "says"), REFUSED, ids=[r[0] for r in REFUSED])
def test_set_may_not_say_what_the_rig_may_not_and_exits_2_naming_the_rule(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], rig: str, set_: str, says: str | None
) -> None:
    if says is None:  # accepted exactly when it changes nothing the rig holds
        before = load_mission("paper_experiment", rig=rig)
        try:
            after = with_sets(before, [set_])
        except MissionError as exc:
            assert "the rig's own" in str(exc)
        else:
            assert after.safety == before.safety and after.start_emulators == before.start_emulators
        return
    code, err = run(tmp_path, capsys, rig, set_)
    assert code == 2, err
    line = one_line(err)
    assert says in line and f"--set {set_}" in line, line
    assert not (tmp_path / "run").exists()  # refused before anything: no run directory, no preflight


@pytest.mark.parametrize("rig", SAFE_RIGS)
def test_set_may_tighten_the_rigs_safety(rig: str) -> None:
    m = load_mission("paper_experiment", rig=rig)
    tight = with_sets(
        m,
        [
            "safety.max_speed_xy=0.3",
            "safety.fence_lo=[-1.5,-1.5,0.4]",
            "safety.fence_hi=[1.5,1.5,1.8]",
            "safety.land_battery=20",
            "safety.command_timeout=0.3",
        ],
    )
    s = tight.safety
    assert (s.max_speed_xy, s.fence_hi, s.land_battery, s.command_timeout) == (0.3, (1.5, 1.5, 1.8), 20, 0.3)
    assert s.enabled and tight.rig == m.rig and tight.backend == m.backend


def test_the_ideal_rig_may_turn_safety_on_but_not_past_a_limits_bounds() -> None:
    m = load_mission("paper_sim", rig="ideal")
    assert not m.safety.enabled
    on = with_sets(m, ["safety.enabled=true", "safety.fence_hi=[50,50,20]", "safety.max_speed_xy=5"])
    assert on.safety.enabled and on.safety.fence_hi == (50.0, 50.0, 20.0)
    with pytest.raises(MissionError, match=f"within ±{MAX_FENCE_M:g} m"):
        with_sets(m, ["safety.enabled=true", "safety.fence_hi=[1e9,1e9,1e9]"])
    with pytest.raises(MissionError, match="backend"):
        with_sets(m, ["backend=sim_lab"])


def test_set_never_changes_which_rig_it_is(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The emulated lab without its emulators would be a real lab on loopback placeholders."""
    code, err = run(tmp_path, capsys, "emulated-lab", "compensation.response_s=0.1", "start_emulators=false")
    assert code == 2 and "start_emulators: the rig's own (True)" in one_line(err)
    code, err = run(tmp_path, capsys, "lab-sim", "start_emulators=true")
    assert code == 2 and "start_emulators: no emulators for backend 'sim_lab'" in one_line(err)


# ---- rig files: the same rules -----------------------------------------------------------------------------
def _rig_copy(tmp_path: Path, name: str, edit) -> Path:
    src = MISSION_CONFIGS / "rigs" / f"{name}.yaml"
    rig = yaml.safe_load(src.read_text())
    for mount, rel in rig.get("cameras", {}).items():  # absolute: the copy lives elsewhere
        rig["cameras"][mount] = str((src.parent / rel).resolve())
    for d in rig.get("drones", []):
        d["camera"] = str((src.parent / d["camera"]).resolve())
    edit(rig)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(rig))
    return path


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda r: r["safety"].update(enabled=False), "safety.enabled: false only on the ideal rig"),
        (lambda r: r["safety"].update(fence_hi=[1e9, 1e9, 1e9]), f"within ±{MAX_FENCE_M:g} m"),
        (lambda r: r["safety"].update(max_speed_xy=1e9), "max_speed_xy must be at most"),
    ],
)
@pytest.mark.parametrize("name", SAFE_RIGS)
def test_a_rig_file_may_not_say_it_either(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, edit, says: str
) -> None:
    path = _rig_copy(tmp_path, name, edit)
    for argv in (["validate", str(path)], ["validate", "paper_experiment", "--rig", str(path)]):
        assert app.main(argv) == 2
        line = one_line(capsys.readouterr().err)
        assert says in line and str(path.name) in line, line


# ---- --set values through the hardened loader --------------------------------------------------------------
ABSURD_SETS = [
    ("gains.k_s=" + "9" * 5000, "--set gains.k_s: line 1: an integer of 5000 digits"),
    ("gains.k_s=" + "[" * 5000 + "]" * 5000, "--set gains.k_s: nested too deeply"),
    ("gains.k_s=" + "[" * 100 + "]" * 100, "nested deeper than 64 levels"),
    ("gains.k_s=" + "{a: " * 5000 + "1" + "}" * 5000, "--set gains.k_s: nested too deeply"),
    ("gains.k_s=&a [*a]", "--set gains.k_s: line 1, 0: anchors and aliases are not allowed"),
    ("a" + ".a" * 5000 + "=1", "a key nested deeper than 64 levels"),
]


@pytest.mark.parametrize(
    ("set_", "says"), ABSURD_SETS, ids=["int", "deep", "deep100", "deepmap", "alias", "key"]
)
def test_absurd_set_values_exit_2_with_one_line_in_run_and_sweep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], set_: str, says: str
) -> None:
    code, err = run(tmp_path, capsys, "lab-sim", set_)
    assert code == 2, err
    assert says in one_line(err)
    if "nested too deeply" in says:  # the pure-Python loader takes ~5 s to refuse it: once is enough
        return
    code = app.main(["sweep", "paper_sim", "--seeds", "1", "--set", set_, "--out", str(tmp_path / "sweep")])
    assert code == 2
    assert says in one_line(capsys.readouterr().err)


def test_a_sweep_may_tighten_the_rigs_safety_but_not_loosen_it() -> None:
    from flightstack.runtime.flight import resolved_mission_yaml

    base_m = load_mission("paper_experiment", rig="lab-sim")
    base = yaml.safe_load(resolved_mission_yaml(base_m))
    plan = build_plan(base, parse_grid(["safety.max_speed_xy=0.3,0.5"]), 1, base_m.resolve("."))
    assert len(plan.combinations) == 2
    for bad, says in [
        ("safety.max_speed_xy=0.3,0.8", "safety.max_speed_xy: 0.8 is above the rig's 0.5"),
        ("safety.enabled=false", "safety.enabled: false only on the ideal rig"),
    ]:
        with pytest.raises(SweepError, match=says):
            build_plan(base, parse_grid([bad]), 1, base_m.resolve("."))


# ---- a mission whose drones are not a list -----------------------------------------------------------------
@pytest.mark.parametrize("value", [3.0, None, "three", {"id": 1}])
@pytest.mark.parametrize("rig", ("ideal", *SAFE_RIGS))
def test_drones_that_are_not_a_list_exit_2_naming_the_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], rig: str, value: object
) -> None:
    exp = yaml.safe_load((MISSION_CONFIGS / "paper_experiment.yaml").read_text())
    exp["drones"] = value
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(exp))
    assert app.main(["validate", str(path), "--rig", rig]) == 2
    line = one_line(capsys.readouterr().err)
    assert str(path) in line and "drones: Input should be a valid list (line" in line, line


ODD = [3.0, None, "x", [1], {"a": 1}]


def test_any_odd_value_of_an_experiment_key_is_a_mission_error_on_every_rig(tmp_path: Path) -> None:
    """Composition never crashes on a value of the wrong type: the schema names it (TypeError was exit 1)."""
    exp = yaml.safe_load((MISSION_CONFIGS / "paper_experiment.yaml").read_text())
    paths: list[tuple[object, ...]] = [(k,) for k in exp] + [("drones", 0)]
    paths += [("drones", 0, k) for k in exp["drones"][0]] + [("target", k) for k in exp["target"]]
    path = tmp_path / "exp.yaml"
    checked = 0
    for where in paths:
        for value in ODD:
            doc = copy.deepcopy(exp)
            node = doc
            for part in where[:-1]:
                node = node[part]
            node[where[-1]] = value
            path.write_text(yaml.safe_dump(doc))
            for rig in ("ideal", *SAFE_RIGS):
                with contextlib.suppress(MissionError):  # anything else fails the test
                    load_mission(path, rig=rig)
                checked += 1
    assert checked == len(paths) * len(ODD) * 4
