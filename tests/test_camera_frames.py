"""A mode's camera frames in the run directory (flightstack.recording.camera_frames) and the tap that
records them (flightstack.runtime.camera_tap): what is written reads back (tags, stamps, the picture), a
record cut short waits and a damaged one stops the reading, the writer never blocks and keeps its size
bound; a simulated-lab flight records at most IMAGE_HZ frames per camera and mission second, and the export
writes them as foxglove.CompressedImage at their stamps."""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest

from flightstack.config.rig import resolved_document
from flightstack.hal import Frame
from flightstack.recording import camera_frames
from flightstack.recording.camera_frames import (
    IMAGE_HZ,
    MAGIC,
    CameraFrame,
    FrameTail,
    FrameWriter,
    encode_record,
    images_name,
    read_frames,
)
from flightstack.recording.files import is_run_file
from flightstack.recording.mcap_export import export_mcap
from flightstack.runtime.camera_tap import CameraTap, FrameKeeper, keep_frames, release_frames
from tests.conftest import random_recording
from tests.mcap_read import read_mcap


def _picture(rng: np.random.Generator, grey: bool = False) -> np.ndarray:
    """A smooth 120 × 160 picture (JPEG keeps it within a few grey levels)."""
    y, x = np.mgrid[0:120, 0:160]
    base = (x + 2 * y).astype(float) % 256
    if grey:
        return base.astype(np.uint8)
    return np.stack([base, 255 - base, np.full_like(base, rng.integers(0, 256))], axis=-1).astype(np.uint8)


