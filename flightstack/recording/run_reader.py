"""Reading a run directory back: recording.json, events.jsonl, the recording's status and every mode's
Recording (from the final npz, or from the row stream of a run that was killed).

Every file is checked as it is decoded (files.REQUIRED_FILES and OPTIONAL_FILES say which a reader
needs): a damaged required one raises RunDirError naming it, a damaged optional one is skipped and
listed in `RunContents.skipped` as `<file>: <what>`."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flightstack.recording.files import (
    EVENTS_FILE,
    MISSION_FILE,
    ROWS_SUFFIX,
    STATE_FILE,
    RunDirError,
    read_json_object,
)
from flightstack.recording.rows import read_row_stream
from flightstack.recording.timeseries import ARRAY_FIELDS, MAX_DRONES, Recording

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

_log = logging.getLogger(__name__)


@dataclass
class RunContents:
    """What a run directory holds: every mode's Recording in the order flown, the recording's status
    {"complete", "reason"} and what was skipped as damaged (`<file>: <what>`, one line each)."""

    recordings: dict[str, Recording]
    status: dict[str, Any]
    skipped: list[str] = field(default_factory=list)


def read_state(run_dir: Path) -> dict[str, Any]:
    """recording.json of a run directory ({} if absent or damaged)."""
    try:
        return _state(Path(run_dir))
    except RunDirError:
        return {}


def _state(run_dir: Path) -> dict[str, Any]:
    """recording.json ({} if absent); RunDirError when it is not JSON of the shape RunWriter writes."""
    path = run_dir / STATE_FILE
    if not path.exists():
        return {}
    doc = read_json_object(path)
    modes = doc.get("modes", {})
    if not isinstance(modes, dict):
        raise RunDirError(path, "modes: not an object")
    if not isinstance(doc.get("complete", False), bool) or not isinstance(doc.get("reason"), str | None):
        raise RunDirError(path, "complete / reason: not a boolean / a text")
    for mode, st in modes.items():
        if not isinstance(st, dict):
            raise RunDirError(path, f"modes.{mode}: not an object")
        ids = st.get("drone_ids", [])
        if not _int_list(ids):
            raise RunDirError(path, f"modes.{mode}.drone_ids: not a list of at most {MAX_DRONES} integers")
        problem = Recording.meta_problem(st)
        if problem is not None:
            raise RunDirError(path, f"modes.{mode}.{problem}")
    return doc


def _int_list(x: object) -> bool:
    return (
        isinstance(x, list)
        and len(x) <= MAX_DRONES
        and all(isinstance(i, int) and not isinstance(i, bool) for i in x)
    )


def resolved_mission(run_dir: Path) -> tuple[Mission | None, str | None]:
    """The run's mission_resolved.yaml as a Mission (its files not required to exist here), or (None, why
    not): the file is missing, or it does not load (an old or hand-edited file). For readers that can do
    without it (`view`, `export`); `report` and `train` insist on a mission."""
    from flightstack.config.mission import load_mission

    path = Path(run_dir) / MISSION_FILE
    if not path.is_file():
        return None, f"no {MISSION_FILE}"
    try:
        return load_mission(path, check_files=False), None
    except (OSError, ValueError) as exc:  # MissionError is a ValueError
        return None, f"{MISSION_FILE} does not load ({type(exc).__name__}: {exc})"


def read_events(run_dir: Path) -> list[dict[str, Any]]:
    """The events of events.jsonl, oldest first; a line that is not a JSON object (the last one cut
    short by a kill, a damaged one) is skipped."""
    return _events(Path(run_dir))[0]


def _events(run_dir: Path) -> tuple[list[dict[str, Any]], str | None]:
    """(events, what was skipped or None)."""
    path = run_dir / EVENTS_FILE
    out: list[dict[str, Any]] = []
    if not path.exists():
        return out, None
    try:
        data = path.read_bytes()
    except OSError as exc:
        return out, f"{EVENTS_FILE}: {exc.strerror or exc}"
    bad: list[int] = []
    lines = data.split(b"\n")
    for k, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            ev = json.loads(line.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            ev = None
        if isinstance(ev, dict):
            out.append(ev)
        else:
            bad.append(k)
    if not bad:
        return out, None
    torn = " (the last one cut short: a kill?)" if bad == [len(lines)] else ""
    lines_text = ", ".join(map(str, bad[:5])) + (", ..." if len(bad) > 5 else "")
    n = len(out) + len(bad)
    return out, f"{EVENTS_FILE}: {len(bad)} of {n} lines not JSON objects (line {lines_text}){torn}"


def recording_status(run_dir: Path, recs: Mapping[str, Recording] | None = None) -> dict[str, Any]:
    """{"complete", "reason"} of a run directory's recording, as `RunWriter.status` said when it closed;
    a run directory whose writer never closed (killed) is incomplete; one written before the recorder
    existed (no recording.json) is complete if it has a final npz per mode; one whose recording.json is
    damaged is incomplete (its state is unknown)."""
    try:
        doc = _state(Path(run_dir))
    except RunDirError as exc:
        return {"complete": False, "reason": f"{STATE_FILE} damaged: {exc.what}"}
    return _status(doc, recs)


def _status(doc: Mapping[str, Any], recs: Mapping[str, Recording] | None) -> dict[str, Any]:
    if not doc:
        return {"complete": bool(recs), "reason": None if recs else "no recording found"}
    if doc.get("state") != "closed":
        reason = "cut short: the process ended without closing the recording (killed?)"
        if doc.get("reason") not in (None, "in progress"):
            reason += f"; before that: {doc['reason']}"
        return {"complete": False, "reason": reason}
    return {"complete": bool(doc.get("complete")), "reason": doc.get("reason")}


def load_run(run_dir: Path | str, mission: Mission | None = None) -> dict[str, Recording]:
    """Every mode's Recording of a run directory (`read_run`; what it skipped is logged)."""
    contents = read_run(run_dir, mission)
    for line in contents.skipped:
        _log.warning("skipped: %s", line)
    return contents.recordings


