"""The rig is an object: a new rig is one module and one line of the registry, and no module but
the registry and the rigs themselves decides anything by a rig's or backend's name."""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.config import rigs
from flightstack.config.links import LINKS, PROFILES
from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import MISSION_CONFIGS
from flightstack.recording.timeseries import ARRAY_FIELDS, MACHINE_FIELDS
from tests.conftest import REPO, fly_mode

# ---- a rig added in one file and one registry line ------------------------------------------------------
COPIES = {  # the built-in rig copied -> its class, and the experiment it flies
    "ideal": ("flightstack.sim_backend.rigs.ideal", "IdealRig", "paper_sim"),
    "lab-sim": ("flightstack.sim_backend.rigs.lab_sim", "LabSimRig", "paper_experiment"),
}


def _add_rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, of: str) -> Path:
    """A new rig `copy_<of>`: its module (one file, a copy of the built-in rig under a new name), its line
    in the registry, and a rig file naming it (the built-in rig file with the new backend)."""
    module, cls, _ = COPIES[of]
    backend = "copy_" + of.replace("-", "_")
    (tmp_path / f"{backend}.py").write_text(
        textwrap.dedent(f"""
        from {module} import {cls}

        class CopiedRig({cls}):
            name = "{backend}"

        RIG = CopiedRig()
        """)
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(rigs.RIGS, backend, f"{backend}:RIG")  # the one registry line
    src = MISSION_CONFIGS / "rigs" / f"{of}.yaml"
    doc = yaml.safe_load(src.read_text())
    for mount, rel in doc.get("cameras", {}).items():  # absolute: the copy lives elsewhere
        doc["cameras"][mount] = str((src.parent / rel).resolve())
    doc.update(rig=backend, backend=backend)
    path = tmp_path / f"{backend}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize("of", sorted(COPIES))
def test_a_rig_added_in_one_file_and_one_line_flies_as_the_rig_it_copies(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, of: str
) -> None:
    experiment = COPIES[of][2]
    copy_file = _add_rig(tmp_path, monkeypatch, of)
    short = {"duration_s": 4.0}
    mission = load_mission(experiment, short, rig=copy_file)
    original = load_mission(experiment, short, rig=of)
    assert mission.backend == f"copy_{of.replace('-', '_')}" and mission.rig_type.name == mission.backend
    assert type(mission.rig_type).__mro__[1] is type(original.rig_type)
    flown, reference = fly_mode(mission, "none"), fly_mode(original, "none")
    assert flown.ticks_done == reference.ticks_done == mission.n_ticks
    fields = [f for f in ARRAY_FIELDS if f not in MACHINE_FIELDS]  # the machine's clock differs
    differing = [f for f in fields if not np.array_equal(getattr(flown, f), getattr(reference, f), True)]
    assert not differing, f"the copy flies differently from {of}: {differing}"
    print(f"{of} copied: {flown.ticks_done} ticks, {len(fields)} arrays bit-identical")


def test_a_backend_not_in_the_registry_is_named_with_what_is_known(tmp_path: Path) -> None:
    doc = yaml.safe_load((MISSION_CONFIGS / "rigs" / "ideal.yaml").read_text())
    doc.update(rig="nosuch", backend="crazyflie")
    path = tmp_path / "nosuch.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(
        MissionError, match="backend: must be one of sim_ideal, sim_lab, tello, got 'crazyflie'"
    ):
        load_mission("paper_sim", rig=path)
    doc.update(backend="sim_lab", emulated={"video_fps": 30.0})
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(MissionError, match="emulated: no emulators for backend 'sim_lab'"):
        load_mission("paper_experiment", rig=path)


# ---- nothing but the registry and the rigs keys on a rig's name -----------------------------------------
BACKEND_NAMES = frozenset(rigs.RIGS)
RIG_FILE_NAMES = frozenset(p.stem for p in (MISSION_CONFIGS / "rigs").glob("*.yaml"))
UNAMBIGUOUS = BACKEND_NAMES - set(PROFILES) - set(LINKS)
"""Backend names that name nothing else (not a link, link kind or links profile)."""
PRODUCT = ("flightstack", "drivers", "sim_backend", "calibration", "benchmarks")
RIG_HOMES = ("flightstack/config/rigs.py", "sim_backend/rigs/", "drivers/lab/rig.py")
"""The registry and the rigs: the only places a rig's name may decide anything."""


