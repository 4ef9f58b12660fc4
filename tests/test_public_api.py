"""The declared API: `flightstack.__all__` names what a script may import, each name resolves to
the object its module defines, `import flightstack` loads none of them until asked, and no module of the
package imports another module's private name."""

from __future__ import annotations

import ast
import subprocess
import sys

import flightstack
from tests.conftest import REPO

PRODUCT = ("flightstack", "drivers", "sim_backend", "calibration", "benchmarks")


def test_every_public_name_is_declared_once_and_resolves_to_its_module() -> None:
    assert sorted(flightstack.__all__) == sorted(flightstack.API) and len(set(flightstack.__all__)) == len(
        flightstack.__all__
    )
    for name, module in flightstack.API.items():
        obj = getattr(flightstack, name)
        assert getattr(sys.modules[module], name) is obj, name
        assert getattr(obj, "__module__", module) == module, f"{name} is defined in {obj.__module__}"
        assert (obj.__doc__ or "").strip(), f"{name} has no docstring for the API reference"


def test_importing_the_package_loads_nothing_until_a_name_is_asked_for() -> None:
    code = (
        "import sys, flightstack; before = {m for m in sys.modules if m.startswith('flightstack.')}; "
        "flightstack.Flight; after = {m for m in sys.modules if m.startswith('flightstack.')}; "
        "print(len(before), 'flightstack.runtime.flight' in after)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    loaded, flight_loaded = out.stdout.split()
    assert (int(loaded), flight_loaded) == (0, "True"), out.stdout + out.stderr


def test_an_unknown_name_is_an_attribute_error_naming_it() -> None:
    try:
        flightstack.nosuch  # noqa: B018
    except AttributeError as exc:
        assert "nosuch" in str(exc)
    else:
        raise AssertionError("flightstack.nosuch resolved")


def private_imports(source: str) -> list[tuple[int, str]]:
    """(line, name) of each private name (`_x`, not `__x__`) imported from another flightstack module."""
    return [
        (node.lineno, alias.name)
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("flightstack")
        for alias in node.names
        if alias.name.startswith("_") and not alias.name.startswith("__")
    ]


def test_no_module_imports_another_modules_private_name() -> None:
    assert private_imports("from flightstack.paper.gp_kernel import _pairwise_sq_diff, lml\n") == [
        (1, "_pairwise_sq_diff")
    ]
    files = [p for top in PRODUCT for p in sorted((REPO / top).rglob("*.py"))]
    found = [
        f"{p.relative_to(REPO)}:{line}: {name}"
        for p in files
        for line, name in private_imports(p.read_text())
    ]
    assert not found, "make the name public in its module, or move the caller:\n" + "\n".join(found)


def test_the_api_reference_lists_every_public_name() -> None:
    page = (REPO / "docs" / "api" / "index.md").read_text()
    missing = [name for name in flightstack.__all__ if f"`{name}`" not in page]
    assert not missing, (
        f"docs/api/index.md does not list {missing} (python3 docs/hooks/generated.py --update)"
    )
