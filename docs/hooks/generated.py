"""The parts of the manual that a command or a constant already states: rendered into the pages, and again
when the site is built (an MkDocs hook).

A page holds one as a block between the lines `<!-- generated: NAME -->` and `<!-- /generated: NAME -->`.
The committed block is what a reader sees on a code host; `python3 docs/hooks/generated.py --update`
rewrites every block from the installed package, and `tests/test_generated_pages.py` (unit tier) fails
when one is stale. At build time `on_page_markdown` renders each block afresh, so the site is always the
installed version's. The blocks:

- `cli`: every subcommand of `flightstack.cli.app.build_parser()`, its usage and its options;
- `run-files`: `flightstack.recording.files.RUN_FILES`, `REQUIRED_FILES` and `OPTIONAL_FILES`;
- `event-kinds`: every kind of `flightstack.events.KINDS` with the sources that report it, its severity
  and its meaning;
- `fault-rows`: the rows of `flightstack.faults.FAULTS`, in table order, with the fault each injects
  (the row function's docstring) and the reaction documented for it in `fault_reactions.yml`;
- `import-contract`: the layers of `tests/import_contract.toml`, top first, with what each may import and
  the contract's named exceptions and reserved names (tests/import_contract.py checks the code against it).

An unknown NAME, or a block without its closing line, fails the build and the update.
"""

from __future__ import annotations

import argparse
import inspect
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

OPEN = re.compile(r"^<!-- generated: ([a-z-]+) -->$", re.MULTILINE)
BLOCK = re.compile(
    r"^<!-- generated: ([a-z-]+) -->\n(.*?)^<!-- /generated: \1 -->$", re.MULTILINE | re.DOTALL
)
DOCS = Path(__file__).resolve().parents[1]
WIDTH = 100


def _cell(text: str) -> str:
    """One markdown table cell: one line, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _first_paragraph(doc: str | None) -> str:
    return " ".join((inspect.cleandoc(doc or "").split("\n\n") or [""])[0].split())


# ---- the CLI reference ------------------------------------------------------------------------------------
def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each direct subcommand, in the parser's order."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            out += [(name, helps.get(name, ""), sp) for name, sp in action.choices.items()]
    return out


def _usage(parser: argparse.ArgumentParser) -> str:
    fmt = argparse.HelpFormatter(parser.prog, width=WIDTH)
    fmt.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups, prefix="")
    return fmt.format_help().strip()


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    fmt = argparse.HelpFormatter(parser.prog, width=WIDTH)
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.help == argparse.SUPPRESS:
            continue
        if action.option_strings:
            metavar = "" if action.nargs == 0 else " " + fmt._format_args(action, action.dest.upper())
            name = ", ".join(f"{s}{metavar}" for s in action.option_strings)
        else:
            name = fmt._metavar_formatter(action, action.dest)(1)[0]
        help_text = fmt._expand_help(action) if action.help else ""
        default = action.default
        hidden = default in (None, False, argparse.SUPPRESS) or action.nargs == 0
        shown = "" if hidden else f"`{_default(default)}`"
        if action.choices is not None and not isinstance(action.choices, dict) and action.metavar:
            help_text += f" (one of: {', '.join(map(str, action.choices))})"
        rows.append(f"| `{_cell(name)}` | {_cell(help_text)} | {shown} |")
    return rows


def _default(value: object) -> object:
    """A default as a reader's checkout names it: a file of the package's data relative to its folder
    (`mission_configs/paper_experiment.yaml`), not this machine's absolute path."""
    if isinstance(value, (str, Path)) and Path(value).is_absolute():
        from flightstack import mission_configs

        data = Path(next(iter(mission_configs.__path__))).resolve()
        path = Path(value).resolve()
        if path.is_relative_to(data):
            return f"mission_configs/{path.relative_to(data).as_posix()}"
    return value


def _command_section(path: list[str], help_line: str, parser: argparse.ArgumentParser, level: int) -> str:
    parts = [f"{'#' * level} {' '.join(path)}", ""]
    if help_line:
        parts += [help_line[0].upper() + help_line[1:] + ("" if help_line.endswith(".") else "."), ""]
    if parser.description and parser.description.strip() != help_line.strip():
        desc = inspect.cleandoc(parser.description)
        parts += ["```text", desc, "```", ""] if "\n" in desc else [desc, ""]
    parts += ["```text", _usage(parser), "```", ""]
    rows = _option_rows(parser)
    if rows:
        parts += ["| argument | what | default |", "|---|---|---|", *rows, ""]
    for name, sub_help, sub in _subcommands(parser):
        parts.append(_command_section([*path, name], sub_help, sub, min(level + 1, 4)))
    return "\n".join(parts)


