"""`flightstack export RUN_DIR --mcap FILE` (flightstack.recording.mcap_export), read back with
the mcap library: the topics and their schemas, one message per tick, times in order on the mission
clock, values equal to the recording (NaN as null), events as foxglove.Log with their level, the CLI's
exit codes, and the shipped Foxglove schemas."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from flightstack.cli import app as cli
from flightstack.config.rig import resolved_document
from flightstack.recording.mcap_export import CLOCK_FIELDS, POSE_FIELDS, export_mcap
from flightstack.recording.mcap_messages import FOXGLOVE_SCHEMAS, LOG_ERROR, LOG_INFO, LOG_WARNING
from flightstack.recording.run_reader import load_run
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording
from tests.conftest import random_recording

SCHEMA_DIR = resources.files("flightstack.recording") / "schemas" / "foxglove"
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


def _read(path: Path) -> dict[str, Any]:
    """Every message of an MCAP file: per topic [(log_time, publish_time, decoded JSON)], the schema
    name and encodings per topic, the file order of (topic, log_time), attachments and metadata."""
    by_topic: dict[str, list[tuple[int, int, Any]]] = defaultdict(list)
    schemas: dict[str, tuple[str, str, str]] = {}
    order: list[tuple[str, int]] = []

    def strict(c: str) -> None:
        raise AssertionError(f"not valid JSON: {c}")

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            assert schema is not None
            by_topic[channel.topic].append(
                (msg.log_time, msg.publish_time, json.loads(msg.data, parse_constant=strict))
            )
            schemas[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
            order.append((channel.topic, msg.log_time))
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    return {
        "topics": by_topic,
        "schemas": schemas,
        "order": order,
        "attachments": attachments,
        "meta": metadata,
    }


@pytest.fixture(scope="module")
def fake_mcap(fake_run: Path) -> tuple[Any, dict[str, Any]]:
    out = fake_run.parent / "fake.mcap"
    return export_mcap(fake_run, out), _read(out)


def _expected_topics(mode: str, ids: list[int], rec: Recording) -> dict[str, str]:
    """Topic -> schema name of a mode, from ARRAY_FIELDS at run time."""
    exp = {f"/{mode}/clock": "flightstack.clock", f"/{mode}/events": "foxglove.Log"}
    for entity in ["target", *(f"drone{i}" for i in ids), *(f"drone{i}/estimate" for i in ids)]:
        exp[f"/{mode}/{entity}/tf"] = "foxglove.FrameTransform"
        exp[f"/{mode}/{entity}/pose"] = "foxglove.PoseInFrame"
    for f in ARRAY_FIELDS:
        if f in POSE_FIELDS or f in CLOCK_FIELDS:
            continue
        a = getattr(rec, f)
        per_drone = a.ndim >= 2 and a.shape[1] == len(ids)
        for topic in [f"/{mode}/drone{i}/{f}" for i in ids] if per_drone else [f"/{mode}/{f}"]:
            exp[topic] = f"flightstack.{f}"
    return exp


def test_shipped_foxglove_schemas_parse_and_carry_their_license() -> None:
    names = sorted(p.name for p in SCHEMA_DIR.iterdir())
    assert {f"{n}.json" for n in FOXGLOVE_SCHEMAS} <= set(names)
    for name in names:
        if name.endswith(".json"):
            doc = json.loads((SCHEMA_DIR / name).read_text(encoding="utf-8"))
            assert doc["title"] == f"foxglove.{name[: -len('.json')]}"
            assert doc["type"] == "object" and "timestamp" in doc["properties"]
    assert "MIT License" in (SCHEMA_DIR / "LICENSE").read_text(encoding="utf-8")
    readme = (SCHEMA_DIR / "README.md").read_text(encoding="utf-8")
    assert "foxglove/foxglove-sdk" in readme and "86ab07b03a1086055eaba38941f31fa7702af005" in readme


def test_topics_schemas_and_one_message_per_tick(
    fake_run: Path, fake_mcap: tuple[Any, dict[str, Any]]
) -> None:
    summary, got = fake_mcap
    recs = load_run(fake_run)
    expected: dict[str, str] = {}
    for mode, rec in recs.items():
        expected |= _expected_topics(mode, rec.drone_ids, rec)
    assert {t: s[0] for t, s in got["schemas"].items()} == expected
    assert summary.schemas == expected
    assert all(s[1:] == ("jsonschema", "json") for s in got["schemas"].values())
    for topic, msgs in got["topics"].items():
        want = len(recs[topic.split("/")[1]].events) if topic.endswith("/events") else N
        assert len(msgs) == want == summary.topics[topic], topic
    per_drone = [t for t in expected if t.startswith("/none/drone") and t.endswith("/e_c")]
    assert sum(len(got["topics"][t]) for t in per_drone) == N * len(IDS)  # ticks x drones
    assert summary.messages == len(got["order"])
    assert summary.mode_ticks == {"dgp": N, "none": N}


def test_times_on_the_mission_clock_monotonic_per_topic_and_in_file_order(
    fake_run: Path, fake_mcap: tuple[Any, dict[str, Any]]
) -> None:
    _, got = fake_mcap
    recs = load_run(fake_run)
    times = [t for _, t in got["order"]]
    assert times == sorted(times)  # written in time order across topics
    for topic, msgs in got["topics"].items():
        log = [m[0] for m in msgs]
        assert log == sorted(log), topic
        assert all(lt == pt for lt, pt, _ in msgs), topic
    base_none = float(recs["none"].wall_t[0]) - float(recs["none"].t[0])
    clock = got["topics"]["/none/clock"]
    assert [m[0] for m in clock] == [int((base_none + t) * 1e9) for t in recs["none"].t]
    assert [m[2]["t"] for m in clock] == recs["none"].t.tolist()
    assert [m[0] for m in got["topics"]["/dgp/clock"]] == [
        int(t * 1e9) for t in recs["dgp"].t
    ]  # wall_t 0: base 0
    tf = got["topics"]["/none/drone1/tf"][5]
    assert tf[2]["timestamp"]["sec"] * 1_000_000_000 + tf[2]["timestamp"]["nsec"] == tf[0]
    assert json.loads(got["meta"]["flightstack"]["time_base_s"]) == {"none": base_none, "dgp": 0.0}
    assert got["attachments"]["metrics.json"] == b'{"modes": {}}\n'


def _check_values(rec: Recording, mode: str, topics: dict[str, list[tuple[int, int, Any]]]) -> None:
    """Poses, e_c and every loop-health array present equal the recording (NaN as null)."""

    def same(x: Any, v: float) -> bool:
        return x is None if not math.isfinite(v) else x == v

    for j, i in enumerate(rec.drone_ids):
        for entity, a in (
            (f"drone{i}", rec.g_wi[:, j]),
            (f"drone{i}/estimate", rec.g_bar_w[:, j]),
            ("target", rec.g_w0),
        ):
            for k, (_, _, m) in enumerate(topics[f"/{mode}/{entity}/tf"]):
                x, y, z, th = a[k].tolist()
                assert m["translation"] == {"x": x, "y": y, "z": z}
                assert m["rotation"] == {"x": 0.0, "y": 0.0, "z": math.sin(th / 2), "w": math.cos(th / 2)}
                assert (m["parent_frame_id"], m["child_frame_id"]) == ("world", f"{mode}/{entity}")
            for k, (_, _, m) in enumerate(topics[f"/{mode}/{entity}/pose"]):
                assert m["frame_id"] == "world"
                assert list(m["pose"]["position"].values()) == a[k, :3].tolist()
        for k, (_, _, m) in enumerate(topics[f"/{mode}/drone{i}/e_c"]):
            assert list(m) == ["x", "y", "z", "theta"]
            assert all(same(x, v) for x, v in zip(m.values(), rec.e_c[k, j].tolist(), strict=True)), (k, m)
        for f in ("frame_age", "pose_age"):
            if f in ARRAY_FIELDS:
                vals = [m["value"] for _, _, m in topics[f"/{mode}/drone{i}/{f}"]]
                assert all(same(x, v) for x, v in zip(vals, getattr(rec, f)[:, j].tolist(), strict=True))
    for f in ("loop_period", "loop_compute"):
        if f in ARRAY_FIELDS:
            vals = [m["value"] for _, _, m in topics[f"/{mode}/{f}"]]
            assert all(same(x, v) for x, v in zip(vals, getattr(rec, f).tolist(), strict=True))
    visible = [m["value"] for _, _, m in topics[f"/{mode}/drone{rec.drone_ids[0]}/visible"]]
    assert visible == rec.visible[:, 0].tolist()


def test_values_equal_the_recording_and_nan_is_null(
    fake_run: Path, fake_mcap: tuple[Any, dict[str, Any]]
) -> None:
    _, got = fake_mcap
    recs = load_run(fake_run)
    for mode, rec in recs.items():
        _check_values(rec, mode, got["topics"])
    nan_tick = got["topics"]["/none/drone2/e_c"][3][2]
    assert nan_tick["theta"] is None and nan_tick["x"] == recs["none"].e_c[3, 1, 0]


def test_events_are_foxglove_logs_with_levels_in_time_order(fake_mcap: tuple[Any, dict[str, Any]]) -> None:
    _, got = fake_mcap
    logs = got["topics"]["/none/events"]
    base = WALL0
    by_text = {json.loads(m["message"].split("  ", 1)[1])["event"] + str(m["level"]): m for _, _, m in logs}
    assert len(by_text) == len(EVENTS)
    for ev, level in zip(EVENTS, LEVELS, strict=True):
        m = by_text[f"{ev['event']}{level}"]
        assert json.loads(m["message"].split("  ", 1)[1]) == {**ev, "mode": "none"}
        assert m["name"] == ev.get("source", "flightstack") and m["file"] == "" and m["line"] == 0
    when = {json.loads(m["message"].split("  ", 1)[1])["event"] + str(m["level"]): lt for lt, _, m in logs}
    assert when["landed2"] == int((base + 0.2) * 1e9)  # sorted before the safety event at 0.5 s
    assert when["safety3"] == int((base + 0.5) * 1e9)
    assert when["bus presence2"] == when["landed2"]  # no t: the time of the event before it in the file
    assert when["mocap4"] == when["landed2"]  # a monotonic stamp is not on the mission clock: likewise
    assert [m[2]["level"] for m in got["topics"]["/dgp/events"]] == [LOG_INFO]


def test_modes_pick_a_subset_in_their_order(fake_run: Path, tmp_path: Path) -> None:
    summary = export_mcap(fake_run, tmp_path / "dgp.mcap", modes=["dgp"])
    got = _read(tmp_path / "dgp.mcap")
    assert summary.modes == ["dgp"] and {t.split("/")[1] for t in got["topics"]} == {"dgp"}


def test_foxglove_messages_validate_against_the_shipped_schemas(
    fake_mcap: tuple[Any, dict[str, Any]],
) -> None:
    import jsonschema  # a dev dependency (pyproject.toml)

    _, got = fake_mcap
    for topic, (name, _, _) in got["schemas"].items():
        if name.startswith("foxglove."):
            schema = json.loads((SCHEMA_DIR / f"{name.split('.')[1]}.json").read_text(encoding="utf-8"))
            for _, _, m in got["topics"][topic][:5]:
                jsonschema.validate(m, schema)


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
    assert {t.split("/")[1] for t in _read(out)["topics"]} == {"none"}
    missing = tmp_path / "nothing here"
    assert cli.main(["export", str(missing), "--mcap", str(tmp_path / "a.mcap")]) == 2
    assert str(missing) in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["export", str(tmp_path / "empty"), "--mcap", str(tmp_path / "a.mcap")]) == 2
    assert "no recording" in capsys.readouterr().err
    assert cli.main(["export", str(fake_run), "--mcap", str(tmp_path / "a.mcap"), "--modes", "local"]) == 2
    assert "no mode local" in capsys.readouterr().err
    assert not (tmp_path / "a.mcap").exists()


def test_a_real_short_run_exports_its_recording(tmp_path: Path) -> None:
    """paper_sim (ideal rig, 500 Hz), mode none for 0.05 s, flown in process, then exported by the CLI."""
    doc = resolved_document("paper_sim")
    doc.update(duration_s=0.05, compare_modes=["none"])
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    run, out = tmp_path / "run", tmp_path / "run.mcap"
    assert cli.main(["sim", str(tmp_path / "m.yaml"), "--out", str(run), "--no-progress"]) == 0
    assert cli.main(["export", str(run), "--mcap", str(out)]) == 0
    rec = load_run(run)["none"]
    got = _read(out)
    assert {t: s[0] for t, s in got["schemas"].items()} == _expected_topics("none", rec.drone_ids, rec)
    assert len(got["topics"]["/none/drone1/e_c"]) == rec.ticks_done > 0
    _check_values(rec, "none", got["topics"])
    levels = {
        json.loads(m["message"].split("  ", 1)[1])["event"]: m["level"]
        for _, _, m in got["topics"]["/none/events"]
    }
    assert levels["end"] == LOG_INFO and levels["landed"] == LOG_INFO
    assert {"metrics.json", "mission_resolved.yaml"} <= set(got["attachments"])


def test_a_recording_without_ticks_exports_its_events(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    Recording.empty("none", list(IDS), 0).save(run / "timeseries_none.npz")
    (run / "events.jsonl").write_text(
        json.dumps({"t": 0.0, "event": "end", "reason": "interrupted", "mode": "none"})
    )
    summary = export_mcap(run, tmp_path / "o.mcap")
    got = _read(tmp_path / "o.mcap")
    assert summary.mode_ticks == {"none": 0} and summary.messages == 1
    assert [m[2]["level"] for m in got["topics"]["/none/events"]] == [LOG_WARNING]


def test_run_writes_mcap_after_the_landing_and_refuses_an_existing_file_before_flying(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`run … --mcap FILE`: the same file `export` writes, from the recording, once the drones are down;
    an existing FILE without --force is refused before anything flies (exit 2, no run directory)."""
    out, mcap_file = tmp_path / "run", tmp_path / "run.mcap"
    argv = ["run", "paper_sim", "--modes", "none", "--duration", "0.1", "--no-progress"]
    assert cli.main([*argv, "--out", str(out), "--mcap", str(mcap_file)]) == 0
    assert "MCAP: " in capsys.readouterr().out
    got = _read(mcap_file)
    rec = load_run(out)["none"]
    assert len(got["topics"]["/none/target/pose"]) == rec.ticks_done == 50
    poses = [m["pose"]["position"] for _, _, m in got["topics"]["/none/drone1/pose"]]
    np.testing.assert_array_equal([[p["x"], p["y"], p["z"]] for p in poses], rec.g_wi[:, 0, :3])
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
