"""The layouts shipped with the docs (docs/foxglove/flightstack-<mode>.json) are the ones
flightstack.recording.foxglove_layout makes, one per mode, and name only topics the MCAP writer writes
(that real runs hold them: tests/test_foxglove_logs.py)."""

from __future__ import annotations

import json
from pathlib import Path

from flightstack.config.types import Mode
from flightstack.recording.camera_frames import MAGIC, CameraFrame, encode_record, images_name
from flightstack.recording.foxglove_layout import (
    LAYOUT_DRONES,
    layout,
    layout_json,
    layout_name,
    layout_topics,
)
from flightstack.recording.mcap_export import export_mcap
from tests.conftest import REPO, random_recording
from tests.mcap_read import read_mcap

SHIPPED = REPO / "docs" / "foxglove"


def test_one_layout_per_mode_is_shipped_as_the_module_makes_it() -> None:
    """Stale or missing: `python -m flightstack.recording.foxglove_layout docs/foxglove` rewrites them."""
    assert sorted(p.name for p in SHIPPED.glob("*.json")) == sorted(layout_name(m.value) for m in Mode)
    for mode in Mode:
        assert (SHIPPED / layout_name(mode.value)).read_text() == layout_json(mode.value), mode


def test_a_layout_names_only_topics_the_writer_writes(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    random_recording("dgp", list(LAYOUT_DRONES), 30).save(run / "timeseries_dgp.npz")
    records = [encode_record(CameraFrame(i, 0.1, False, None, b"\xff\xd8")) for i in LAYOUT_DRONES]
    (run / images_name("dgp")).write_bytes(MAGIC + b"".join(records))
    (run / "events.jsonl").write_text(json.dumps({"t": 0.0, "event": "end", "reason": "x", "mode": "dgp"}))
    export_mcap(run, tmp_path / "o.mcap")
    written = set(read_mcap(tmp_path / "o.mcap").topics)
    named = layout_topics(layout("dgp"))
    assert named <= written, named - written
    assert {"/dgp/pose/target", "/dgp/pose/drones", "/dgp/scene", "/dgp/drone1/image", "/dgp/events"} <= named
