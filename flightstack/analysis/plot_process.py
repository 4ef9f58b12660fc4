"""A run's plots drawn by a second Python process while the flight goes on.

matplotlib's import and drawing cost about as much as the three flown modes of `paper_sim` (about 0.5 s
and 0.2 s a plot on 2 idle cores); drawn in the flight's own process they came after everything else. A
`PlotProcess` starts `python -m flightstack.analysis.plot_process` when the flight opens its run
directory: it imports matplotlib on the other core while the flight flies, draws the trajectory as soon as
the data run and the training are on disk, and the error plots once the last mode is.

The child reads what it draws from the run directory (the same files `flightstack report` reads), so a
plot shows what was recorded. Requests and replies are one JSON object per line:

- parent → child: `{"run_dir": str, "plots": [names of files.PLOTS], "modes": [mode names]}`;
- child → parent: `{"written": [file names], "error": str | null}`, one per request, in order.

The child ignores SIGINT (a Ctrl-C is the flight's to handle: it lands, then plots) and ends at the end
of its input, i.e. when the flight closes the pipe or dies. Whatever the child did not draw (it failed,
died or did not answer in time) the flight draws itself (`Flight`), so a broken child costs time, not
plots.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

from flightstack.recording.files import PLOTS

REPLY_TIMEOUT_S = 60.0
"""Longest wait for the child's reply to the last request (s); then the flight draws what is missing."""


class PlotProcess:
    """The child process; `request` hands it plots to draw, `finish` waits for its replies and ends it.
    Never raises: a child that cannot start or breaks leaves `problem` set and draws nothing more."""

    def __init__(self, command: Sequence[str] | None = None) -> None:
        """command: the child's command line (default: this module's `main` in this interpreter)."""
        self.problem: str | None = None
        self._replies: list[dict[str, Any]] = []
        self._asked = 0
        self._ended = False  # the child closed its output (it exited)
        self._cond = threading.Condition()
        try:
            self._proc: subprocess.Popen[str] | None = subprocess.Popen(
                list(command or [sys.executable, "-m", "flightstack.analysis.plot_process"]),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,  # errors come back in the replies
                text=True,
            )
        except OSError as exc:
            self._proc, self.problem = None, f"plot process not started: {exc}"
            return
        assert self._proc.stdout is not None
        self._reader = threading.Thread(
            target=self._read, args=(self._proc.stdout,), name="plot-process-replies", daemon=True
        )
        self._reader.start()

    def __enter__(self) -> PlotProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request(self, run_dir: Path, plots: Sequence[str], modes: Sequence[str]) -> None:
        """Ask for `plots` (names of files.PLOTS) of `run_dir` from the final npz of `modes`, which must
        be on disk already."""
        if self._proc is None or self.problem is not None:
            return
        line = json.dumps({"run_dir": str(run_dir), "plots": list(plots), "modes": list(modes)})
        try:
            assert self._proc.stdin is not None
            self._proc.stdin.write(line + "\n")
            self._proc.stdin.flush()
        except (OSError, ValueError) as exc:  # the child died: BrokenPipe, or a closed pipe
            with self._cond:
                self.problem = self.problem or f"plot process gone: {exc}"
                self._cond.notify_all()
            return
        self._asked += 1

    def finish(self, timeout_s: float = REPLY_TIMEOUT_S) -> set[str]:
        """Wait (at most `timeout_s`) for every reply; the plot names drawn. Ends the child."""
        with self._cond:
            answered = lambda: len(self._replies) >= self._asked or self._ended or self.problem  # noqa: E731
            self._cond.wait_for(answered, timeout_s)
            if len(self._replies) < self._asked and self.problem is None:
                why = "ended" if self._ended else f"did not answer within {timeout_s:.0f} s"
                self.problem = f"plot process {why} before drawing every plot"
            replies = list(self._replies)
        self.close()
        by_file = {f: name for name, f in PLOTS.items()}
        drawn = {by_file[f] for r in replies for f in r.get("written", []) if f in by_file}
        errors = [str(r["error"]) for r in replies if r.get("error")]
        if errors and self.problem is None:
            self.problem = "; ".join(errors)
        return drawn

    def close(self) -> None:
        """End the child: close its input (it exits), kill it if it has not within 2 s. Idempotent."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            assert proc.stdin is not None
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    def _read(self, stdout: IO[str]) -> None:
        for line in stdout:
            try:
                reply = json.loads(line)
            except ValueError:
                reply = None
            with self._cond:
                if not isinstance(reply, dict):
                    self.problem = self.problem or f"plot process: unreadable reply {line[:80]!r}"
                else:
                    self._replies.append(reply)
                self._cond.notify_all()
        with self._cond:
            self._ended = True
            self._cond.notify_all()


def draw(run_dir: Path, plots: Sequence[str], modes: Sequence[str]) -> list[str]:
    """Draw `plots` of `run_dir` from its mission and the final npz of `modes`; the file names written."""
    from flightstack.analysis.report import run_mission, write_plots
    from flightstack.learning.training import load_datasets
    from flightstack.recording.files import DATASETS_FILE
    from flightstack.recording.timeseries import Recording

    mission = run_mission(run_dir)
    recs = {m: Recording.load(run_dir / f"timeseries_{m}.npz") for m in modes}
    has_data = "trajectory" in plots and (run_dir / DATASETS_FILE).exists()  # none: experts were given
    data = load_datasets(run_dir / DATASETS_FILE) if has_data else []
    return [p.name for p in write_plots(run_dir, mission, recs, data, only=set(plots))]


def request_problem(req: object) -> str | None:
    """What makes `req` no request (None: it is one)."""
    if not isinstance(req, dict) or set(req) != {"run_dir", "plots", "modes"}:
        return "a request is an object with run_dir, plots and modes"
    if not isinstance(req["run_dir"], str):
        return "run_dir: not a string"
    if not isinstance(req["plots"], list) or not set(req["plots"]) <= set(PLOTS):
        return f"plots: not a list of {sorted(PLOTS)}"
    if not isinstance(req["modes"], list) or not all(
        isinstance(m, str) and m.isidentifier() for m in req["modes"]
    ):
        return "modes: not a list of mode names"
    return None


def serve(stdin: IO[str], stdout: IO[str]) -> None:
    """Answer each request line of `stdin` on `stdout` until the end of `stdin`; never raises on a
    request (an unreadable one, a missing file, a failed plot: its reply says so)."""
    for line in stdin:
        try:
            req = json.loads(line)
            problem = request_problem(req)
            if problem is not None:
                raise ValueError(problem)
            written = draw(Path(req["run_dir"]), req["plots"], req["modes"])
            reply: dict[str, Any] = {"written": written, "error": None}
        except Exception as exc:  # any failure goes back to the flight, which draws the plots itself
            reply = {"written": [], "error": f"{type(exc).__name__}: {exc}"}
        stdout.write(json.dumps(reply) + "\n")
        stdout.flush()


def main() -> int:
    """The child: ignore SIGINT, import the plotting modules at once, then serve stdin."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import flightstack.analysis.report  # noqa: F401  matplotlib: what this process is for, loaded early

    serve(sys.stdin, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
