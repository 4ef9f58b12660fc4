"""The live MCAP (flightstack.recording.mcap_live): written while the run goes, every value equal to the
run's own recording, and what a kill leaves: the flight's process killed, the follower finishes the file;
both killed, the file reads up to its last complete chunk. Runs tests/live_run_writer.py (a run directory
written tick by tick at 500 Hz) and reads the file as a user's tool would (tests/mcap_read.py)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.exceptions import McapError

from flightstack.cli import app as cli
from flightstack.recording.files import LIVE_MCAP_FILE, TORN_MCAP_FILE
from flightstack.recording.mcap_live import AUTOGROUP, FLUSH_PERIOD_S, NICENESS, POLL_S, STALL_S, LiveMcap
from flightstack.recording.mcap_writer import CHUNK_BYTES
from flightstack.recording.rows import read_rows
from flightstack.recording.run_reader import load_run, resolved_mission
from tests.conftest import REPO, Bound, eventually, process_running
from tests.mcap_read import assert_mcap_holds, read_mcap, read_mcap_stream

RATE_HZ = 500.0
pytestmark = pytest.mark.system


def _start(out: Path, n: int) -> tuple[subprocess.Popen[str], int]:
    """The writer process and its follower's pid."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.live_run_writer", str(out), str(n), str(RATE_HZ)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("follower "), (line, proc.stderr.read() if proc.stderr else "")
    return proc, int(line.split()[1])


def _rows_at_least(proc: subprocess.Popen[str], k: int) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("rows ") and int(line.split()[1]) >= k:
            return
    raise AssertionError(f"the writer ended before {k} rows")


def _ticks(path: Path) -> int:
    """Ticks readable so far; 0 before the follower (its imports take seconds on a busy machine) creates
    the file."""
    if not path.exists():
        return 0
    return len(read_mcap_stream(path).topics.get("/none/tick", []))


def test_written_during_the_run_and_equal_to_the_recording(tmp_path: Path) -> None:
    """Readable while the run goes on (by the `mcap` package's stream reader; its default reader fails on
    a file without its summary: docs/logs.md), then equal to the run's recording. The run is stopped once
    ticks are readable: the follower yields the cores to the flight, so on a loaded machine its first chunk
    may take tens of seconds (up to 240 s of run here)."""
    out = tmp_path / "run"
    n = 120_000  # 240 s at most
    proc, follower = _start(out, n)
    try:
        assert eventually(lambda: _ticks(out / LIVE_MCAP_FILE) > 0 or proc.poll() is not None, 300.0)
        seen = _ticks(out / LIVE_MCAP_FILE)
        assert proc.poll() is None and seen > 0, seen  # readable while the writer is still writing
        with pytest.raises(McapError):  # by the stream reader only: the default one needs the summary
            read_mcap(out / LIVE_MCAP_FILE)
        (tmp_path / "stop").touch()
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert '"error": null' in stdout.splitlines()[-1], stdout
    (stopped,) = [int(x.split()[1]) for x in stdout.splitlines() if x.startswith("stopped ")]
    mission, _ = resolved_mission(out)
    got = read_mcap(out / LIVE_MCAP_FILE)
    recs = load_run(out, mission)
    assert recs["none"].ticks_done == stopped >= seen
    assert_mcap_holds(recs, got)
    assert {"metrics.json", "recording.json", "mission_resolved.yaml"} <= set(got.attachments)
    assert not process_running(follower)
    print(f"live MCAP: {seen} of {stopped} ticks readable while the run went on")