def _mentions_rig(node: ast.AST) -> bool:
    """The expression reads a backend or a rig (`mission.backend`, `r.get("backend")`, `rig`, ...)."""
    for n in ast.walk(node):
        if isinstance(n, ast.Name) and n.id in ("backend", "rig"):
            return True
        if isinstance(n, ast.Attribute) and n.attr in ("backend", "rig"):
            return True
        if isinstance(n, ast.Constant) and n.value in ("backend", "rig"):
            return True
    return False


def _names_in(node: ast.AST, names: frozenset[str]) -> list[str]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and n.value in names]


def keyed_by_rig_name(source: str) -> list[tuple[int, str]]:
    """(line, what) for each comparison, membership test or mapping keyed by a rig's or backend's name: a
    comparison with a backend name no other vocabulary uses (UNAMBIGUOUS), or with any backend or rig
    file's name where it reads a backend or rig; a collection of UNAMBIGUOUS names; a lookup keyed by a
    backend. (`tello` is also a link and a profile: compared with something else, it is not a rig.)"""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            names = _names_in(node, UNAMBIGUOUS)
            if not names and any(_mentions_rig(o) for o in [node.left, *node.comparators]):
                names = _names_in(node, BACKEND_NAMES | RIG_FILE_NAMES)
            if names:
                found.append((node.lineno, f"compares with {', '.join(names)}"))
        elif isinstance(node, (ast.Dict, ast.Set, ast.List, ast.Tuple)):
            keys = node.keys if isinstance(node, ast.Dict) else node.elts
            names = [k.value for k in keys if isinstance(k, ast.Constant) and k.value in UNAMBIGUOUS]
            if names:
                found.append((node.lineno, f"a mapping or collection of {', '.join(names)}"))
        elif _is_backend(_lookup_key(node)):
            found.append((node.lineno, "a lookup keyed by the backend"))
    return sorted(found)


def _lookup_key(node: ast.AST) -> ast.AST | None:
    """The key of `x[key]` or `x.get(key, ...)`; None for anything else."""
    if isinstance(node, ast.Subscript):
        return node.slice
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get":
        return node.args[0] if node.args else None
    return None


def _is_backend(node: ast.AST | None) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr == "backend") or (
        isinstance(node, ast.Name) and node.id == "backend"
    )


def test_the_check_finds_each_way_of_keying_on_a_rig_name() -> None:
    """The checker itself: every shape it must catch is caught, and what is not about rigs is not."""
    caught = keyed_by_rig_name(
        textwrap.dedent("""
        a = mission.backend == "sim_ideal"
        b = r.get("backend") != "tello"
        c = mission.backend in Z_DOWN
        Z_DOWN = frozenset({"sim_ideal"})
        LOOPS = {"sim_lab": "module:attr"}
        d = args.rig == "lab-sim"
        e = LOOPS[mission.backend]
        f = LOOPS.get(mission.backend)
        """)
    )
    assert [line for line, _ in caught] == [2, 3, 5, 6, 7, 8, 9]
    assert not keyed_by_rig_name('link = "tello"\nok = kind == "tello"\nsource = {"tello": 1}\nrig = "lab"\n')


def test_nothing_outside_the_registry_and_the_rigs_keys_on_a_rig_name() -> None:
    found = []
    files = [p for top in PRODUCT for p in sorted((REPO / top).rglob("*.py"))]
    for path in files:
        rel = path.relative_to(REPO).as_posix()
        if rel.startswith(RIG_HOMES):
            continue
        found += [f"{rel}:{line}: {what}" for line, what in keyed_by_rig_name(path.read_text())]
    assert len(files) > 250
    assert not found, "ask the rig (flightstack.config.rigs.RigFacts), not its name:\n" + "\n".join(found)
