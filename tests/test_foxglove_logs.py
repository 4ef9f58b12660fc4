"""The run's MCAP shows in Foxglove without a custom layout: a paper_sim run and an emulated-lab run,
flown by `flightstack run` with the live MCAP, carry the bodies' poses as foxglove.PoseInFrame and
PosesInFrame in a frame tree whose `world` is z up (the drones above the target on both rigs), the scene
as foxglove.SceneUpdate and, on the emulated lab, each camera's frames as foxglove.CompressedImage at most
IMAGE_HZ a second within the size budget per minute (docs/logs.md); every topic the shipped layouts name
is in the recordings (the image topics: in the emulated lab's; the ideal rig has no cameras)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flightstack.recording.camera_frames import BUDGET_BYTES_PER_MIN, IMAGE_HZ
from flightstack.recording.files import LIVE_MCAP_FILE
from flightstack.recording.foxglove_layout import layout_name, layout_topics
from flightstack.recording.run_reader import load_run
from tests.conftest import REPO, run_cli
from tests.mcap_read import McapContents, read_mcap, world_positions

pytestmark = pytest.mark.system

LAB_S = 6.0
"""Mission time (s) of the emulated-lab flight."""
FOXGLOVE = {
    "/none/tf": "foxglove.FrameTransforms",
    "/none/pose/target": "foxglove.PoseInFrame",
    "/none/pose/drones": "foxglove.PosesInFrame",
    "/none/pose/estimates": "foxglove.PosesInFrame",
    "/none/scene": "foxglove.SceneUpdate",
    "/none/events": "foxglove.Log",
}
IMAGES = {f"/none/drone{i}/image": "foxglove.CompressedImage" for i in (1, 2)}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """rig name -> the run directory of mode none: paper_sim for 2 s, paper_experiment on the emulated lab
    for LAB_S s."""
    out = {rig: tmp_path_factory.mktemp(rig) / "run" for rig in ("ideal", "emulated-lab")}
    argv = {
        "ideal": ["run", "paper_sim", "--duration", "2"],
        "emulated-lab": ["run", "paper_experiment", "--rig", "emulated-lab", "--duration", str(LAB_S)],
    }
    for rig, args in argv.items():
        r = run_cli(*args, "--modes", "none", "--out", str(out[rig]), "--no-progress", timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def mcaps(runs: dict[str, Path]) -> dict[str, McapContents]:
    return {rig: read_mcap(run / LIVE_MCAP_FILE) for rig, run in runs.items()}


def test_poses_scene_and_on_the_emulated_lab_images_are_foxglove_messages(
    runs: dict[str, Path], mcaps: dict[str, McapContents]
) -> None:
    for rig, got in mcaps.items():
        schemas = {t: s[0] for t, s in got.schemas.items()}
        want = FOXGLOVE | (IMAGES if rig == "emulated-lab" else {})
        assert want.items() <= schemas.items(), rig
        assert not [t for t in schemas if t.endswith("/image")] or rig == "emulated-lab"
        tf = len(got.topics["/none/tf"])
        assert tf > 0 and all(
            len(got.topics[f"/none/pose/{w}"]) == tf for w in ("target", "drones", "estimates")
        )
        assert len(got.topics["/none/scene"]) >= 1
        print(f"{rig}: {got.messages} messages on {len(got.topics)} topics: "
              f"{ {t: len(m) for t, m in got.topics.items()} }")  # fmt: skip
    scene = mcaps["emulated-lab"].topics["/none/scene"][0][1]
    assert {e.id for e in scene.entities} == {"fence", "markers"}  # safety on: the fence is drawn


def test_world_is_z_up_the_drones_above_the_target_on_both_rigs(mcaps: dict[str, McapContents]) -> None:
    """Composed as a 3-D panel composes the transforms: on the ideal rig (Σw's z down the optical axis)
    and on the emulated lab (Σw the motion-capture frame, z up), every drone is above the target."""
    for rig, got in mcaps.items():
        gaps = []
        for _, msg in got.topics["/none/tf"]:
            at = world_positions(msg)
            gaps += [at[f"none/drone{i}"][2] - at["none/target"][2] for i in (1, 2)]
        print(f"{rig}: drones above the target by {min(gaps):.3f} .. {max(gaps):.3f} m")
        assert min(gaps) > 0.5, rig


def test_the_emulated_labs_images_are_bounded_in_rate_and_size(
    runs: dict[str, Path], mcaps: dict[str, McapContents]
) -> None:
    got = mcaps["emulated-lab"]
    rec = load_run(runs["emulated-lab"])["none"]
    minutes = float(rec.t[rec.ticks_done - 1] - rec.t[0]) / 60.0
    images = 0
    for topic in IMAGES:
        msgs = got.topics[topic]
        gaps_s = np.diff([lt for lt, _ in msgs]) / 1e9
        assert 2 <= len(msgs) <= IMAGE_HZ * (minutes * 60.0 + 1.0) + 1, (topic, len(msgs))
        assert np.all(gaps_s >= 1.0 / IMAGE_HZ - 1e-6), topic
        assert all(m.format == "jpeg" and m.data[:2] == b"\xff\xd8" for _, m in msgs)
        images += sum(len(m.data) for _, m in msgs)
    size = (runs["emulated-lab"] / LIVE_MCAP_FILE).stat().st_size
    print(f"emulated lab, {minutes * 60:.1f} s: images {images / minutes / 1e6:.2f} MB/min, "
          f"recording.mcap {size / minutes / 1e6:.2f} MB/min")  # fmt: skip
    assert images / minutes <= BUDGET_BYTES_PER_MIN


def test_every_topic_of_the_shipped_layout_is_in_the_recordings(mcaps: dict[str, McapContents]) -> None:
    topics = layout_topics(json.loads((REPO / "docs" / "foxglove" / layout_name("none")).read_text()))
    assert topics <= set(mcaps["emulated-lab"].topics)
    assert topics - set(IMAGES) <= set(mcaps["ideal"].topics)  # no cameras on the ideal rig