def _priority(pid: int) -> tuple[int, str]:
    """(nice value, the autogroup line "/autogroup-N nice K") of a running process; the line is empty for a
    process in no autogroup (the root task group: a process in init's session, as under some CI runners)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    nice = int(stat[stat.rindex(")") + 2 :].split()[16])  # field 19 of proc(5), after "pid (comm) "
    return nice, Path(f"/proc/{pid}/autogroup").read_text().strip()


def _lowered(pid: int) -> tuple[int, str] | None:
    """(nice, the autogroup line's end " nice K") of a running process; None once it has ended."""
    try:
        nice, group = _priority(pid)
    except OSError:
        return None
    return nice, group[group.rfind(" nice ") :]


@pytest.mark.skipif(
    not AUTOGROUP.exists(), reason="this kernel has no autogroup scheduling (/proc/self/autogroup)"
)
def test_the_follower_yields_the_cores_to_the_flight(tmp_path: Path) -> None:
    """nice +10 for the follower and for its session's autogroup (it is alone in its session): under
    autogroup scheduling its own nice alone would count only within that session."""
    # a flight of 60 s, killed once seen: the follower sets its group back to 0 at the end of the flight,
    # which on a busy machine may come before its imports are done (it sets its own nice, then its group's)
    proc, follower = _start(tmp_path / "run", 30_000)
    lowered = (NICENESS, f" nice {NICENESS}")
    try:
        seen = eventually(
            lambda: _lowered(follower) == lowered or proc.poll() is not None or not process_running(follower),
            60.0,
        )
        nice, group = _priority(follower) if process_running(follower) else (None, "(ended)")
        mine = _priority(os.getpid())
    finally:
        proc.kill()
        proc.wait(timeout=10)
    assert eventually(lambda: not process_running(follower), 60.0), "the follower did not finish"
    assert seen and nice == NICENESS and group.endswith(lowered[1]), (nice, group, proc.returncode)
    # its own group, not the flight's (which may be no autogroup at all: the root task group)
    assert group.split()[0] != (mine[1].split() or ["root task group"])[0], (group, mine)
    # once the flight is over it finishes at a fair share: the group back to nice 0, without privilege
    probe = (
        "from pathlib import Path; from flightstack.recording import mcap_live as m\n"
        "m.lower_priority(); a = Path('/proc/self/autogroup').read_text().split()[-1]\n"
        "ok = m.set_group_nice(0); print(a, ok, Path('/proc/self/autogroup').read_text().split()[-1])"
    )
    # as root: with no capability left (setpriv), as an unprivileged user's process would be
    drop = ["setpriv", "--bounding-set=-all", "--inh-caps=-all"] if os.getuid() == 0 else []
    if drop and shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: cannot drop the capabilities to check the last step")
    r = subprocess.run(
        [*drop, sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, cwd=REPO,
        start_new_session=True,
    )  # fmt: skip
    assert r.stdout.split() == [str(NICENESS), "True", "0"], (r.stdout, r.stderr[-2000:])


def test_a_killed_flight_leaves_a_finished_file(tmp_path: Path) -> None:
    """SIGKILL of the flight's process: the follower reads end of file on its pipe, copies every row the
    row stream has and writes the summary; the file reads with its indexes."""
    out = tmp_path / "run"
    proc, follower = _start(out, 60_000)
    try:
        _rows_at_least(proc, 1500)
        proc.kill()
        proc.wait(timeout=10)
        t0 = time.monotonic()
        assert eventually(lambda: not process_running(follower), 60.0), "the follower did not finish"
        finished = time.monotonic() - t0
    finally:
        proc.kill()
    _, rows = read_rows(out / "timeseries_none.rows")
    mission, _ = resolved_mission(out)
    recs = load_run(out, mission)
    got = read_mcap(out / LIVE_MCAP_FILE)  # complete: summary and indexes
    assert recs["none"].ticks_done == len(rows) >= 1000
    assert_mcap_holds(recs, got)
    print(f"flight killed at {len(rows)} rows: the follower finished the file in {finished:.2f} s")


def test_a_killed_follower_loses_at_most_its_open_chunk(tmp_path: Path) -> None:
    """SIGKILL of the flight and its follower at once: the file reads front to back up to its last
    complete chunk; what is lost is at most the open chunk (≤ FLUSH_PERIOD_S of wall time) and the rows not
    polled yet (POLL_S), and what was read equals the recording."""
    out = tmp_path / "run"
    proc, follower = _start(out, 60_000)
    try:  # once the follower has caught up (its start, imports included, takes seconds on a busy machine)
        assert eventually(lambda: _ticks(out / LIVE_MCAP_FILE) >= 1000, 90.0)
        os.kill(follower, signal.SIGKILL)
        proc.kill()
        proc.wait(timeout=10)
    finally:
        proc.kill()
    _, rows = read_rows(out / "timeseries_none.rows")
    got = read_mcap_stream(out / LIVE_MCAP_FILE)
    assert got.error is not None  # cut short: no summary
    mission, _ = resolved_mission(out)
    rec = load_run(out, mission)["none"]
    have = len(got.topics["/none/tick"])
    lost_s = (len(rows) - have) / RATE_HZ
    print(
        f"follower killed at {len(rows)} rows on disk: {have} ticks readable, {lost_s:.2f} s lost "
        f"(bound {FLUSH_PERIOD_S + POLL_S:.1f} s + scheduling; chunks of at most {CHUNK_BYTES} B)"
    )
    assert have > 0 and lost_s <= FLUSH_PERIOD_S + POLL_S + 2.0, (have, len(rows))  # 2 s: a loaded machine
    # a chunk may end inside a block (its ticks written before its drones): compare the whole ticks
    whole = min(len(got.topics[t]) for t in ["/none/tick", *(f"/none/drone{i}" for i in rec.drone_ids)])
    for t in ["/none/tick", *(f"/none/drone{i}" for i in rec.drone_ids)]:
        got.topics[t] = got.topics[t][:whole]
    last = got.topics["/none/tick"][-1][0]
    got.topics["/none/tf"] = [m for m in got.topics["/none/tf"] if m[0] <= last]
    rec.ticks_done = whole
    assert_mcap_holds({"none": rec.truncated()}, got)


def test_run_writes_the_live_mcap_unless_told_not_to(tmp_path: Path) -> None:
    argv = ["run", "paper_sim", "--modes", "none", "--duration", "0.1", "--no-progress"]
    assert cli.main([*argv, "--out", str(tmp_path / "a")]) == 0
    mission, _ = resolved_mission(tmp_path / "a")
    assert_mcap_holds(load_run(tmp_path / "a", mission), read_mcap(tmp_path / "a" / LIVE_MCAP_FILE))
    assert cli.main([*argv, "--out", str(tmp_path / "b"), "--no-live-mcap"]) == 0
    assert not (tmp_path / "b" / LIVE_MCAP_FILE).exists()


RUN_ARGV = ["run", "paper_sim", "--modes", "none", "--duration", "2", "--no-progress"]
"""A short simulated run with the live MCAP (in this process: the test reaches its writer)."""


def _run_with_writer(
    out: Path, monkeypatch: pytest.MonkeyPatch, before_finish: Callable[[LiveMcap], None]
) -> tuple[int, list[int]]:
    """`flightstack run` into `out`, `before_finish(writer)` called once the flight is over and before the
    run tells its writer so (the writer is still following the run directory, as during the flight);
    (exit code, the writer's pid)."""
    finish = LiveMcap.finish
    pids: list[int] = []

    def patched(self: LiveMcap, *args: Any, **kwargs: Any) -> dict[str, Any]:
        pids.append(self.proc.pid)
        before_finish(self)
        return finish(self, *args, **kwargs)

    monkeypatch.setattr(LiveMcap, "finish", patched)
    try:
        code = cli.main([*RUN_ARGV, "--out", str(out)])
    finally:
        for pid in pids:  # never leave a writer stopped or running
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
                os.kill(pid, signal.SIGKILL)
    return code, pids


def _raw(msgs: list[tuple[int, Any]]) -> list[tuple[int, bytes]]:
    return [(when, msg.SerializeToString()) for when, msg in msgs]


def _error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


def test_a_killed_writer_is_reported_and_report_finalises_its_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """SIGKILL of the writer while it follows the run, once its file holds messages: the run says so in
    one `error:` line and exits 1 (docs/getting-started.md, exit codes); the file does not open in a
    seeking reader until `flightstack report` finalises it, with every message a stream read recovers."""
    out = tmp_path / "run"
    path = out / LIVE_MCAP_FILE

    def kill(writer: LiveMcap) -> None:
        assert eventually(lambda: _ticks(path) > 0, 120.0), "the writer wrote no chunk"
        writer.proc.kill()
        writer.proc.wait(timeout=10)

    code, _ = _run_with_writer(out, monkeypatch, kill)
    err = capfd.readouterr().err
    assert code == 1, err
    (line,) = _error_lines(err)
    assert "live MCAP" in line and "SIGKILL" in line and f"flightstack report {out}" in line, line
    torn = read_mcap_stream(path)
    assert torn.error is not None and torn.messages > 0
    with pytest.raises(Exception):  # noqa: B017 (whatever the torn bytes make of the summary)
        read_mcap(path)
    torn_bytes = path.stat().st_size
    assert cli.main(["report", str(out), "--no-plots"]) == 0
    report_out = capfd.readouterr().out
    got = read_mcap(path)  # the standard reader: summary, indexes
    assert got.messages == torn.messages and set(got.topics) == set(torn.topics)
    for topic, msgs in torn.topics.items():  # the same messages (bytes: NaN != NaN), perhaps reordered
        assert sorted(_raw(got.topics[topic])) == sorted(_raw(msgs)), topic
    assert (out / TORN_MCAP_FILE).stat().st_size == torn_bytes  # the original kept beside it
    assert f"{torn.messages} messages recovered" in report_out, report_out
    assert cli.main(["report", str(out), "--no-plots"]) == 0  # a whole file is left as it is
    assert "finalised" not in capfd.readouterr().out
    print(f"writer killed: {torn.messages} messages recovered by report")


def test_a_stopped_writer_is_killed_soon_after_the_flight(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
    safety_bound: Bound,
) -> None:
    """SIGSTOP of the writer during the run: the run ends within 5 s of telling it the flight is over
    (it is killed after STALL_S without progress), says so in one `error:` line, exits 1 and leaves no
    process behind."""
    out = tmp_path / "run"
    told: list[float] = []

    def stop(writer: LiveMcap) -> None:
        os.kill(writer.proc.pid, signal.SIGSTOP)
        told.append(time.monotonic())

    code, pids = _run_with_writer(out, monkeypatch, stop)
    ended = time.monotonic() - told[0]
    err = capfd.readouterr().err
    assert code == 1, err
    (line,) = _error_lines(err)
    assert "live MCAP" in line and "no progress" in line, line
    assert not process_running(pids[0])
    safety_bound(
        f"the run's end after the flight's with its writer stopped (stall time {STALL_S:g} s)",
        ended,
        5.0,
        "s",
    )