def _decode(jpeg: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img


def test_written_frames_read_back_with_their_tags_stamps_and_picture(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    path = tmp_path / images_name("none")
    w = FrameWriter(path)
    shown = [(1, 0.5, _picture(rng), False, None), (2, 0.52, _picture(rng, grey=True), True, 3)]
    for drone, stamp, img, damaged, since in shown:
        assert w.offer(drone, stamp, img, damaged, since)
    w.close()
    frames, error = read_frames(path)
    assert error is None and w.counts["written"] == 2 and w.bytes == path.stat().st_size
    for fr, (drone, stamp, img, damaged, since) in zip(frames, shown, strict=True):
        assert (fr.drone, fr.stamp, fr.damaged, fr.since_loss) == (drone, stamp, damaged, since)
        back = _decode(fr.jpeg)
        assert back.shape == img.shape  # a grey camera's frame stays grey
        assert np.abs(back.astype(int) - img.astype(int)).mean() < 3.0


def test_a_record_cut_short_waits_and_a_damaged_one_stops_the_reading(tmp_path: Path) -> None:
    path = tmp_path / images_name("none")
    one = encode_record(CameraFrame(1, 0.0, False, None, b"\xff\xd8jpeg"))
    path.write_bytes(MAGIC + one + one[:10])
    tail = FrameTail(path)
    assert [f.jpeg for f in tail.read()] == [b"\xff\xd8jpeg"]
    with open(path, "ab") as fh:  # the writer finishes the record: it is read now
        fh.write(one[10:])
    assert len(tail.read()) == 1 and tail.error is None
    with open(path, "ab") as fh:
        fh.write(b"XXXX" + one[4:] + one)
    assert tail.read() == [] and "damaged record" in str(tail.error)
    tail.close()
    (tmp_path / "other").write_bytes(b"not frames at all")
    frames, error = read_frames(tmp_path / "other")
    assert frames == [] and "no magic" in str(error)
    assert read_frames(tmp_path / "missing") == ([], None)


def test_the_writer_never_blocks_drops_when_full_and_keeps_its_size_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    release = threading.Event()

    def slow_encode(image: np.ndarray, quality: int = 75) -> bytes:
        release.wait(10.0)
        return b"\xff" * 1000

    monkeypatch.setattr(camera_frames, "encode_jpeg", slow_encode)
    w = FrameWriter(tmp_path / images_name("none"), queue_frames=2, max_bytes=len(MAGIC) + 2500)
    img = np.zeros((4, 4), np.uint8)
    offered = [w.offer(1, k * 0.5, img, False, None) for k in range(10)]  # the thread holds one
    assert offered.count(False) == w.counts["dropped"] >= 10 - 3
    release.set()
    w.close()
    assert w.counts["written"] == 2 and w.counts["over_size"] == 10 - 2 - w.counts["dropped"]
    assert (tmp_path / images_name("none")).stat().st_size <= len(MAGIC) + 2500


def test_frames_keepers_nest_and_each_observer_removes_its_own() -> None:
    cam = SimpleNamespace(latest=lambda: Frame(1.0, np.zeros((2, 2), np.uint8), None))
    agent = SimpleNamespace(camera=cam, cfg=SimpleNamespace(drone_id=1))
    first = keep_frames([agent])
    second = keep_frames([agent])
    assert agent.camera.latest() is not None
    assert first[1].last is not None and second[1].last is not None
    release_frames([agent], first)  # the inner one: the outer one now wraps the camera itself
    assert isinstance(agent.camera, FrameKeeper) and agent.camera is second[1] and agent.camera.inner is cam
    release_frames([agent], second)
    assert agent.camera is cam


def test_the_tap_records_at_most_image_hz_per_camera_and_mission_second(tmp_path: Path) -> None:
    """Frames every 1/30 s for 3 s: 2 per camera and second are recorded, the first at once."""
    rng = np.random.default_rng(1)
    clock = {"t": 0.0}
    agents = [
        SimpleNamespace(
            camera=SimpleNamespace(latest=lambda: Frame(clock["t"], _picture(rng), None)),
            cfg=SimpleNamespace(drone_id=i),
        )
        for i in (1, 2)
    ]
    fleet: Any = SimpleNamespace(agents=agents)
    rec: Any = SimpleNamespace(mode="none")
    tap = CameraTap(tmp_path)
    tap.start(fleet, rec)
    for k in range(90):
        clock["t"] = k / 30
        for a in agents:
            a.camera.latest()
        tap.on_tick(fleet, rec, k + 1)
    tap.close(rec)
    assert all(not isinstance(a.camera, FrameKeeper) for a in agents)
    frames, _ = read_frames(tmp_path / images_name("none"))
    for i in (1, 2):
        stamps = np.array([f.stamp for f in frames if f.drone == i])
        assert len(stamps) == 3 * IMAGE_HZ and stamps[0] == 0.0
        assert np.all(np.diff(stamps) >= 1 / IMAGE_HZ - 1e-9)
    assert tap.written == {"none": 12} and tap.dropped == {"none": 0}


def test_a_simulated_lab_flight_records_its_frames_and_the_export_writes_them(tmp_path: Path) -> None:
    """paper_experiment on lab-sim (rendered cameras) for 1.5 s in process: images_none.jpgs holds each
    camera's frames at most IMAGE_HZ a second, and `export` writes them as JPEG CompressedImages in each
    camera's frame at their stamps on the mode's time base."""
    import yaml

    from flightstack.config.mission import load_mission
    from flightstack.runtime.flight import Flight

    doc = resolved_document("paper_experiment", rig="lab-sim")
    doc.update(duration_s=1.5, compare_modes=["none"])
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    run = tmp_path / "run"
    with Flight(load_mission(tmp_path / "m.yaml"), run) as flight:
        rec = flight.fly_mode("none")
    assert is_run_file(images_name("none"))
    frames, error = read_frames(run / images_name("none"))
    assert error is None
    for i in (1, 2):
        stamps = [f.stamp for f in frames if f.drone == i]
        assert 1 <= len(stamps) <= 1.5 * IMAGE_HZ + 1
        assert np.all(np.diff(stamps) >= 1 / IMAGE_HZ - 1e-9)
    export_mcap(run, tmp_path / "o.mcap")
    got = read_mcap(tmp_path / "o.mcap")
    base = float(rec.wall_t[0] - rec.t[0]) if rec.wall_t[0] else 0.0
    for i in (1, 2):
        msgs = got.topics[f"/none/drone{i}/image"]
        mine = [f for f in frames if f.drone == i]
        assert got.schemas[f"/none/drone{i}/image"][0] == "foxglove.CompressedImage"
        assert [m.data for _, m in msgs] == [f.jpeg for f in mine]
        assert {(m.format, m.frame_id) for _, m in msgs} == {("jpeg", f"none/drone{i}/camera")}
        assert [lt for lt, _ in msgs] == [int((base + f.stamp) * 1e9) for f in mine]


def test_a_run_without_camera_frames_exports_no_images(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    random_recording("none", [1], 10).save(run / "timeseries_none.npz")
    summary = export_mcap(run, tmp_path / "o.mcap")
    assert summary.mode_images == {"none": 0}
    assert not any(t.endswith("/image") for t in read_mcap(tmp_path / "o.mcap").topics)
