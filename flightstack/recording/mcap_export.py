"""A finished (or cut short) run directory as one MCAP file: `flightstack export RUN_DIR --mcap FILE`, for
run directories written before the live MCAP (mcap_live.py) or without it. The same writer and the same
topics as the live file (flightstack.recording.mcap_writer has the layout and the time base), the camera
frames from each mode's images_<mode>.jpgs (camera_frames.py), the frame tree and scene from the mission
(mcap_scene.py)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from flightstack.recording.camera_frames import images_name, read_frames
from flightstack.recording.files import METRICS_FILE, MISSION_FILE, STATE_FILE
from flightstack.recording.mcap_scene import Scene
from flightstack.recording.mcap_writer import RunMcap
from flightstack.recording.run_reader import read_run, resolved_mission
from flightstack.recording.timeseries import ARRAY_FIELDS

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

ATTACHMENTS = {
    METRICS_FILE: "application/json",
    STATE_FILE: "application/json",
    MISSION_FILE: "application/yaml",
}
"""Files of the run directory attached to the MCAP file (when present), with their media types."""


class ExportError(ValueError):
    """The run directory cannot be exported (missing, no recording, an unknown mode)."""


@dataclass
class ExportSummary:
    """What `export_mcap` wrote: messages per topic; per mode its ticks and mission-clock span (s)."""

    path: Path
    modes: list[str]
    topics: dict[str, int] = field(default_factory=dict)
    mode_ticks: dict[str, int] = field(default_factory=dict)
    mode_seconds: dict[str, float] = field(default_factory=dict)
    mode_images: dict[str, int] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    """Damaged optional files and row stream tails left out (`<file>: <what>`, run_reader.read_run)."""

    @property
    def messages(self) -> int:
        return sum(self.topics.values())


def attach_run_files(mcap: RunMcap, run_dir: Path, when_ns: int) -> None:
    """Attach the run directory's ATTACHMENTS that exist (read now)."""
    for name, media_type in ATTACHMENTS.items():
        path = run_dir / name
        if path.is_file():
            mcap.attach(name, media_type, path.read_bytes(), when_ns)


def export_mcap(
    run_dir: Path | str, out: Path | str, modes: list[str] | None = None, mission: Mission | None = None
) -> ExportSummary:
    """Write the run directory's recording (every mode, or `modes` in that order) to the MCAP file `out`
    (replaced atomically if it exists). mission: lets `read_run` recompute e_c and e_e of a recording cut
    short (a row stream), and sets the frame tree and scene (else the run's mission_resolved.yaml, if it
    loads). Raises ExportError for a missing run directory, one without a recording, or an
    unknown mode; RunDirError (naming the file) for a damaged recording; OSError when `out` cannot be
    written."""
    run_dir, out = Path(run_dir), Path(out)
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: no such run directory")
    contents = read_run(run_dir, mission)
    recs = contents.recordings
    if not recs:
        raise ExportError(f"{run_dir}: no recording (timeseries_<mode>.npz or .rows) in it")
    chosen = list(recs) if modes is None else list(modes)
    unknown = [m for m in chosen if m not in recs]
    if unknown:
        raise ExportError(f"{run_dir}: no mode {', '.join(unknown)} recorded (it has {', '.join(recs)})")
    summary = ExportSummary(out, chosen, skipped=contents.skipped)
    if mission is None:
        mission, _ = resolved_mission(run_dir)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    try:
        mcap = RunMcap(tmp, scene=None if mission is None else Scene.of(mission))
        for mode in chosen:
            rec = recs[mode].truncated()
            mcap.ticks(mode, rec.drone_ids, {f: getattr(rec, f) for f in ARRAY_FIELDS})
            mcap.events(mode, rec.events)
            frames, error = read_frames(run_dir / images_name(mode))
            mcap.frames(mode, frames)
            summary.mode_images[mode] = len(frames)
            if error is not None:
                summary.skipped.append(error)
            summary.mode_ticks[mode] = rec.ticks_done
            summary.mode_seconds[mode] = float(rec.t[-1] - rec.t[0]) if rec.ticks_done else 0.0
        attach_run_files(mcap, run_dir, mcap.first_ns or 0)
        mcap.close()
        summary.topics = dict(mcap.counts)
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return summary


__all__ = ["ATTACHMENTS", "ExportError", "ExportSummary", "attach_run_files", "export_mcap"]
