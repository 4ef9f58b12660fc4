"""Reading a run directory back: recording.json, events.jsonl, the recording's status and every mode's
Recording (from the final npz, or from the row stream of a run that was killed)."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flightstack.recording.files import EVENTS_FILE, MISSION_FILE, ROWS_SUFFIX, STATE_FILE
from flightstack.recording.rows import read_rows
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

_log = logging.getLogger(__name__)


def read_state(run_dir: Path) -> dict[str, Any]:
    """recording.json of a run directory ({} if absent or unreadable)."""
    try:
        doc = json.loads((Path(run_dir) / STATE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


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
    """The events of events.jsonl, oldest first; a line cut short by a kill is skipped."""
    path = Path(run_dir) / EVENTS_FILE
    out: list[dict[str, Any]] = []
    if not path.is_file():
        return out
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        if isinstance(ev, dict):
            out.append(ev)
    return out


def recording_status(run_dir: Path, recs: Mapping[str, Recording] | None = None) -> dict[str, Any]:
    """{"complete", "reason"} of a run directory's recording, as `RunWriter.status` said when it closed;
    a run directory whose writer never closed (killed) is incomplete; one written before the recorder
    existed (no recording.json) is complete if it has a final npz per mode."""
    doc = read_state(run_dir)
    if not doc:
        return {"complete": bool(recs), "reason": None if recs else "no recording found"}
    if doc.get("state") != "closed":
        reason = "cut short: the process ended without closing the recording (killed?)"
        if doc.get("reason") not in (None, "in progress"):
            reason += f"; before that: {doc['reason']}"
        return {"complete": False, "reason": reason}
    return {"complete": bool(doc.get("complete")), "reason": doc.get("reason")}


def load_run(run_dir: Path | str, mission: Mission | None = None) -> dict[str, Recording]:
    """Every mode's Recording of a run directory, in the order flown: from the final
    timeseries_<mode>.npz when there is one, else from its row stream (a run cut short by a kill, a
    crash or a full disk), with the facts of recording.json and the events of events.jsonl (an event
    without a `mode` belongs to the mode of the event before it). For a row stream e_c and e_e are
    recomputed from the poses when `mission` is given (else zeros), and `error` says the recording was
    cut short unless its writer closed it."""
    run_dir = Path(run_dir)
    state = read_state(run_dir)
    modes_state: dict[str, dict[str, Any]] = state.get("modes", {}) if isinstance(state, dict) else {}
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
        if npz.is_file():
            rec = Recording.load(npz)
            rec.apply_meta(st)
        else:
            try:
                meta, rows = read_rows(rows_path)
            except (OSError, ValueError) as exc:
                _log.error("%s: %s", rows_path, exc)
                continue
            ids = [int(i) for i in meta.get("drone_ids", st.get("drone_ids", []))]
            names = rows.dtype.names or ()
            rec = Recording.from_columns(mode, ids, {f: rows[f] for f in ARRAY_FIELDS if f in names})
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
        recs[mode] = rec
    current = order[0] if order else None
    for ev in read_events(run_dir):
        m = ev.get("mode")
        if isinstance(m, str):
            current = m
        target = m if isinstance(m, str) else current
        if target in recs:
            recs[target].events.append(ev)
    return recs