def read_run(run_dir: Path | str, mission: Mission | None = None) -> RunContents:
    """Every mode's Recording of a run directory, in the order flown: from the final
    timeseries_<mode>.npz when there is one, else from its row stream (a run cut short by a kill, a
    crash or a full disk), with the facts of recording.json and the events of events.jsonl (an event
    without a `mode` belongs to the mode of the event before it). For a row stream e_c and e_e are
    recomputed from the poses when `mission` is given (else zeros), and `error` says the recording was
    cut short unless its writer closed it.

    RunDirError (naming the file) when a mode's recording is damaged (a row stream's damaged tail is
    dropped instead and listed in `skipped`); a damaged recording.json or events.jsonl is skipped (the
    status then says the state is unknown). An empty `recordings` when there is none."""
    run_dir = Path(run_dir)
    skipped: list[str] = []
    try:
        state = _state(run_dir)
        status_doc: dict[str, Any] | None = state
    except RunDirError as exc:
        skipped.append(f"{STATE_FILE}: {exc.what}")
        state, status_doc = {}, None
    modes_state: dict[str, dict[str, Any]] = state.get("modes", {})
    found = {p.name[len("timeseries_") : -len(".npz")] for p in run_dir.glob("timeseries_*.npz")}
    found |= {
        p.name[len("timeseries_") : -len(ROWS_SUFFIX)] for p in run_dir.glob(f"timeseries_*{ROWS_SUFFIX}")
    }
    order = [m for m in modes_state if m in found] + sorted(found - set(modes_state))
    recs: dict[str, Recording] = {}
    for mode in order:
        st = modes_state.get(mode, {})
        npz = run_dir / f"timeseries_{mode}.npz"
        rows_path = run_dir / f"timeseries_{mode}{ROWS_SUFFIX}"
        if npz.exists():
            try:
                rec = Recording.load(npz)
            except RunDirError as exc:
                if not rows_path.exists():
                    raise
                skipped.append(f"{npz.name}: {exc.what}; read its row stream instead")
                rec = _from_rows(rows_path, mode, st, mission, skipped)
            else:
                rec.apply_meta(st)
        else:
            rec = _from_rows(rows_path, mode, st, mission, skipped)
        recs[mode] = rec
    events, bad = _events(run_dir)
    if bad is not None:
        skipped.append(bad)
    current = order[0] if order else None
    for ev in events:
        m = ev.get("mode")
        if isinstance(m, str):
            current = m
        target = m if isinstance(m, str) else current
        if target in recs:
            recs[target].events.append(ev)
    if status_doc is None:
        status = {"complete": False, "reason": f"unknown: {STATE_FILE} damaged"}
    else:
        status = _status(status_doc, recs)
    return RunContents(recs, status, skipped)


def _from_rows(
    rows_path: Path, mode: str, st: Mapping[str, Any], mission: Mission | None, skipped: list[str]
) -> Recording:
    """A mode's Recording from its row stream (RunDirError when its header is damaged)."""
    meta, rows, dropped = read_row_stream(rows_path)
    if dropped is not None and len(rows) == 0:
        raise RunDirError(rows_path, f"no readable row: {dropped.removeprefix('kept the first 0 rows; ')}")
    if dropped is not None:
        skipped.append(f"{rows_path.name}: {dropped}")
    ids = meta.get("drone_ids", st.get("drone_ids", []))
    if not _int_list(ids):
        raise RunDirError(rows_path, f"header: drone_ids {str(ids)[:40]} is not a list of integers")
    names = rows.dtype.names or ()
    try:
        rec = Recording.from_columns(mode, ids, {f: rows[f] for f in ARRAY_FIELDS if f in names})
    except ValueError as exc:
        raise RunDirError(rows_path, str(exc)) from None
    good, why = rec.plausible_ticks()
    if why is not None:
        skipped.append(f"{rows_path.name}: kept the first {good} rows; dropped the rest: {why}")
        rec.ticks_done = good
        rec = rec.truncated()
    rec.apply_meta(st)
    k = rec.ticks_done
    if not st.get("wall_seconds") and k > 1:
        rec.wall_seconds = float(rec.wall_t[k - 1] - rec.wall_t[0])
    if st.get("state") != "closed" and not rec.error:
        rec.error = f"recording cut short after {k} ticks (the process ended without closing it)"
    if mission is not None:
        desired = {d.id: d.desired_pose.pose().as_vector() for d in mission.drones}
        if all(i in desired for i in ids):
            rec.fill_true_errors(np.array([desired[i] for i in ids]).reshape(len(ids), 4))
    return rec