def render_cli() -> str:
    """Every subcommand of `flightstack`, as the installed parser defines it."""
    from flightstack.cli.app import build_parser

    parser = build_parser()
    parts = ["```text", _usage(parser), "```", "", "| argument | what | default |", "|---|---|---|"]
    parts += [*_option_rows(parser), ""]
    for name, help_line, sub in _subcommands(parser):
        parts.append(_command_section([parser.prog, name], help_line, sub, 2))
    return "\n".join(parts)


# ---- the run directory ------------------------------------------------------------------------------------
def render_run_files() -> str:
    """The names a run writes and what each reader needs, from flightstack.recording.files."""
    from flightstack.recording import files

    lines = ["| name (pattern) a run writes |", "|---|"]
    lines += [f"| `{_cell(name)}` |" for name in files.RUN_FILES]
    lines += ["", "| required by `report`, `export`, `view` | why |", "|---|---|"]
    lines += [f"| `{_cell(k)}` | {_cell(v)} |" for k, v in files.REQUIRED_FILES.items()]
    lines += ["", "| optional (skipped when damaged) | without it |", "|---|---|"]
    lines += [f"| `{_cell(k)}` | {_cell(v)} |" for k, v in files.OPTIONAL_FILES.items()]
    return "\n".join(lines) + "\n"


# ---- the event kinds ------------------------------------------------------------------------------------
def render_event_kinds() -> str:
    """Every declared event kind, in declaration order: who reports it (the per-source Literals of
    flightstack.events), its severity and its meaning."""
    from typing import get_args

    from flightstack import events

    per_source = {
        "safety": events.SafetyKind,
        "run": events.RunKind,
        "bus": events.BusKind,
        "tello": events.TelloKind,
        "mocap": events.MocapKind,
        "scamper": events.ScamperKind,
        "lab": events.LabKind,
        "world": events.WorldKind,
    }
    sources = {k: [s for s, lit in per_source.items() if k in get_args(lit)] for k in events.KINDS}
    lines = ["| kind | source | severity | meaning |", "|---|---|---|---|"]
    for kind, info in events.KINDS.items():
        lines.append(f"| `{kind}` | {', '.join(sources[kind])} | {info.severity} | {_cell(info.meaning)} |")
    return "\n".join(lines) + "\n"


# ---- the fault table ------------------------------------------------------------------------------------
REACTIONS = Path(__file__).with_name("fault_reactions.yml")
WHERE = {
    "rows_sim": "simulated lab",
    "rows_cli": "simulated lab, through the CLI",
    "rows_processes": "agent processes (Zenoh)",
    "rows_lab_bus": "Zenoh on loopback",
    "rows_robot_preflight": "preflight, a MAVLink-spec rover on loopback",
}
"""Where a row flies, by its module (the other modules fly the emulated lab)."""
CONSTANT = re.compile(r"\b[A-Z][A-Z0-9_]{2,}\b")


def _fault(fn: Callable[..., Any]) -> str:
    """The row function's docstring, its module's numeric constants given their values."""
    module = inspect.getmodule(fn)

    def value(match: re.Match[str]) -> str:
        v = getattr(module, match.group(0), None)
        ok = isinstance(v, (int, float)) and not isinstance(v, bool)
        return f"{match.group(0)} (= {v:g})" if ok else match.group(0)

    return CONSTANT.sub(value, _first_paragraph(fn.__doc__))


def render_fault_rows() -> str:
    """Every row of `flightstack faults`, in table order: the fault it injects (the row function's
    docstring) and the reaction documented in fault_reactions.yml (a name there that is not a row fails)."""
    from flightstack.faults import FAULTS

    reactions: dict[str, str] = yaml.safe_load(REACTIONS.read_text(encoding="utf-8"))
    unknown = sorted(set(reactions) - set(FAULTS))
    if unknown:
        raise ValueError(f"{REACTIONS.name}: not rows of flightstack.faults.FAULTS: {', '.join(unknown)}")
    lines = ["| row | where it flies | fault | reaction (measured in one run) |", "|---|---|---|---|"]
    for name, fn in FAULTS.items():
        where = WHERE.get(fn.__module__.rsplit(".", 1)[-1], "emulated lab")
        reaction = reactions.get(name, f"not documented: `flightstack faults --only {name} --expected`")
        lines.append(f"| `{name}` | {where} | {_cell(_fault(fn))} | {_cell(reaction)} |")
    return "\n".join(lines) + "\n"


