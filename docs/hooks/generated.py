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
- `wire-keys`, `wire-prediction`, `wire-control`, `wire-world`: the bus's key expressions
  (`flightstack.comms.wire.CHANNELS`), the prediction message's bytes (`flightstack.comms.messages`), the
  operator channel's JSON (`flightstack.comms.control`) and the served world's messages;
- `csv-columns`: the per-run CSV's columns and rules (`flightstack.recording.csv_table`);
- `import-contract`: the layers of `tests/import_contract.toml`, top first, with what each may import and
  the contract's named exceptions and reserved names (tests/import_contract.py checks the code against it).
- `bibtex`: the preferred citation of `CITATION.cff` (the paper) as a BibTeX entry;
- `api`: the public API, `flightstack.__all__`: each name, the module that defines it and its docstring's
  first paragraph.

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


def _said(text: str) -> str:
    """A sentence's words, without its case and full stop."""
    return " ".join(text.split()).rstrip(".").lower()


def _command_section(path: list[str], help_line: str, parser: argparse.ArgumentParser, level: int) -> str:
    parts = [f"{'#' * level} {' '.join(path)}", ""]
    if help_line:
        parts += [help_line[0].upper() + help_line[1:] + ("" if help_line.endswith(".") else "."), ""]
    if parser.description and _said(parser.description) != _said(help_line):  # not the help line again
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


# ---- the bus's wire format ------------------------------------------------------------------------------
def render_wire_keys() -> str:
    """Every key expression of flightstack.comms.wire.CHANNELS: publisher, subscribers, payload, the Zenoh
    encoding its publisher declares and the attachment."""
    from flightstack.comms import wire

    lines = [
        "| key expression | publisher | subscribers | payload | Zenoh encoding on publish | attachment |",
        "|---|---|---|---|---|---|",
    ]
    for c in wire.CHANNELS:
        enc = "none (liveliness token)" if c.encoding is None else f"`{c.encoding}`"
        lines.append(
            f"| `{c.pattern}` | {_cell(c.publisher)} | {_cell(c.subscribers)} | {_cell(c.payload)} | {enc} | "
            f"{_cell(c.attachment)} |"
        )
    return "\n".join(lines) + "\n"


_FORMAT = re.compile(r"(\d*)([a-zA-Z?])")


def render_wire_prediction() -> str:
    """The prediction message's bytes: flightstack.comms.messages.HEAD / HEAD_FIELDS, the mission name,
    BODY / BODY_FIELDS; offsets computed from the struct formats (L: the mission name's length)."""
    import struct

    from flightstack.comms import messages as msg

    order, codes = msg.HEAD.format[0], _FORMAT.findall(msg.HEAD.format[1:])
    if len(codes) != len(msg.HEAD_FIELDS):
        raise ValueError("messages.HEAD_FIELDS does not name every field of messages.HEAD")
    rows = ["| offset (bytes) | size | struct format | field | holds |", "|---|---|---|---|---|"]
    done = ""
    for (count, code), (name, holds) in zip(codes, msg.HEAD_FIELDS, strict=True):
        fmt = f"{order}{count}{code}"
        offset, size = struct.calcsize(order + done), struct.calcsize(fmt)
        rows.append(f"| {offset} | {size} | `{fmt}` | `{name}` | {_cell(holds)} |")
        done += count + code
    head = msg.HEAD.size
    rows.append(f"| {head} | L | UTF-8 | `mission` | {_cell('the mission name (L bytes, no terminator)')} |")
    ((count, code),) = _FORMAT.findall(msg.BODY.format[1:])
    one = f"{msg.BODY.format[0]}{code}"
    if int(count) != len(msg.BODY_FIELDS):
        raise ValueError("messages.BODY_FIELDS does not name every value of messages.BODY")
    size = struct.calcsize(one)
    for k, (name, holds) in enumerate(msg.BODY_FIELDS):
        offset = f"{head} + L" + (f" + {k * size}" if k else "")
        rows.append(f"| {offset} | {size} | `{one}` | `{name}` | {_cell(holds)} |")
    total = f"{head} + L + {msg.BODY.size}"
    return "\n".join(rows) + f"\n\nA message is exactly {total} bytes.\n"


