"""The recording is written as the run goes (flightstack.recording.run_dir): row streams readable
after a
kill, events once each, an injected ENOSPC stops the recording and not the flight, `--out` is checked
before takeoff, and `flightstack report` rebuilds metrics.json from any recording."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from flightstack.analysis.metrics import mode_metrics
from flightstack.cli import app as cli
from flightstack.config.mission import Mission, load_mission
from flightstack.config.rig import resolved_document
from flightstack.faults.fly import write_run
from flightstack.recording import files
from flightstack.recording import run_dir as recorder
from flightstack.recording.run_dir import (
    ROWS_SUFFIX,
    STREAM_FIELDS,
    ModeWriter,
    RowLayout,
    RunWriter,
    event_line,
    load_run,
    read_rows,
)
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording
from flightstack.runtime.flight import Flight, resolved_mission_yaml
from tests.conftest import MISSIONS, REPO, random_recording

LAB = MISSIONS / "paper_experiment.yaml"


def _lab(duration_s: float = 2.0) -> Mission:
    """The simulated lab (safety on, 20 Hz), mode `none` only."""
    return load_mission(LAB, {"duration_s": duration_s, "compare_modes": ["none"]})


def _fake(n_ticks: int, ids: tuple[int, ...] = (1, 2), seed: int = 0) -> Recording:
    """A recording of n_ticks random ticks (every array filled), not yet marked done."""
    rec = random_recording("none", list(ids), n_ticks, seed)
    rec.ticks_done = 0
    return rec


def _small_sim_mission(tmp_path: Path, duration_s: float = 1.0) -> Path:
    """paper_sim (ideal simulation, 500 Hz) flying mode `none` only for duration_s."""
    m = resolved_document("paper_sim")
    m.update(duration_s=duration_s, compare_modes=["none"])
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    return path


def _lines(run_dir: Path) -> list[bytes]:
    return (run_dir / "events.jsonl").read_bytes().splitlines(keepends=True)


def test_row_stream_drops_a_torn_or_zero_filled_tail(tmp_path: Path) -> None:
    rec = _fake(30)
    layout = RowLayout.of_recording(rec, ARRAY_FIELDS)
    path = tmp_path / f"x{ROWS_SUFFIX}"
    blocks = [layout.pack({f: getattr(rec, f)[a:b] for f in ARRAY_FIELDS}, a) for a, b in ((0, 12), (12, 20))]
    with open(path, "wb") as fh:
        fh.write(layout.header() + b"".join(blocks) + blocks[0][: layout.dtype.itemsize // 2])  # kill
    meta, rows = read_rows(path)
    assert meta == {"mode": "none", "drone_ids": [1, 2]} and len(rows) == 20
    for f in ARRAY_FIELDS:
        np.testing.assert_array_equal(rows[f], getattr(rec, f)[:20])
    with open(path, "r+b") as fh:  # power loss: the size grew, the data did not arrive (zeros)
        fh.truncate(len(layout.header()) + len(b"".join(blocks)) + 3 * layout.dtype.itemsize)
    assert len(read_rows(path)[1]) == 20


def test_append_writes_blocks_as_the_run_goes_cheaply(tmp_path: Path) -> None:
    n = 4000
    src = _fake(n, (1, 2, 3))
    rec = Recording.empty("none", [1, 2, 3], n)
    run = RunWriter(tmp_path, block_period_s=0.05)
    w = run.mode("none", [1, 2, 3], n)
    costs = []
    for k in range(n):
        for f in ARRAY_FIELDS:
            getattr(rec, f)[k] = getattr(src, f)[k]
        rec.ticks_done = k + 1
        t0 = time.perf_counter()
        w.append(rec, k + 1)
        costs.append(time.perf_counter() - t0)
        if k == 99:  # 100 ticks, then 0.1 s of wall time: the next append hands them over
            time.sleep(0.1)
    assert run.drain()
    _, rows = read_rows(w.rows_path)  # before close: what a kill would leave
    assert len(rows) >= 100 and rows["t"][-1] == rec.t[len(rows) - 1]
    assert np.median(costs) * 1e6 < 5.0  # µs: nothing to do on most ticks
    assert np.mean(costs) * 1e6 < 50.0  # with a 2000-tick block packed now and then
    rec.e_c[:] = src.e_c  # the runner fills the true errors at the end
    w.close(rec)
    assert not w.rows_path.exists() and run.status() == {"complete": True, "reason": None}
    run.close()
    back = load_run(tmp_path)["none"]
    for f in ARRAY_FIELDS:
        np.testing.assert_array_equal(getattr(back, f), getattr(rec, f))


def test_an_event_written_at_once_is_not_written_again(tmp_path: Path) -> None:
    rec = _fake(10)
    with RunWriter(tmp_path) as run:
        w = run.mode("none", [1, 2], 10)
        end = {"t": 0.5, "event": "end", "reason": "mission complete", "mode": "none"}
        w.event(end)  # the runner flushes it before landing
        assert run.drain()
        assert _lines(tmp_path) == [event_line(end)]
        rec.events += [{"t": 0.1, "event": "neighbours", "drone": 1, "mode": "none"}, end]
        rec.events.append({"t": 0.6, "event": "landed", "drone": 1, "height_m": float("nan"), "mode": "none"})
        w.append(rec, 5)
        w.close(rec)
    assert Counter(_lines(tmp_path)) == Counter(event_line(e) for e in rec.events)
    assert json.loads(_lines(tmp_path)[-1])["height_m"] is None  # strict JSON


def test_run_mode_records_as_it_flies(tmp_path: Path) -> None:
    mission = _lab(2.0)
    with Flight(mission, tmp_path) as flight:
        rec = flight.fly_mode("none")
        assert flight.writer is not None
        m = flight.writer.write_metrics(mode_metrics(rec, mission))
    assert rec.ticks_done == 40 and m["recording"] == {"complete": True, "reason": None}
    assert not list(tmp_path.glob(f"*{ROWS_SUFFIX}"))
    state = json.loads((tmp_path / "recording.json").read_text())
    assert state["state"] == "closed" and state["modes"]["none"]["rows_written"] == 40
    back = load_run(tmp_path, mission)["none"]
    for f in ARRAY_FIELDS:
        np.testing.assert_array_equal(getattr(back, f), getattr(rec, f))
    assert Counter(_lines(tmp_path)) == Counter(event_line(e) for e in rec.events)
    # every event once; on disk in the order they happened (safety events as they are logged), which is
    # not rec.events' order (the runner appends the safety log at the end)
    key = lambda e: json.dumps(e, sort_keys=True)  # noqa: E731
    assert sorted(map(key, back.events)) == sorted(map(key, json.loads(json.dumps(rec.events))))
    assert back.vision_rejections == rec.vision_rejections and back.wall_seconds == rec.wall_seconds


def _fly_with_writer(mission: Mission, writer: Any) -> Recording:
    """Mode `none` through the runner with a writer the test controls (a block every tick, a process
    killed at the end): below the Flight, which always opens its own."""
    from flightstack.runtime.fleet import assemble_fleet
    from flightstack.runtime.runner import run_mode

    with assemble_fleet(mission, "none", None, backend=None, bus=None, agent_ids=None, writer=writer) as f:
        return run_mode(f, writer=writer)


def test_a_full_disk_stops_the_recording_not_the_flight(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = recorder._write_bytes
    calls = [0]

    def disk_fills_up(fd: int, data: bytes) -> None:
        calls[0] += 1
        if calls[0] > 12:  # after the header, the takeoff's safety events and a few blocks
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd, data)

    monkeypatch.setattr(recorder, "_write_bytes", disk_fills_up)
    mission = _lab(2.0)
    ids = [d.id for d in mission.drones]
    run = RunWriter(tmp_path, block_period_s=0.0)  # a block every tick: the disk fills mid-flight
    w = run.mode("none", ids, 40)
    rec = _fly_with_writer(mission, w)
    assert rec.ticks_done == 40 and rec.error is None and not rec.interrupted  # flown to the end
    assert {e["drone"] for e in rec.events if e["event"] == "landed"} == set(ids)
    stopped = [e for e in rec.events if e["event"] == "recording_stopped"]
    assert len(stopped) == 1 and "ENOSPC" in stopped[0]["reason"], stopped
    assert 0 < stopped[0]["ticks_written"] < 40
    m = run.write_metrics(mode_metrics(rec, mission))
    run.close()
    assert m["recording"]["complete"] is False and "No space left on device" in m["recording"]["reason"]
    assert json.loads((tmp_path / "metrics.json").read_text())["recording"] == m["recording"]
    state = json.loads((tmp_path / "recording.json").read_text())
    assert state["complete"] is False and "ENOSPC" in state["reason"]
    for line in _lines(tmp_path):  # what reached events.jsonl is whole lines
        json.loads(line)
    back = load_run(tmp_path, mission)["none"]  # the final npz (not a stream write) made it here
    assert back.ticks_done == 40


class _KilledAtTheEnd:
    """A ModeWriter whose process dies right after the run's last block reached the disk: close() only
    flushes (no final npz, recording.json never closed)."""

    def __init__(self, inner: ModeWriter) -> None:
        self.inner = inner

    def append(self, rec: Recording, upto_tick: int) -> None:
        self.inner.append(rec, upto_tick)

    def event(self, ev: dict[str, Any]) -> None:
        self.inner.event(ev)

    def add_event_source(self, source: Any) -> None:
        self.inner.add_event_source(source)

    def close(self, rec: Recording | None = None) -> None:
        assert rec is not None
        self.inner.flush(rec)


def test_report_rebuilds_metrics_of_a_killed_run_from_its_row_stream(tmp_path: Path) -> None:
    mission = _lab(2.0)
    (tmp_path / "mission_resolved.yaml").write_text(resolved_mission_yaml(mission))
    run = RunWriter(tmp_path)
    w = run.mode("none", [d.id for d in mission.drones], 40)
    rec = _fly_with_writer(mission, _KilledAtTheEnd(w))
    run._queue.put(None)  # the writer thread dies with the process; nothing is closed
    assert (tmp_path / f"timeseries_none{ROWS_SUFFIX}").is_file()
    assert not (tmp_path / "timeseries_none.npz").exists() and not (tmp_path / "metrics.json").exists()
    assert cli.main(["report", str(tmp_path)]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["recording"]["complete"] is False and "cut short" in m["recording"]["reason"]
    want = mode_metrics(rec, mission)
    got = m["modes"]["none"]
    assert got["ticks"] == 40 and "cut short" in got["error"]
    for key in (
        "mean_sq_error",
        "mean_position_error_m",
        "max_fence_excursion_m",
        "rms_control_position_error_m",
    ):
        assert got[key] == pytest.approx(want[key], rel=1e-12), key  # e_c, e_e recomputed from the poses
    assert got["safety_event_counts"] == want["safety_event_counts"]
    for name in ("trajectory.png", "error_ec.png", "error_ee.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"


def test_sigkill_of_flightstack_sim_loses_at_most_1s(tmp_path: Path) -> None:
    """A real kill: `flightstack sim` SIGKILLed mid-flight; the row stream holds every tick up to
    < 1 s of wall time before the kill, and `report` rebuilds metrics from it."""
    out = tmp_path / "run"
    mission = _small_sim_mission(tmp_path, 600.0)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "flightstack.cli.app",
            "sim",
            str(mission),
            "--out",
            str(out),
            "--no-progress",
        ],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        rows = out / f"timeseries_none{ROWS_SUFFIX}"
        deadline = time.monotonic() + 60
        while not rows.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(2.3)
        killed_at = time.time()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    _, data = read_rows(rows)
    lost_s = killed_at - float(data["wall_t"][-1])
    assert len(data) > 100 and 0 <= lost_s < 1.0, (len(data), lost_s)
    assert set(STREAM_FIELDS) <= set(data.dtype.names or ())
    assert cli.main(["report", str(out), "--no-plots"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["modes"]["none"]["ticks"] == len(data) and m["recording"]["complete"] is False
    assert np.isfinite(m["modes"]["none"]["mean_sq_error"])


def test_sim_writes_a_complete_run_and_report_reproduces_its_metrics(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert cli.main(["sim", str(_small_sim_mission(tmp_path)), "--out", str(out), "--no-progress"]) == 0
    first = json.loads((out / "metrics.json").read_text())
    assert first["recording"] == {"complete": True, "reason": None}
    assert (
        not list(out.glob(f"*{ROWS_SUFFIX}"))
        and Recording.load(out / "timeseries_none.npz").ticks_done == 500
    )
    assert cli.main(["report", str(out)]) == 0
    assert json.loads((out / "metrics.json").read_text()) == first


def test_sim_on_a_full_disk_flies_on_and_exits_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def full(fd: int, data: bytes) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(recorder, "_write_bytes", full)
    out = tmp_path / "run"
    assert cli.main(["sim", str(_small_sim_mission(tmp_path)), "--out", str(out), "--no-progress"]) == 1
    assert "recording incomplete: No space left on device" in capsys.readouterr().err
    m = json.loads((out / "metrics.json").read_text())
    assert m["modes"]["none"]["ticks"] == 500 and m["recording"]["complete"] is False


def test_out_is_checked_before_anything_takes_off(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_flight(*args: object, **kwargs: object) -> None:
        raise AssertionError("took off")

    monkeypatch.setattr("flightstack.runtime.flight.Flight.fly", no_flight)
    monkeypatch.setattr("flightstack.comms.factory.make_bus", no_flight)
    mission = _small_sim_mission(tmp_path)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert cli.main(["sim", str(mission), "--out", str(blocker / "run")]) == 2
    assert "cannot create the directory" in capsys.readouterr().err
    m = yaml.safe_load(mission.read_text())
    eps = {p: f"tcp/127.0.0.1:{7400 + int(p)}" for p in "123"}
    m["bus"] = {"kind": "zenoh", "zenoh": {"endpoints": eps, "security": "plaintext"}}
    zmission = tmp_path / "zenoh.yaml"
    zmission.write_text(yaml.safe_dump(m))
    assert cli.main(["agent", str(zmission), "--id", "1", "--mode", "none", "--out", str(blocker / "a")]) == 2
    assert "nothing took off" in capsys.readouterr().err

    class Usage:
        free = 10_000_000  # bytes: less than MIN_FREE_BYTES

    monkeypatch.setattr(files.shutil, "disk_usage", lambda path: Usage)
    assert cli.main(["sim", str(mission), "--out", str(tmp_path / "run")]) == 2
    assert "only 10.0 MB free" in capsys.readouterr().err
    assert (
        cli.main(["agent", str(zmission), "--id", "1", "--mode", "none", "--out", str(tmp_path / "a")]) == 2
    )
    assert "MIN_FREE_BYTES" in capsys.readouterr().err


def test_faults_write_run_reports_a_full_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int, data: bytes) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    mission = _lab()
    rec = _fake(20, tuple(d.id for d in mission.drones))
    rec.ticks_done = 20
    rec.events = [{"t": 0.0, "event": "end", "reason": "mission complete", "mode": "none"}]
    assert write_run(tmp_path / "ok", mission, rec) == []
    assert len(_lines(tmp_path / "ok")) == 1
    monkeypatch.setattr(recorder, "_write_bytes", full)
    problems = write_run(tmp_path / "full", mission, rec)
    assert len(problems) == 1 and "recording incomplete: No space left on device" in problems[0]
    assert json.loads((tmp_path / "full" / "metrics.json").read_text())["recording"]["complete"] is False


def test_datasets_file_round_trip(tmp_path: Path) -> None:
    """datasets.npz: what the experiment writes (save_datasets) is what report and view read back."""
    from flightstack.learning.training import ExpertData, load_datasets, save_datasets

    rng = np.random.default_rng(3)
    data = [ExpertData(i, (0.0, 1.0), rng.normal(size=(5, 4)), rng.normal(size=(5, 4)), np.arange(5) * i)
            for i in (3, 1)]  # fmt: skip
    save_datasets(tmp_path / "d.npz", data)
    back = load_datasets(tmp_path / "d.npz")
    assert [d.drone_id for d in back] == [1, 3]
    for d in back:
        ref = next(x for x in data if x.drone_id == d.drone_id)
        for k in ("X", "Y", "ticks"):
            np.testing.assert_array_equal(getattr(d, k), getattr(ref, k))
    assert load_datasets(tmp_path / "missing.npz") == []


def test_video_counts_never_stand_between_the_flight_and_its_recording() -> None:
    """A camera that raises on the way to the recording gives no counts, not an exception."""
    from types import SimpleNamespace

    from flightstack.runtime.runner import stream_counts

    class Counting:
        def latest(self) -> None:
            return None

        def stream_counts(self) -> dict[str, int]:
            return {"frames": 3}

    class Broken(Counting):
        def stream_counts(self) -> dict[str, int]:
            raise OSError("receiver gone")

    cams = {1: Counting(), 2: Broken()}

    def camera(i: int) -> object:
        if i == 3:
            raise KeyError(i)  # never started
        return cams[i]

    fleet = SimpleNamespace(ids=[1, 2, 3], backend=SimpleNamespace(camera=camera))
    assert stream_counts(fleet) == {"1": {"frames": 3}}  # type: ignore[arg-type]