def render_import_contract() -> str:
    """The contract's layers (top first): members, what they may import and what they do import today
    (from the source, by tests/import_contract.py); then the named exceptions and reserved names."""
    import importlib.util

    path = Path(__file__).parents[2] / "tests" / "import_contract.py"
    spec = importlib.util.spec_from_file_location("import_contract", path)
    assert spec is not None and spec.loader is not None
    checker = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = checker  # dataclasses look their module up there
    spec.loader.exec_module(checker)
    contract = checker.Contract.load()
    uses = checker.layer_imports(checker.build_graph(), contract)
    rows = ["| layer | members | may import (besides itself) | imports today |", "|---|---|---|---|"]
    for name, members in reversed(list(zip(contract.names, contract.layers, strict=True))):
        allowed = [p for m in members for p in contract.restricted.get(m, [])]
        may = f"the standard library, {', '.join(allowed)}" if allowed else "the layers below"
        today = sorted({t.removeprefix("flightstack.") for m in members for t in uses.get(m, ())})
        siblings = " (independent siblings)" if len(members) > 1 else ""
        names = ", ".join(f"`{m}`" for m in members)
        rows.append(f"| {name}{siblings} | {names} | {may} | {', '.join(today) or '-'} |")
    exceptions = [
        f"- `{importer}` → `{imported}`: {_cell(reason)}"
        for (importer, imported), reason in contract.exceptions.items()
    ]
    reserved = [f"- `{n}`: {', '.join(f'`{m}`' for m in only)}" for n, only in contract.reserved.items()]
    return "\n".join(
        [
            *rows,
            "",
            "Named exceptions (an import of a higher layer that the contract allows, with its reason):",
            "",
            *(exceptions or ["- none"]),
            "",
            "Reserved names (imported only by the modules named):",
            "",
            *(reserved or ["- none"]),
            "",
        ]
    )


RENDERERS: dict[str, Callable[[], str]] = {
    "cli": render_cli,
    "run-files": render_run_files,
    "event-kinds": render_event_kinds,
    "fault-rows": render_fault_rows,
    "import-contract": render_import_contract,
}


def render_blocks(markdown: str, where: str) -> str:
    """The page with every generated block rendered anew (ValueError: an unknown name, an unclosed block)."""

    def replace(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in RENDERERS:
            raise ValueError(f"{where}: unknown generated block {name!r}")
        body = RENDERERS[name]().strip("\n")
        return f"<!-- generated: {name} -->\n\n{body}\n\n<!-- /generated: {name} -->"

    rendered = BLOCK.sub(replace, markdown)
    opened, closed = len(OPEN.findall(markdown)), len(BLOCK.findall(markdown))
    if opened != closed:
        raise ValueError(f"{where}: a `<!-- generated: NAME -->` line without its closing line")
    return rendered


def pages_with_blocks(docs: Path = DOCS) -> list[Path]:
    """The manual's pages that hold a generated block."""
    return [p for p in sorted(docs.rglob("*.md")) if OPEN.search(p.read_text(encoding="utf-8"))]


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    return render_blocks(markdown, page.file.src_path)


def main(argv: list[str] | None = None) -> int:
    """`--update`: rewrite the stale blocks of docs/; `--check`: list them and exit 1 if any."""
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--update", action="store_true", help="rewrite the stale blocks (default: --check)")
    args = parser.parse_args(argv)
    stale = []
    for page in pages_with_blocks():
        text = page.read_text(encoding="utf-8")
        fresh = render_blocks(text, str(page.relative_to(DOCS.parent)))
        if fresh != text:
            stale.append(page.relative_to(DOCS.parent))
            if args.update:
                page.write_text(fresh, encoding="utf-8")
    for path in stale:
        print(f"{'updated' if args.update else 'stale'}: {path}")
    return 1 if stale and not args.update else 0


if __name__ == "__main__":
    sys.exit(main())
