"""`flightstack export RUN_DIR --mcap FILE` (flightstack.recording.mcap_export) and the typed messages
both MCAP writers share (mcap_schema, mcap_writer), read back with the mcap package and protobuf classes
built from the file's own schemas (tests/mcap_read.py): topics and schemas, one message per tick and
drone, times on the mission clock, every value equal to the recording (NaN included), events as
foxglove.Log with their level, the CLI's exit codes; and the vectorised encoder against the protobuf
library's."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from flightstack.cli import app as cli
from flightstack.config.rig import resolved_document
from flightstack.recording import mcap_schema
from flightstack.recording.mcap_export import export_mcap
from flightstack.recording.mcap_writer import SCENE_PERIOD_S, TF_PERIOD_S
from flightstack.recording.run_reader import load_run
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording
from tests.conftest import random_recording
from tests.mcap_read import McapContents, assert_mcap_holds, read_mcap, world_positions

IDS = (1, 2)
N = 40
WALL0 = 1_700_000_000.25
"""Epoch (s) of the synthetic recordings' first tick."""
EVENTS = [
    {"t": 0.0, "event": "neighbours", "drone": 1, "dropped": [], "added": [2]},
    {
        "t": 0.5,
        "event": "safety",
        "drone": 2,
        "kind": "pose_stale_hover",
        "detail": "pose 0.3 s old",
        "source": "safety",
    },
    {"t": 0.2, "event": "landed", "drone": 1, "height_m": 0.0},  # out of order in the file: sorted
    {
        "event": "bus presence",
        "sender": 2,
        "what": "joined",
        "monotonic": 12345.6,
    },  # no t: after the one before
    {
        "t": 99.0,
        "clock": "monotonic",
        "event": "mocap",
        "kind": "reader_error",
        "detail": "natnet",
        "source": "mocap",
    },
    {"t": 0.9, "event": "NOT LANDED", "drone": 2, "height_m": 0.4},
    {"t": 0.95, "event": "end", "reason": "exception: RuntimeError: boom"},
]
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4  # foxglove.LogLevel (its protobuf enum values)
LEVELS = [LOG_INFO, LOG_WARNING, LOG_INFO, LOG_INFO, LOG_ERROR, LOG_ERROR, LOG_ERROR]


def _fake(mode: str, seed: int, wall: bool = True) -> Recording:
    """N random ticks at 20 Hz of every array of ARRAY_FIELDS; e_c of drone 2 at tick 3 has a NaN θ."""
    rec = random_recording(mode, list(IDS), N, seed)
    rec.wall_t[:] = WALL0 + 3.0 * seed + rec.t if wall else 0.0
    rec.e_c[3, 1, 3] = np.nan
    rec.ticks_done = N
    return rec


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run directory with modes none (wall_t set) and dgp (wall_t zero), events and a metrics.json."""
    run = tmp_path_factory.mktemp("fake") / "run"
    run.mkdir()
    _fake("none", 0).save(run / "timeseries_none.npz")
    _fake("dgp", 1, wall=False).save(run / "timeseries_dgp.npz")
    lines = [json.dumps({**ev, "mode": "none"}) for ev in EVENTS] + [
        json.dumps({"t": 0.0, "event": "safety tick", "ticks": 0, "mode": "dgp"})
    ]
    (run / "events.jsonl").write_text("\n".join(lines) + "\n")
    (run / "metrics.json").write_text('{"modes": {}}\n')
    return run


@pytest.fixture(scope="module")
def fake_mcap(fake_run: Path) -> tuple[Any, McapContents]:
    out = fake_run.parent / "fake.mcap"
    return export_mcap(fake_run, out), read_mcap(out)


def _topics(mode: str, ids: list[int]) -> dict[str, str]:
    return {
        f"/{mode}/tick": "flightstack.Tick",
        **{f"/{mode}/drone{i}": "flightstack.DroneState" for i in ids},
        f"/{mode}/tf": "foxglove.FrameTransforms",
        f"/{mode}/pose/target": "foxglove.PoseInFrame",
        f"/{mode}/pose/drones": "foxglove.PosesInFrame",
        f"/{mode}/pose/estimates": "foxglove.PosesInFrame",
        f"/{mode}/scene": "foxglove.SceneUpdate",
        f"/{mode}/events": "foxglove.Log",
    }


def _log(m: Any) -> dict[str, Any]:
    """The event JSON at the end of a foxglove.Log's text."""
    return json.loads(m.message.split("  ", 1)[1])


