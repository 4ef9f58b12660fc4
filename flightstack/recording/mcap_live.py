"""The run's MCAP (`recording.mcap` in the run directory), written as the flight goes by a companion
process that follows the run directory: `python -m flightstack.recording.mcap_live RUN_DIR OUT`.

Why a process: the flight's own process must not spend its cores, or its GIL, on encoding and compressing
(a 40 s paper_sim run is 245 000 messages, about 1.6 s of CPU), and a writer that fails or hangs must not
touch the control loop. The follower reads what the run directory already holds as it is written
(run_dir.py): each mode's row stream `timeseries_<mode>.rows` (complete rows only, checked by `_seq`;
e_c and e_e computed from the poses and the mission's desired poses, as `load_run` does), the final
`timeseries_<mode>.npz` of a mode written whole, each mode's camera frames `images_<mode>.jpgs`
(camera_frames.py) and events.jsonl; it only reads modes that recording.json names (this run's), so the
files of an earlier run in the directory are never mixed in. It writes through mcap_writer.RunMcap (the
topics and the time base are described there; the frame tree and scene from the run's
mission_resolved.yaml, mcap_scene.py) and closes the open chunk every FLUSH_PERIOD_S.

Its stdin is a pipe from the flight's process: end of file (the run directory closed, or the flight's
process gone, by any signal) makes it read everything left, attach metrics.json, recording.json and the
mission, write the MCAP's summary and exit; it prints one JSON line ({"messages", "topics", "ticks",
"images", "skipped", "error"}). It ignores SIGINT (Ctrl-C lands the drones; the file is finished after)
and runs in its own session, so that a kill of the flight's process group leaves it to finish the file.
The flight's process waits for it while it makes progress (`LiveMcap.finish`: its CPU time or its file's
size; a loaded machine only slows it) and kills it after STALL_S without any (stopped, hung); a follower
that died or was killed is reported as the run's error (flightstack.cli.run), and `flightstack report`
finalises the file it left (mcap_finalise.py).

Its CPU follows the rows it copies, about 30 µs per tick of 3 drones (paper_sim: 1.8 s for 60 000 ticks,
plus about 1 s of imports): at a real flight's rates (20–50 Hz) that is well under 1 % of a core. It
lowers its priority (`lower_priority`) so that on a busy machine the flight gets the cores first and the
follower catches up once the flight is done: nice +10, and the same nice on its session's autogroup.
Where Linux schedules by session (`sched_autogroup_enabled`, on by default on many distributions) a
process's nice counts only within its session, and the follower is alone in its own; without the second
step it competed with the flight as one more session (measured: docs/performance.md). At end of file the
flight is over and its command waits for the file: the follower sets its group back to nice 0 (allowed
without privilege, unlike a process's own nice) to finish at a fair share of a busy machine.
Killed itself (SIGKILL), the file it leaves reads up to its last complete chunk: at most CHUNK_BYTES
(uncompressed) or FLUSH_PERIOD_S of wall time lost, plus the rows it had not polled yet (POLL_S).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from flightstack.child_watch import communicate_while_progressing
from flightstack.recording.camera_frames import FrameTail, images_name
from flightstack.recording.files import EVENTS_FILE, LIVE_MCAP_FILE, ROWS_SUFFIX, STATE_FILE, RunDirError
from flightstack.recording.rows import RowLayout, parse_header
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording
from flightstack.scheduling import AUTOGROUP, set_group_nice

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

_log = logging.getLogger(__name__)

POLL_S = 0.2
"""How often (s) the follower reads the run directory."""
FLUSH_PERIOD_S = 1.0
"""Wall time (s) after which the follower closes its open chunk: what a kill of the follower can lose."""
STALL_S = 2.5
"""Closing a run waits for the follower while it makes progress (CPU time or bytes of its file); this long
(s) without either, it is killed (stopped, or hung) and the file left as a kill leaves it."""
FINISH_TIMEOUT_S = 300.0
"""The most (s) closing a run waits for a follower that keeps making progress; then it is killed too."""
NICENESS = 10
"""The follower's nice increment, and its session's autogroup nice (module docstring)."""
MAX_EVENT_LINE = 1 << 20
"""Bound on one events.jsonl line (B); a longer one is skipped and counted."""


class _RowTail:
    """The complete rows of a growing row stream, read as they appear (an open descriptor keeps reading
    the stream after the recorder removes it at the mode's end)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fh: IO[bytes] | None = None
        self.layout: RowLayout | None = None
        self.read_rows = 0
        self._buf = b""

    def read(self) -> np.ndarray | None:
        """The rows that appeared since the last call (None: none yet). RunDirError for a damaged header."""
        if self.fh is None:
            try:
                self.fh = open(self.path, "rb")  # noqa: SIM115 (kept open: the stream may be removed)
            except FileNotFoundError:
                return None
        self._buf += self.fh.read()
        if self.layout is None:
            parsed = parse_header(self.path, self._buf)
            if parsed is None:
                return None
            self.layout, start = parsed
            self._buf = self._buf[start:]
        size = self.layout.dtype.itemsize
        count = len(self._buf) // size
        if count == 0:
            return None
        rows = np.frombuffer(self._buf[: count * size], dtype=self.layout.dtype)
        ok = rows["_seq"] == np.arange(self.read_rows + 1, self.read_rows + count + 1)
        good = count if ok.all() else int(np.argmin(ok))  # a block still being written: wait for it
        self._buf = self._buf[good * size :]
        self.read_rows += good
        return rows[:good].copy() if good else None

    def close(self) -> None:
        if self.fh is not None:
            self.fh.close()
            self.fh = None


class RunFollower:
    """Copies a run directory into a RunMcap as it is written (module docstring): `poll` often, `finish`
    once. `skipped`: what was left out and why (counted)."""

    def __init__(self, run_dir: Path, out: Path) -> None:
        from flightstack.recording.mcap_writer import RunMcap

        self.run_dir = run_dir
        self.mcap = RunMcap(out)
        self.tails: dict[str, _RowTail] = {}
        self.frame_tails: dict[str, FrameTail] = {}
        self.done: set[str] = set()  # modes whose every row is in the MCAP
        self.ticks: Counter[str] = Counter()
        self.images: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        self._ids: dict[str, list[int]] = {}
        self._mission: Mission | None = None
        self._mission_read = False
        self._events_at = 0
        self._event_buf = b""
        self._event_mode: str | None = None
        self._early: list[dict[str, Any]] = []  # events before any mode was named
        self._last_flush = time.monotonic()

    # ---- the run's facts ------------------------------------------------------------------------------
    def _modes(self) -> dict[str, dict[str, Any]]:
        try:
            doc = json.loads((self.run_dir / STATE_FILE).read_text())
        except (OSError, ValueError):
            return {}  # not written yet, or being replaced: next poll
        modes = doc.get("modes") if isinstance(doc, dict) else None
        return {str(k): v for k, v in modes.items() if isinstance(v, dict)} if isinstance(modes, dict) else {}

    def _read_mission(self) -> Mission | None:
        """The run's mission, read once at the first rows (Flight writes it before anything flies); it sets
        the MCAP's frame tree and scene (mcap_scene.Scene). None: no mission file."""
        if not self._mission_read:
            from flightstack.recording.mcap_scene import Scene
            from flightstack.recording.run_reader import resolved_mission

            self._mission_read = True
            self._mission, _ = resolved_mission(self.run_dir)
            if self._mission is not None:
                self.mcap.channels.scene = Scene.of(self._mission)
        return self._mission

    def _desired(self, ids: list[int]) -> np.ndarray | None:
        """The drones' desired poses g_d (n, 4) from the run's mission (None: no mission file)."""
        mission = self._read_mission()
        g_d = {} if mission is None else {d.id: d.desired_pose.pose().as_vector() for d in mission.drones}
        if not all(i in g_d for i in ids):
            return None
        return np.array([g_d[i] for i in ids], dtype=float).reshape(len(ids), 4)

    # ---- copying ----------------------------------------------------------------------------------------
    def _write_rows(self, mode: str, ids: list[int], columns: dict[str, np.ndarray]) -> None:
        self._read_mission()
        rec = Recording.from_columns(mode, ids, columns)
        if "e_c" not in columns:  # a row stream: derived here as load_run does
            g_d = self._desired(ids)
            if g_d is None:
                self.skipped["e_c, e_e: no mission file to compute them from (written as zeros)"] += 1
            else:
                rec.fill_true_errors(g_d)
        self.mcap.ticks(mode, ids, {f: getattr(rec, f) for f in ARRAY_FIELDS})
        self.ticks[mode] += len(rec.t)

    def _poll_mode(self, mode: str, state: dict[str, Any], final: bool) -> None:
        if mode in self.done:
            return
        tail = self.tails.setdefault(mode, _RowTail(self.run_dir / f"timeseries_{mode}{ROWS_SUFFIX}"))
        rows = tail.read()
        if rows is not None and tail.layout is not None:
            ids = [int(i) for i in tail.layout.meta.get("drone_ids", state.get("drone_ids", []))]
            self._ids[mode] = ids
            names = rows.dtype.names or ()
            self._write_rows(mode, ids, {f: rows[f] for f in ARRAY_FIELDS if f in names})
        closed = state.get("state") == "closed"
        if closed and state.get("final"):
            npz = self.run_dir / str(state["final"])
            have = self.ticks[mode]
            rec = Recording.load(npz) if have < int(state.get("ticks_done", have)) else None
            if rec is not None and rec.ticks_done > have:  # a mode written whole, or rows never seen
                rec = rec.truncated()
                self._write_rows(mode, rec.drone_ids, {f: getattr(rec, f)[have:] for f in ARRAY_FIELDS})
            self.done.add(mode)
            tail.close()
        elif closed and final:
            self.done.add(mode)  # cut short: its row stream is all there is
            tail.close()

    def _poll_frames(self, mode: str) -> None:
        """The camera frames of `mode` written since the last poll (read until the run is over: the frames
        of a mode may be finished after its recording is)."""
        tail = self.frame_tails.setdefault(mode, FrameTail(self.run_dir / images_name(mode)))
        frames = tail.read()
        if frames:
            self.mcap.frames(mode, frames)
            self.images[mode] += len(frames)
        if tail.error is not None and tail.error not in self.skipped:
            self.skipped[tail.error] += 1

    def _poll_events(self) -> None:
        path = self.run_dir / EVENTS_FILE
        try:
            with open(path, "rb") as fh:
                fh.seek(self._events_at)
                data = fh.read()
        except FileNotFoundError:
            return
        self._events_at += len(data)
        self._event_buf += data
        *lines, self._event_buf = self._event_buf.split(b"\n")
        if len(self._event_buf) > MAX_EVENT_LINE:
            self.skipped["an events.jsonl line longer than 1 MiB"] += 1
            self._event_buf = b""
        for line in lines:
            if not line.strip():
                continue
            try:
                ev = json.loads(line)
            except (ValueError, RecursionError):
                self.skipped["an events.jsonl line that is not JSON"] += 1
                continue
            if not isinstance(ev, dict):
                self.skipped["an events.jsonl line that is not an object"] += 1
                continue
            if isinstance(ev.get("mode"), str):
                self._event_mode = ev["mode"]
            if self._event_mode is None:  # before any mode: the first mode's, as read_run has it
                self._early.append(ev)
                continue
            self.mcap.events(self._event_mode, [ev])

    def poll(self, final: bool = False) -> None:
        """Copy what appeared since the last poll; final: the run is over (read every row left)."""
        modes = self._modes()
        if self._early and (first := self._event_mode or next(iter(modes), None)) is not None:
            early, self._early = self._early, []
            self.mcap.events(first, early)
        for mode, state in modes.items():
            try:
                self._poll_mode(mode, state, final)
            except (RunDirError, ValueError, OSError) as exc:
                self.skipped[f"timeseries_{mode}: {exc}"] += 1
                self.done.add(mode)
            try:
                self._poll_frames(mode)
            except OSError as exc:
                self.skipped[f"{images_name(mode)}: {exc}"] += 1
        self._poll_events()
        if time.monotonic() - self._last_flush >= FLUSH_PERIOD_S:
            self.mcap.flush()
            self._last_flush = time.monotonic()

    def finish(self) -> dict[str, Any]:
        """Read everything left, attach the run's files, close the MCAP; what was written."""
        from flightstack.recording.mcap_export import attach_run_files

        error = None
        try:
            self.poll(final=True)
            attach_run_files(self.mcap, self.run_dir, self.mcap.first_ns or 0)
        except Exception as exc:  # the file is still closed below: what was written stays readable
            error = f"{type(exc).__name__}: {exc}"
        finally:
            for tail in self.tails.values():
                tail.close()
            for frames in self.frame_tails.values():
                frames.close()
            self.mcap.close()
        if self._early:
            self.skipped["events of a run that flew no mode"] += len(self._early)
        return {
            "messages": sum(self.mcap.counts.values()),
            "topics": len(self.mcap.counts),
            "ticks": dict(self.ticks),
            "images": dict(self.images),
            "skipped": dict(self.skipped),
            "error": error,
        }


def follow(run_dir: Path, out: Path, stop_fd: int) -> dict[str, Any]:
    """Follow `run_dir` into `out` until `stop_fd` reads end of file (or SIGTERM); then finish."""
    stopping = False

    def on_term(signum: int, frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, on_term)
    follower = RunFollower(run_dir, out)
    while not stopping:
        try:
            ready, _, _ = select.select([stop_fd], [], [], POLL_S)
        except InterruptedError:
            ready = []
        if ready and not os.read(stop_fd, 4096):
            break
        follower.poll()
    set_group_nice(0)  # the flight is over: nothing left to yield to (module docstring)
    return follower.finish()


def lower_priority(nice: int = NICENESS, autogroup: Path = AUTOGROUP) -> None:
    """Yield the cores to the flight (module docstring): nice +`nice` for this process, and `nice` for its
    session's autogroup where the kernel has one and this process leads its session (raising it needs no
    privilege)."""
    with contextlib.suppress(OSError):
        os.nice(nice)
    set_group_nice(nice, autogroup)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m flightstack.recording.mcap_live RUN_DIR OUT", file=sys.stderr)
        return 2
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    lower_priority()
    try:
        report = follow(Path(args[0]), Path(args[1]), sys.stdin.fileno())
    except Exception as exc:  # e.g. OUT cannot be created: said on one line
        print(json.dumps({"error": f"{type(exc).__name__}: {exc}"}), flush=True)
        return 1
    print(json.dumps(report), flush=True)
    return 0 if report["error"] is None else 1


class LiveMcap:
    """The follower process of a run directory, started by RunWriter(live_mcap=True)."""

    def __init__(self, run_dir: Path, out: Path | None = None) -> None:
        self.out = out or run_dir / LIVE_MCAP_FILE
        self.report: dict[str, Any] | None = None
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "flightstack.recording.mcap_live", str(run_dir), str(self.out)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )

    def finish(self, stall_s: float = STALL_S, timeout_s: float = FINISH_TIMEOUT_S) -> dict[str, Any]:
        """Tell the follower the run is over and wait for its report while it makes progress (killed
        after `stall_s` s without any, or `timeout_s` s in all: child_watch). `error` in the report is None
        only when the file was finished. Never raises."""
        if self.report is not None:
            return self.report
        try:
            out, err, killed = communicate_while_progressing(self.proc, stall_s, timeout_s, self._size)
            self.report = _report(self.proc.returncode, out, err, killed)
        except Exception as exc:
            self.report = {"error": f"{type(exc).__name__}: {exc}"}
        return self.report

    def _size(self) -> int:
        """The file's size (B; -1 before it exists): the follower's progress besides its CPU time."""
        try:
            return self.out.stat().st_size
        except OSError:
            return -1


def _report(returncode: int, out: bytes, err: bytes, killed: str | None) -> dict[str, Any]:
    """The follower's report (its last stdout line), its error said in one line when the file was not
    finished: killed here for `killed`, ended by a signal, or ended without a report."""
    lines = out.decode(errors="replace").strip().splitlines()
    try:
        report = json.loads(lines[-1]) if lines else {}
    except ValueError:
        report = {}
    if not isinstance(report, dict):
        report = {}
    last = (err.decode(errors="replace").strip().splitlines() or [""])[-1][:300]
    if killed is not None:
        report["error"] = f"the writer was killed: {killed}; the file ends at its last complete chunk"
    elif returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        report["error"] = f"the writer ended by {name}; the file ends at its last complete chunk"
    elif not report.get("error") and (returncode != 0 or "messages" not in report):
        report["error"] = f"the writer exited with {returncode} without finishing the file" + (
            f" ({last})" if last else ""
        )
    report.setdefault("error", None)
    return report


if __name__ == "__main__":
    sys.exit(main())
