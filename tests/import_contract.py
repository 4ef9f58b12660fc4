"""The import contract: which layer of the package may import which, checked from the source.

Reads tests/import_contract.toml (the layers, bottom to top; the named exceptions with their reasons; the
names only one module may import; the third-party packages the math may use) and every module of the
installed package's folders, mapped as pyproject's `package-dir` maps them (`drivers/` is
`flightstack.drivers`, ...). Every import counts: at module level, inside functions, under TYPE_CHECKING.

Breaks reported:
- a cycle between modules (a strongly connected group of the module graph);
- an import of a higher layer, or of a sibling in the same layer (siblings are independent), not named
  as an exception;
- an import of a name reserved to other modules (`[[reserved]]`);
- a third-party import in a layer restricted to named packages (`[restricted]`).

`python tests/import_contract.py` prints every break and exits 1 if there is any; `--graph` also prints
the layer-to-layer imports. tests/test_import_contract.py runs the same check in the unit tier.
"""

from __future__ import annotations

import ast
import sys
import tomllib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONTRACT = Path(__file__).with_name("import_contract.toml")
PACKAGE_DIRS = {
    "flightstack": "flightstack",
    "flightstack.drivers": "drivers",
    "flightstack.calibration": "calibration",
    "flightstack.sim_backend": "sim_backend",
}
"""Import name -> folder, as pyproject's [tool.setuptools.package-dir] (mission_configs/ has no code)."""


@dataclass(frozen=True)
class Import:
    """`importer` imports `imported` (both module names) at `line`; `name`: the imported name, if any."""

    importer: str
    imported: str
    line: int
    name: str = ""


@dataclass
class Graph:
    """Every module of the package (name -> file) and every import between two of them; `external`:
    module -> top-level names of the other packages it imports."""

    modules: dict[str, Path] = field(default_factory=dict)
    imports: list[Import] = field(default_factory=list)
    external: dict[str, set[str]] = field(default_factory=lambda: defaultdict(set))


def module_files(root: Path = ROOT) -> dict[str, Path]:
    """Module name -> file for every .py file under the mapped folders."""
    out: dict[str, Path] = {}
    mapped = {folder for pkg, folder in PACKAGE_DIRS.items() if pkg != "flightstack"}
    for pkg, folder in PACKAGE_DIRS.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = list(path.relative_to(root / folder).with_suffix("").parts)
            if pkg == "flightstack" and parts and parts[0] in mapped:
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([pkg, *parts])] = path
    return out