def test_topics_schemas_and_one_message_per_tick_and_drone(fake_run: Path, fake_mcap: Any) -> None:
    summary, got = fake_mcap
    recs = load_run(fake_run)
    expected = _topics("none", list(IDS)) | _topics("dgp", list(IDS))
    assert {t: s[0] for t, s in got.schemas.items()} == expected
    assert all(s[1:] == ("protobuf", "protobuf") for s in got.schemas.values())
    for topic, msgs in got.topics.items():
        mode = topic.split("/")[1]
        want = N  # 20 Hz: a transform and poses per tick
        if topic.endswith("/events"):
            want = len(recs[mode].events)
        elif topic.endswith("/scene"):  # t = 0 and 1 s of the 2 s
            want = math.ceil(N / 20 / SCENE_PERIOD_S)
        assert len(msgs) == want == summary.topics[topic], topic
    assert summary.messages == got.messages and summary.mode_ticks == {"dgp": N, "none": N}
    assert got.attachments["metrics.json"] == b'{"modes": {}}\n'
    meta = got.metadata["flightstack"]
    assert json.loads(meta["time_base_s"]) == {"none": WALL0, "dgp": 0.0} and meta["modes"] == ",".join(recs)


def test_every_value_equals_the_recording_nan_included(fake_run: Path, fake_mcap: Any) -> None:
    _, got = fake_mcap
    recs = load_run(fake_run)
    assert_mcap_holds(recs, got)
    nan_tick = got.topics["/none/drone2"][3][1]
    assert math.isnan(nan_tick.e_c[3]) and nan_tick.e_c[0] == recs["none"].e_c[3, 1, 0]


def test_events_are_foxglove_logs_with_levels_at_their_mission_time(fake_mcap: Any) -> None:
    _, got = fake_mcap
    logs = got.topics["/none/events"]
    assert [_log(m) for _, m in logs] == [{**ev, "mode": "none"} for ev in EVENTS]  # file order
    assert [m.level for _, m in logs] == LEVELS
    assert [m.name for _, m in logs] == [ev.get("source", "flightstack") for ev in EVENTS]
    when = [lt for lt, _ in logs]
    assert when[1] == int((WALL0 + 0.5) * 1e9) and when[2] == int((WALL0 + 0.2) * 1e9)
    assert when[3] == when[2]  # no t: the time of the event before it in the file
    assert when[4] == when[3]  # a monotonic stamp is not on the mission clock: likewise
    assert all(m.timestamp.seconds * 10**9 + m.timestamp.nanos == lt for lt, m in logs)
    assert [m.level for _, m in got.topics["/dgp/events"]] == [LOG_INFO]