_JSON_TYPES = {
    "str": "string",
    "int": "integer",
    "float": "number",
    "bool": "true or false",
    "str | None": "string or null",
    "tuple[int, ...]": "array of integers",
    "tuple[tuple[str, int], ...]": "object: string → integer",
}


def render_wire_control() -> str:
    """The operator channel's JSON: an example of the envelope (control.encode_control), then each kind's
    payload fields (the typed views' dataclass fields, their JSON types) and its docstring."""
    import dataclasses
    import json

    from flightstack.comms import control

    example = {"drone": 1, "mode": "dgp", "t": 12.5, "tick": 1250, "battery_pct": 87.0, "flying": True,
               "link_alive": True, "visible": True, "n_fused": 3, "pose_fresh": True, "rejection": None,
               "dropped": {"stale": 2}, "restarts": {"agent-2": 1}}  # fmt: skip
    envelope = json.loads(control.encode_control("lab", control.STATUS, example, [1]))
    out = ["A status of drone 1 of mission `lab`, as `encode_control` writes it:", "", "```json"]
    out += [json.dumps(envelope, indent=2, ensure_ascii=False), "```", ""]
    kinds = (
        (control.ABORT, control.AbortRequest),
        (control.STATUS, control.StatusReport),
        (control.ABORT_ACK, control.AckReport),
    )
    for kind, cls in kinds:
        what = _first_paragraph(cls.__doc__)
        out += [f'`"kind": "{kind}"`: `payload` holds ({cls.__name__}) {what}', ""]
        out += ["| field | JSON type |", "|---|---|"]
        for f in dataclasses.fields(cls):
            if f.type not in _JSON_TYPES:
                raise ValueError(f"{cls.__name__}.{f.name}: no JSON type for {f.type!r}")
            out.append(f"| `{f.name}` | {_JSON_TYPES[str(f.type)]} |")
        out.append("")
    return "\n".join(out)


def render_wire_world() -> str:
    """The served world's framing (sim_backend/served/messages.py `_LEN`) and an example tick and command
    header, as `encode_tick` and `encode_cmd` write them."""
    import json

    from flightstack.sim_backend.served import messages as wm

    n = wm._LEN.size
    rows = [
        "| offset (bytes) | size | struct format | holds |",
        "|---|---|---|---|",
        f"| 0 | {n} | `{wm._LEN.format}` | L: the JSON header's length (bytes, at most {wm.MAX_HEADER}) |",
        f"| {n} | L | UTF-8 | the JSON header (one object, no NaN or Infinity) |",
        f"| {n} + L | H·W·3 (H·W) | uint8 | a tick's camera image, RGB (grey), row-major, when its "
        "`frame.image` is [H, W] ([H, W, 1]: a grey camera's); else nothing |",
    ]
    state = wm.TickState(87.0, 1.0, True, True, "flying")
    truth = wm.Truth((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 1.0, 3.14159))
    poses = {"drone1": (2.49, 0.5, 0.0, 1.0, 3.14159), "target": (2.49, 0.0, 0.0, 0.0, 0.0)}
    frame = wm.FrameHead(2.48, (0.125, -0.03, 0.15, -0.025), None)
    tick = wm.make_tick(250, 2.5, state, poses, truth, frame)
    cmd = wm.WorldCmd(250, (wm.DroneCall(wm.VELOCITY_CALL, (0.1, 0.0, -0.05, 0.2)),))
    if wm.decode_tick(wm.encode_tick(tick))[0] != tick or wm.decode_cmd(wm.encode_cmd(cmd))[0] != cmd:
        raise ValueError("the served world's example messages do not decode to themselves")
    for what, data in (("tick 250 of drone 1", wm.encode_tick(tick)), ("its command", wm.encode_cmd(cmd))):
        (length,) = wm._LEN.unpack_from(data)
        head = json.loads(data[n : n + length])
        rows += ["", f"The header of {what} (L = {length}):", "", "```json", json.dumps(head), "```"]
    return "\n".join(rows) + "\n"