def _owner(name: str, modules: dict[str, Path]) -> str | None:
    """The module that `name` (a module or a name inside one) lives in, or None outside the package."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def build_graph(root: Path = ROOT) -> Graph:
    """Parse every module and collect its imports (all of them: the whole syntax tree is walked)."""
    g = Graph(modules=module_files(root))
    for mod, path in g.modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    _add(g, mod, alias.name, node.lineno, "")
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                for alias in node.names:
                    full = f"{source}.{alias.name}"
                    target = full if full in g.modules else source
                    _add(g, mod, target, node.lineno, "" if full in g.modules else alias.name)
    return g


def _add(g: Graph, mod: str, target: str, line: int, name: str) -> None:
    owner = _owner(target, g.modules)
    if owner is None:
        top = target.partition(".")[0]
        if top and top != "flightstack":
            g.external[mod].add(top)
    elif owner != mod:
        g.imports.append(Import(mod, owner, line, name))


def cycles(g: Graph) -> list[list[str]]:
    """The groups of modules that import each other (Tarjan's strongly connected components, size > 1)."""
    edges: dict[str, set[str]] = defaultdict(set)
    for imp in g.imports:
        edges[imp.importer].add(imp.imported)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # recursion depth <= number of modules (~200)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(g.modules):
        if v not in index:
            visit(v)
    return groups


@dataclass(frozen=True)
class Contract:
    """layers: bottom to top, each a list of independent siblings (module or package names);
    exceptions: (importer, imported) -> reason; reserved: fully qualified name -> modules allowed to
    import it; restricted: layer -> third-party packages it may import (besides the standard library)."""

    layers: list[list[str]]
    exceptions: dict[tuple[str, str], str]
    reserved: dict[str, list[str]]
    restricted: dict[str, list[str]]
    names: list[str] = field(default_factory=list)
    """Each layer's name, bottom to top (as `layers`)."""

    @classmethod
    def load(cls, path: Path = CONTRACT) -> Contract:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        return cls(
            names=[str(layer["name"]) for layer in data["layer"]],
            layers=[list(layer["members"]) for layer in data["layer"]],
            exceptions={(e["importer"], e["imported"]): e["reason"] for e in data.get("exception", [])},
            reserved={r["name"]: list(r["only"]) for r in data.get("reserved", [])},
            restricted={k: list(v) for k, v in data.get("restricted", {}).items()},
        )

    def place(self, module: str) -> tuple[int, str] | None:
        """(layer index, member) of a module: the longest member name that is the module or its package."""
        best: tuple[int, str] | None = None
        for i, members in enumerate(self.layers):
            for m in members:
                if (module == m or module.startswith(m + ".")) and (best is None or len(m) > len(best[1])):
                    best = (i, m)
        return best


def folder_cycles(g: Graph) -> list[list[str]]:
    """Groups of sibling folders that import each other: in each package below the top level (whose
    folders the layers order), its subpackages and its own modules (its folder, named `pkg/`) are the
    folders. Two folders that import each other are one concept split in two, or two tangled."""
    packages = {m for m, p in g.modules.items() if p.name == "__init__.py"} - {"flightstack"}
    folders = Graph(modules={})
    for imp in g.imports:
        for pkg in packages:
            a, b = _folder_in(pkg, imp.importer, packages), _folder_in(pkg, imp.imported, packages)
            if a is not None and b is not None and a != b:
                folders.modules.setdefault(a, Path()), folders.modules.setdefault(b, Path())
                folders.imports.append(Import(a, b, imp.line, ""))
    return cycles(folders)


def _folder_in(pkg: str, module: str, packages: set[str]) -> str | None:
    """The folder of `pkg` that holds `module` (`pkg/` for pkg's own modules), or None outside pkg."""
    if not module.startswith(pkg + "."):
        return None
    child = pkg + "." + module[len(pkg) + 1 :].split(".")[0]
    return child if child in packages else pkg + "/"


def breaks(g: Graph, c: Contract) -> list[str]:
    """Every break of the contract, one line each (empty: the code keeps the contract)."""
    out = [f"cycle: {' <-> '.join(group)}" for group in cycles(g)]
    out += [f"folder cycle: {' <-> '.join(group)}" for group in folder_cycles(g)]
    out += [f"module in no layer: {m}" for m in sorted(g.modules) if c.place(m) is None]
    used: set[tuple[str, str]] = set()
    seen: set[tuple[str, int, str]] = set()
    for imp in sorted(g.imports, key=lambda i: (i.importer, i.line, i.imported, i.name)):
        a, b = c.place(imp.importer), c.place(imp.imported)
        if a is None or b is None or a[1] == b[1]:
            pass
        elif b[0] > a[0] or (b[0] == a[0] and a[1] != b[1]):
            key = (_member_of(imp.importer, c), _member_of(imp.imported, c))
            exc = next((k for k in c.exceptions if _covers(k, imp)), None)
            if exc is None and (imp.importer, imp.line, imp.imported) not in seen:
                seen.add((imp.importer, imp.line, imp.imported))
                what = "a higher layer" if b[0] > a[0] else "a sibling (siblings are independent)"
                out.append(f"{imp.importer}:{imp.line} imports {imp.imported}: {what} ({key[0]} -> {key[1]})")
            elif exc is not None:
                used.add(exc)
        for name, only in c.reserved.items():
            owner, _, attr = name.rpartition(".")
            if imp.imported == owner and imp.name == attr and imp.importer not in only:
                out.append(f"{imp.importer}:{imp.line} imports {name}: reserved to {', '.join(only)}")
    out += [f"unused exception: {a} -> {b}" for a, b in sorted(set(c.exceptions) - used)]
    for layer, allowed in c.restricted.items():
        for mod, tops in sorted(g.external.items()):
            if mod == layer or mod.startswith(layer + "."):
                bad = sorted(t for t in tops if t not in allowed and t not in sys.stdlib_module_names)
                out += [f"{mod} imports {t}: {layer} may use only {', '.join(allowed)}" for t in bad]
    return out


def _member_of(module: str, c: Contract) -> str:
    placed = c.place(module)
    return placed[1] if placed else module


def _covers(key: tuple[str, str], imp: Import) -> bool:
    """An exception names the importing and the imported module (or package) exactly."""
    importer, imported = key
    return (imp.importer == importer or imp.importer.startswith(importer + ".")) and (
        imp.imported == imported or imp.imported.startswith(imported + ".")
    )


def layer_imports(g: Graph, c: Contract) -> dict[str, set[str]]:
    """Member -> the other members it imports (the layer-to-layer picture)."""
    out: dict[str, set[str]] = defaultdict(set)
    for imp in g.imports:
        a, b = _member_of(imp.importer, c), _member_of(imp.imported, c)
        if a != b:
            out[a].add(b)
    return out


def main(argv: list[str]) -> int:
    g, c = build_graph(), Contract.load()
    if "--graph" in argv:
        for member, targets in sorted(layer_imports(g, c).items()):
            print(f"{member} -> {', '.join(sorted(targets))}")
    found = breaks(g, c)
    print(f"{len(g.modules)} modules, {len(g.imports)} imports, {len(found)} breaks of {CONTRACT.name}")
    for line in found:
        print(f"  {line}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