def test_transforms_are_thinned_to_their_period_on_a_fast_recording(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    rec = random_recording("none", [1], 200, 3)
    rec.t[:] = np.arange(200) * 0.002  # 500 Hz
    rec.wall_t[:] = 0.0  # log time = mission time
    rec.save(run / "timeseries_none.npz")
    export_mcap(run, tmp_path / "o.mcap")
    got = read_mcap(tmp_path / "o.mcap")
    stamps = [m.transforms[0].timestamp for _, m in got.topics["/none/tf"]]
    tf_t = np.array([s.seconds + s.nanos / 1e9 for s in stamps])
    assert len(got.topics["/none/tick"]) == 200
    assert len(tf_t) == math.ceil(200 * 0.002 / TF_PERIOD_S - 1e-9)
    assert np.all(np.diff(tf_t) >= TF_PERIOD_S - 1e-6)
    assert_mcap_holds(load_run(run), got)


def test_modes_pick_a_subset_in_their_order(fake_run: Path, tmp_path: Path) -> None:
    summary = export_mcap(fake_run, tmp_path / "dgp.mcap", modes=["dgp"])
    got = read_mcap(tmp_path / "dgp.mcap")
    assert summary.modes == ["dgp"] and {t.split("/")[1] for t in got.topics} == {"dgp"}


def _classes() -> dict[str, Any]:
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(mcap_schema.file_descriptor_set()).file:
        pool.Add(fd)
    names = (mcap_schema.TICK, mcap_schema.DRONE)
    return {n: message_factory.GetMessageClass(pool.FindMessageTypeByName(n)) for n in names}


def _columns(fields: tuple[str, ...], n: int) -> dict[str, np.ndarray]:
    """Every field of a schema for n messages of drone 4, every value nonzero."""
    rec = random_recording("none", [4], n, 11)
    cols: dict[str, np.ndarray] = {"drone": np.full(n, 4)}
    for f in fields:
        if f == "drone":
            continue
        a = np.asarray(getattr(rec, f))
        a = a[:, 0] if mcap_schema.per_drone(f) else a
        cols[f] = np.where(a == 0, 1, a) if a.dtype.kind != "b" else np.ones(n, dtype=bool)
    return cols


def test_the_vectorised_encoder_writes_what_the_protobuf_library_writes() -> None:
    """Every field nonzero (proto3 leaves zeros out): byte for byte the library's SerializeToString;
    with zeros, NaN and ±inf: the library decodes every value back."""
    cls = _classes()
    n = 50
    schemas = ((mcap_schema.TICK, mcap_schema.TICK_FIELDS), (mcap_schema.DRONE, mcap_schema.DRONE_FIELDS))
    for schema, fields in schemas:
        cols = _columns(fields, n)
        msgs = mcap_schema.encode(schema, cols)
        assert msgs.shape == (n, mcap_schema.message_size(schema))
        for k in (0, n - 1):
            ref = cls[schema]()
            for f in fields:
                v = np.asarray(cols[f])[k]
                if v.ndim:
                    getattr(ref, f).extend(v.tolist())
                else:
                    setattr(ref, f, v.item())
            assert ref.SerializeToString() == msgs[k].tobytes(), (schema, k)
    cols = _columns(mcap_schema.DRONE_FIELDS, 2)
    cols["V_cmd"][0] = [0.0, np.nan, np.inf, -np.inf]
    cols["visible"][0], cols["n_fused"][0], cols["t"][0] = False, -3, 0.0
    m = cls[mcap_schema.DRONE].FromString(mcap_schema.encode(mcap_schema.DRONE, cols)[0].tobytes())
    assert m.V_cmd[0] == 0.0 and math.isnan(m.V_cmd[1]) and list(m.V_cmd)[2:] == [np.inf, -np.inf]
    assert (m.visible, m.n_fused, m.t, m.drone) == (False, -3, 0.0, 4)


def test_the_schema_follows_the_recordings_arrays() -> None:
    """A field added to timeseries.ARRAY_LAYOUT is written without a change to the schema's code."""
    tick, drone = _classes().values()
    assert [f.name for f in tick.DESCRIPTOR.fields] == list(mcap_schema.TICK_FIELDS)
    assert [f.name for f in drone.DESCRIPTOR.fields] == list(mcap_schema.DRONE_FIELDS)
    assert set(mcap_schema.TICK_FIELDS) | set(mcap_schema.DRONE_FIELDS) == {*ARRAY_FIELDS, "drone"}
    assert set(mcap_schema.FIELD_DOCS) == {*ARRAY_FIELDS, "drone"}


def test_cli_refuses_to_overwrite_unless_force_and_names_a_bad_run_dir(
    fake_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"keep")
    assert cli.main(["export", str(fake_run), "--mcap", str(out)]) == 2
    assert out.read_bytes() == b"keep" and "--force" in capsys.readouterr().err
    assert cli.main(["export", str(fake_run), "--mcap", str(out), "--force", "--modes", "none"]) == 0
    printed = capsys.readouterr().out
    assert "topics" in printed and "messages" in printed and "/none/" in printed
    assert {t.split("/")[1] for t in read_mcap(out).topics} == {"none"}
    missing = tmp_path / "nothing here"
    assert cli.main(["export", str(missing), "--mcap", str(tmp_path / "a.mcap")]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["export", str(tmp_path / "empty"), "--mcap", str(tmp_path / "a.mcap")]) == 2
    assert "no recording" in capsys.readouterr().err
    assert cli.main(["export", str(fake_run), "--mcap", str(tmp_path / "a.mcap"), "--modes", "local"]) == 2
    assert "no mode local" in capsys.readouterr().err
    assert not (tmp_path / "a.mcap").exists()


def test_export_writes_only_regular_files_outside_the_run(
    fake_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--force at a directory, a FIFO, a device node (made by the test in its own folder, as root) or a
    file of the run itself: exit 2 in one line naming it, nothing replaced."""
    import os
    import stat

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    targets = [tmp_path, fifo, *sorted(p for p in fake_run.iterdir() if p.is_file())[:1]]
    if os.geteuid() == 0:
        node = tmp_path / "null-like"
        os.mknod(node, 0o600 | stat.S_IFCHR, os.makedev(1, 3))  # /dev/null's numbers, in the test's folder
        targets.append(node)
    for target in targets:
        before = target.lstat()
        for flag in ("--mcap", "--csv"):
            assert cli.main(["export", str(fake_run), flag, str(target), "--force"]) == 2, target
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and str(target) in err[0], err
        after = target.lstat()
        assert (after.st_mode, after.st_ino, after.st_size) == (before.st_mode, before.st_ino, before.st_size)
    print(f"refused: {[t.name for t in targets]}")


@pytest.fixture(scope="module")
def short_paper_sim(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """paper_sim (ideal rig, 500 Hz), mode none for 0.05 s, flown in process, then exported by the CLI:
    (run directory, MCAP file)."""
    tmp_path = tmp_path_factory.mktemp("paper_sim")
    doc = resolved_document("paper_sim")
    doc.update(duration_s=0.05, compare_modes=["none"])
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    run, out = tmp_path / "run", tmp_path / "run.mcap"
    assert cli.main(["sim", str(tmp_path / "m.yaml"), "--out", str(run), "--no-progress"]) == 0
    assert cli.main(["export", str(run), "--mcap", str(out)]) == 0
    return run, out


def test_a_real_short_run_exports_its_recording(short_paper_sim: tuple[Path, Path]) -> None:
    run, out = short_paper_sim
    recs = load_run(run)
    got = read_mcap(out)
    assert {t: s[0] for t, s in got.schemas.items()} == _topics("none", recs["none"].drone_ids)
    assert recs["none"].ticks_done == 25
    assert_mcap_holds(recs, got)
    levels = {_log(m)["event"]: m.level for _, m in got.topics["/none/events"]}
    assert levels["end"] == LOG_INFO and levels["landed"] == LOG_INFO
    assert {"metrics.json", "mission_resolved.yaml"} <= set(got.attachments)


def test_on_the_ideal_rig_the_drones_appear_above_the_target_in_world(
    short_paper_sim: tuple[Path, Path],
) -> None:
    """The ideal rig's Σw has z along the cameras' optical axis, down (paper_sim: drones at z = −1.5 m):
    composed as a 3-D panel composes /none/tf, every drone is 1.5 m above the target in `world`, and the
    scene holds the target's markers, in the target's frame."""
    _, out = short_paper_sim
    got = read_mcap(out)
    for _, msg in got.topics["/none/tf"]:
        at = world_positions(msg)
        for i in (1, 2, 3):
            assert at[f"none/drone{i}"][2] - at["none/target"][2] == pytest.approx(1.5, abs=0.01)
    (_, scene), *_ = got.topics["/none/scene"]
    (markers,) = [e for e in scene.entities if e.id == "markers"]
    assert markers.frame_id == "none/target" and markers.frame_locked and len(markers.spheres) == 4
    assert not [e for e in scene.entities if e.id == "fence"]  # the ideal rig flies without safety


def test_a_recording_without_ticks_exports_its_events(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    Recording.empty("none", list(IDS), 0).save(run / "timeseries_none.npz")
    (run / "events.jsonl").write_text(
        json.dumps({"t": 0.0, "event": "end", "reason": "interrupted", "mode": "none"})
    )
    summary = export_mcap(run, tmp_path / "o.mcap")
    got = read_mcap(tmp_path / "o.mcap")
    assert summary.mode_ticks == {"none": 0} and summary.messages == 1
    assert [m.level for _, m in got.topics["/none/events"]] == [LOG_WARNING]


def test_run_writes_mcap_after_the_landing_and_refuses_an_existing_file_before_flying(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`run … --mcap FILE`: the same file `export` writes, from the recording, once the drones are down;
    an existing FILE without --force is refused before anything flies (exit 2, no run directory)."""
    out, mcap_file = tmp_path / "run", tmp_path / "run.mcap"
    argv = ["run", "paper_sim", "--modes", "none", "--duration", "0.1", "--no-progress"]
    assert cli.main([*argv, "--out", str(out), "--mcap", str(mcap_file)]) == 0
    assert "MCAP: " in capsys.readouterr().out
    got = read_mcap(mcap_file)
    recs = load_run(out)
    assert recs["none"].ticks_done == 50
    assert_mcap_holds(recs, got)
    other = tmp_path / "other"
    assert cli.main([*argv, "--out", str(other), "--mcap", str(mcap_file)]) == 2
    assert "exists (--force replaces it); nothing took off" in capsys.readouterr().err
    assert not other.exists()


def test_the_viewer_shows_every_event_at_the_level_and_time_the_export_gives_it() -> None:
    """One severity and one mission-time rule (flightstack.events) for both viewers: the Rerun text log's
    level is the MCAP Log level in Rerun's names, and an event on another clock has no mission time."""
    from flightstack.events import mission_time
    from flightstack.viewer.mode_logger import event_level as rerun_level
    from flightstack.viewer.mode_logger import event_time

    names = {LOG_INFO: "INFO", LOG_WARNING: "WARN", LOG_ERROR: "ERROR"}
    assert [rerun_level(ev) for ev in EVENTS] == [names[lv] for lv in LEVELS]
    times = [event_time(ev, -1.0) for ev in EVENTS]
    assert times == [-1.0 if mission_time(ev) is None else ev["t"] for ev in EVENTS]
    assert mission_time(EVENTS[4]) is None and event_time(EVENTS[4], 7.0) == 7.0  # monotonic t = 99
