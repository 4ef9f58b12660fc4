"""The import contract (tests/import_contract.toml) holds for the package, and its checker finds each kind
of break it promises to find: on a small package written here, not on the real one."""

from __future__ import annotations

from pathlib import Path

from tests.import_contract import CONTRACT, Contract, breaks, build_graph, cycles, folder_cycles


def test_the_package_keeps_its_import_contract() -> None:
    g, c = build_graph(), Contract.load()
    found = breaks(g, c)
    assert not found, "\n".join(found)
    # the package-dir mapping is seen: the mapped folders are in the graph, under their import names
    assert {"flightstack.drivers.tello", "flightstack.sim_backend.lab", "flightstack.calibration.cli"} <= set(
        g.modules
    )


def _package(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def _contract(root: Path, text: str) -> Contract:
    (root / "contract.toml").write_text(text)
    return Contract.load(root / "contract.toml")


LAYERS = """
[[layer]]
name = "math"
members = ["flightstack.paper"]
[[layer]]
name = "middle"
members = ["flightstack.a", "flightstack.b"]
[[layer]]
name = "top"
members = ["flightstack.drivers"]
[[layer]]
name = "package"
members = ["flightstack"]
[restricted]
"flightstack.paper" = ["numpy"]
"""


MATH = "import numpy\nimport yaml\ndef f():\n    from flightstack.drivers import dev\n"
A = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from flightstack import b\n"
B = "from flightstack.paper.math import f\nfrom flightstack.drivers.dev import secret\n"
RESERVED = '[[reserved]]\nname = "flightstack.drivers.dev.secret"\nonly = ["flightstack.drivers.other"]\n'


def test_the_checker_finds_cycles_upward_and_sibling_imports_reserved_names_and_foreign_packages(
    tmp_path: Path,
) -> None:
    _package(
        tmp_path,
        {
            "flightstack/__init__.py": "",
            "flightstack/paper/__init__.py": "",
            # upward, inside a function, to a folder mapped by package-dir (drivers/ -> flightstack.drivers)
            "flightstack/paper/math.py": MATH,
            "flightstack/a.py": A,
            "flightstack/b.py": B,
            "drivers/__init__.py": "",
            "drivers/dev.py": "from . import other\nsecret = 1\n",
            "drivers/other.py": "from .dev import secret\n",
        },
    )
    c = _contract(
        tmp_path,
        LAYERS
        + '[[reserved]]\nname = "flightstack.drivers.dev.secret"\nonly = ["flightstack.drivers.other"]\n',
    )
    g = build_graph(tmp_path)
    assert cycles(g) == [["flightstack.drivers.dev", "flightstack.drivers.other"]]  # relative imports
    found = breaks(g, c)
    assert "cycle: flightstack.drivers.dev <-> flightstack.drivers.other" in found
    assert any(
        b.startswith("flightstack.paper.math:4 imports flightstack.drivers.dev: a higher layer")
        for b in found
    )
    assert any(
        b.startswith("flightstack.a:3 imports flightstack.b: a sibling") for b in found
    )  # TYPE_CHECKING
    assert (
        "flightstack.b:2 imports flightstack.drivers.dev.secret: reserved to flightstack.drivers.other"
        in found
    )
    assert "flightstack.paper.math imports yaml: flightstack.paper may use only numpy" in found
    assert not any("numpy" in b and "yaml" not in b for b in found)  # allowed, and the standard library too


def test_a_named_exception_silences_exactly_its_import_and_an_unused_one_is_a_break(tmp_path: Path) -> None:
    _package(
        tmp_path,
        {
            "flightstack/__init__.py": "",
            "flightstack/paper/__init__.py": "from flightstack import a\n",
            "flightstack/a.py": "",
            "flightstack/b.py": "",
        },
    )
    exception = '[[exception]]\nimporter = "{0}"\nimported = "{1}"\nreason = "because"\n'
    c = _contract(
        tmp_path,
        LAYERS
        + exception.format("flightstack.paper", "flightstack.a")
        + exception.format("flightstack.b", "flightstack.paper"),
    )
    assert breaks(build_graph(tmp_path), c) == ["unused exception: flightstack.b -> flightstack.paper"]


def test_the_contract_names_a_reason_for_every_exception() -> None:
    c = Contract.load(CONTRACT)
    assert all(len(reason.split()) >= 5 for reason in c.exceptions.values())


def test_every_package_of_the_source_is_one_the_wheel_ships() -> None:
    """A package folder missing from pyproject's `packages` list imports from the checkout and is absent
    from the installed wheel (and from the type check, which runs on the installed tree)."""
    import tomllib

    from tests.import_contract import ROOT, module_files

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    packages = {m for m, path in module_files().items() if path.name == "__init__.py"}
    assert packages - listed == set()


def test_the_checker_finds_folders_that_import_each_other(tmp_path: Path) -> None:
    """Two modules in different folders of one package (not a module cycle) still tie the folders."""
    _package(
        tmp_path / "drivers",
        {
            "__init__.py": "",
            "shared.py": "from flightstack.drivers.dev.radio import x\n",
            "dev/__init__.py": "",
            "dev/radio.py": "x = 1\n",
            "dev/link.py": "from flightstack.drivers import helpers\n",
            "helpers.py": "",
        },
    )
    (tmp_path / "flightstack").mkdir()
    (tmp_path / "flightstack" / "__init__.py").write_text("")
    g = build_graph(tmp_path)
    assert not cycles(g)  # no module imports itself back
    assert folder_cycles(g) == [["flightstack.drivers.dev", "flightstack.drivers/"]]