# ---- the per-run CSV ------------------------------------------------------------------------------------
def render_csv_columns() -> str:
    """The CSV's columns (flightstack.recording.csv_table.COLUMNS) and its row and number rules."""
    from flightstack.recording import csv_table as ct

    lines = ["| column | unit | holds |", "|---|---|---|"]
    lines += [f"| `{c.name}` | {c.unit} | {_cell(c.meaning)} |" for c in ct.COLUMNS]
    lines += [
        "",
        f"Rows: tick 0 and every `stride`-th tick after it, stride = max(1, ⌊{ct.CSV_PERIOD_S:g} s / dt⌋), "
        f"raised until a file holds at most {ct.MAX_ROWS:,} rows; one row per drone of each such tick. "
        f"Reals are rounded to {ct.DECIMALS} decimals (trailing zeros dropped), integers written as such; a "
        "value that is not finite is an empty field.",
    ]
    return "\n".join(lines) + "\n"


# ---- the citation ---------------------------------------------------------------------------------------
CITATION = DOCS.parent / "CITATION.cff"
BIBTEX_TYPES = {"conference-paper": "inproceedings", "article": "article"}


def render_bibtex() -> str:
    """CITATION.cff's preferred citation as BibTeX, keyed <first author's family name><year><first title
    word> (lower case); its arXiv identifier as `eprint`."""
    paper = yaml.safe_load(CITATION.read_text(encoding="utf-8"))["preferred-citation"]
    first = re.sub(r"[^a-z]", "", paper["authors"][0]["family-names"].lower())
    word = re.sub(r"[^a-z]", "", paper["title"].split()[0].lower())
    fields = {
        "title": f"{{{paper['title']}}}",
        "author": " and ".join(f"{a['family-names']}, {a['given-names']}" for a in paper["authors"]),
    }
    if "conference" in paper:
        fields["booktitle"] = paper["conference"]["name"]
    if "collection-title" in paper:
        fields["series"] = paper["collection-title"]
    fields["year"] = str(paper["year"])
    arxiv = [i["value"] for i in paper.get("identifiers", []) if str(i["value"]).startswith("arXiv:")]
    if arxiv:
        fields |= {"eprint": arxiv[0].removeprefix("arXiv:"), "archivePrefix": "arXiv"}
    fields["url"] = paper["url"]
    width = max(map(len, fields))
    lines = [f"@{BIBTEX_TYPES[paper['type']]}{{{first}{paper['year']}{word},"]
    lines += [f"  {k:{width}s} = {{{v}}}," for k, v in fields.items()]
    return "\n".join(["```bibtex", *lines, "}", "```"]) + "\n"


def render_api() -> str:
    """`flightstack.__all__` as a table: name, defining module (flightstack.API), first paragraph."""
    import flightstack

    rows = ["| name | module | what it is |", "|---|---|---|"]
    for name, module in flightstack.API.items():
        doc = _first_paragraph(getattr(flightstack, name).__doc__)
        rows.append(f"| `{name}` | `{module}` | {_cell(doc)} |")
    return "\n".join(rows) + "\n"


RENDERERS: dict[str, Callable[[], str]] = {
    "cli": render_cli,
    "run-files": render_run_files,
    "event-kinds": render_event_kinds,
    "fault-rows": render_fault_rows,
    "import-contract": render_import_contract,
    "wire-keys": render_wire_keys,
    "wire-prediction": render_wire_prediction,
    "wire-control": render_wire_control,
    "wire-world": render_wire_world,
    "csv-columns": render_csv_columns,
    "bibtex": render_bibtex,
    "api": render_api,
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
