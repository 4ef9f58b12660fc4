"""`flightstack faults`: fly the simulated mission under each fault and tabulate what the system did.

The registry `FAULTS` maps a row name to a `FaultRow`, a function (mission file, work directory) ->
`FaultResult` (flightstack/faults/result.py). Rows come from the modules named in `ROW_MODULES`, each of
which defines `ROWS: dict[str, FaultRow]` in table order; `register_fault` adds one more at run time. A row
is *handled* when nothing crashed, every drone ended safe, the recording is intact and the observed
reaction is the expected one (docs/faults.md).

Adding rows (e.g. the multi-process runner's "one agent process killed" and "bus partition"): write a
module with `ROWS = {"agent_killed": fn, ...}` and append its import path to `ROW_MODULES`, or call
`register_fault("agent_killed", fn)` before `run_faults`.
"""

from __future__ import annotations

import importlib
import json
import time
import traceback
from collections.abc import Iterable
from pathlib import Path

from flightstack.config.rig import MISSION_CONFIGS
from flightstack.faults.result import FaultResult, FaultRow

__all__ = [
    "DEFAULT_MISSION",
    "FAULTS",
    "ROW_MODULES",
    "FaultResult",
    "FaultRow",
    "format_table",
    "register_fault",
    "run_faults",
    "write_json",
]

DEFAULT_MISSION = MISSION_CONFIGS / "paper_experiment.yaml"
"""The simulated lab mission (backend sim_lab, safety on) that the rows fly by default."""

ROW_MODULES: list[str] = [
    "flightstack.faults.rows_sim",
    "flightstack.faults.rows_cli",
    "flightstack.faults.rows_processes",
    "flightstack.faults.rows_lab",
    "flightstack.faults.rows_lab_kills",
    "flightstack.faults.rows_robot_preflight",
]
"""Modules whose `ROWS` make up the table, in this order."""


def _load_rows() -> dict[str, FaultRow]:
    rows: dict[str, FaultRow] = {}
    for name in ROW_MODULES:
        rows.update(importlib.import_module(name).ROWS)
    return rows


FAULTS: dict[str, FaultRow] = _load_rows()
"""Row name -> row function, in table order."""


def register_fault(name: str, row: FaultRow) -> None:
    """Add (or replace) the row `name`; it runs after the rows already registered."""
    FAULTS.pop(name, None)
    FAULTS[name] = row


def run_one(name: str, mission_path: Path, workdir: Path) -> FaultResult:
    """Run one row; an exception escaping the row itself becomes a crashed, unhandled result."""
    wall0 = time.perf_counter()
    try:
        return FAULTS[name](Path(mission_path), Path(workdir))
    except Exception as exc:
        return FaultResult(
            name=name,
            expected="",
            observed=f"the row raised {type(exc).__name__}: {exc}",
            all_safe=False,
            recording_complete=False,
            crashed=True,
            seconds=time.perf_counter() - wall0,
            reaction_ok=False,
            problems=[traceback.format_exc(limit=-3)],
        )


def run_faults(
    names: Iterable[str] | None, workdir: Path, mission_path: Path = DEFAULT_MISSION
) -> list[FaultResult]:
    """Run the named rows (None: all, in table order) with their files under `workdir`.

    Raises KeyError naming the unknown rows before running anything."""
    todo = list(FAULTS) if names is None else list(names)
    unknown = [n for n in todo if n not in FAULTS]
    if unknown:
        raise KeyError(f"unknown fault(s) {unknown}; known: {', '.join(FAULTS)}")
    Path(workdir).mkdir(parents=True, exist_ok=True)
    return [run_one(n, mission_path, workdir) for n in todo]


def _yes(flag: bool) -> str:
    return "yes" if flag else "NO"


def format_table(results: list[FaultResult], expected: bool = False) -> str:
    """A fixed-width table, one line per row (handled, crashed, all safe, recording, wall s), each followed
    by its observed reaction (and, with `expected`, the documented one) and any failed check."""
    width = max([len("fault"), *(len(r.name) for r in results)])
    head = f"{'fault':<{width}}  handled  crashed  all safe  recording  wall s"
    lines = [head, "-" * len(head)]
    for r in results:
        lines.append(
            f"{r.name:<{width}}  {_yes(r.handled):<7}  {'YES' if r.crashed else 'no':<7}  "
            f"{_yes(r.all_safe):<8}  {_yes(r.recording_complete):<9}  {r.seconds:6.1f}"
        )
        if expected:
            lines.append(f"    expected: {r.expected}")
        lines.append(f"    observed: {r.observed}")
        lines.extend(f"    FAILED {p}" for p in r.problems)
    n_ok = sum(r.handled for r in results)
    total = sum(r.seconds for r in results)
    lines.append(f"{n_ok}/{len(results)} faults handled in {total:.1f} s")
    return "\n".join(lines)


def write_json(results: list[FaultResult], path: Path) -> None:
    """faults.json: {"handled": all handled, "results": [FaultResult as dict, ...]}."""
    doc = {"handled": all(r.handled for r in results), "results": [r.to_dict() for r in results]}
    Path(path).write_text(json.dumps(doc, indent=2, default=str) + "\n")
