"""`flightstack calibrate latency --rig` on the emulated lab, closed loop: the real drivers fly an emulated
Tello (the `tello` links: video 300 ms + U(0, 100 ms) at 30 fps, 2 % lost; rc 50 ms + U(0, 30 ms)) over
the still rover; its camera renders what it sees from a child process, motion capture reports the
poses. The flight takes off, holds its station over the target, yaws in the pattern, flies the rc steps
and lands.

Truth: each frame's bar-coded index names its record in the emulated Tello's capture log (true capture
time, time sent); each rc level's motion starts at the start of the physics step that first integrates
it (the emulator's `rc_acted`: the step moves by its mean velocity from its start; on average half a step,
TICK_S / 2 = 5 ms, before the datagram's receipt, more when a loaded machine runs the step late). The
recovered camera
latency (capture → decoded) is within ±10 ms of the true mean of the frames used, the rc latency within
±10 ms of the true one. And the command itself, in a child process with a timeout: it writes a links file
that a rig includes (`links: {include: FILE}`).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

pytest.importorskip("av")
pytest.importorskip("motioncapture")
pytest.importorskip("pymavlink")

from flightstack.calibration.latency_flight import fly_latency_calibration, one_drone
from flightstack.config.mission import load_mission, mission_to_dict
from flightstack.drivers.tello.rc import RcGains, velocity_to_rc
from flightstack.hal import Frame
from flightstack.sim_backend.build import initial_drone_pose
from flightstack.sim_backend.emulated_lab import DRONE_STARTS, EmulatedLab
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from flightstack.sim_backend.emulators.tello.frames import read_frame_index
from flightstack.sim_backend.emulators.tello.view import index_area
from flightstack.vision.camera_file import load_calibration
from tests.conftest import MISSIONS, Bound, run_cli

pytestmark = pytest.mark.system


class TappedCamera:
    """The backend's camera, noting each new frame's bar-coded index by its stamp (its decode time), read
    from the whole decoded frame (TelloCamera.last_decoded: the EDU's downward stream carries the code in
    the noise below the picture, which `latest` cuts off)."""

    def __init__(self, inner: Any, seen: dict[float, int], cal: Any) -> None:
        self.inner, self.seen, self.cal = inner, seen, cal

    def latest(self) -> Frame | None:
        f = self.inner.latest()
        whole = self.inner.last_decoded
        if f is not None and f.stamp not in self.seen and whole is not None:
            cal = self.cal
            self.seen[f.stamp] = read_frame_index(
                whole.image if cal is None else index_area(cal, whole.image)
            )
        return f

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


class TappedBackend:
    """The hardware backend with its cameras tapped (TappedCamera)."""

    def __init__(self, inner: Any, seen: dict[float, int]) -> None:
        self.inner, self.seen = inner, seen
        self.simulated = inner.simulated
        self.clock = inner.clock

    def camera(self, drone_id: int) -> TappedCamera:
        """Drone `drone_id`'s camera, tapped; its calibration says where the bar code is (index_area)."""
        m = self.inner.mission
        d = next(d for d in m.drones if d.id == drone_id)
        cal = None if d.camera is None or d.camera.calibration is None else m.resolve(d.camera.calibration)
        return TappedCamera(
            self.inner.camera(drone_id), self.seen, None if cal is None else load_calibration(cal)
        )

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def true_age(log: list[tuple[int, float, float]], t_decoded: float, index: int) -> float | None:
    """A frame's true capture → decode delay (s): the record of its index sent last before it was decoded
    (an index repeats when the camera restarts its stream); None without one (a garbled bar code)."""
    sent = [(ts, tc) for i, tc, ts in log if i == index and ts <= t_decoded and t_decoded - ts < 1.0]
    return t_decoded - max(sent)[1] if sent else None


def test_the_flown_calibration_recovers_the_emulated_latencies(tmp_path: Path, safety_bound: Bound) -> None:
    mission = one_drone(
        load_mission("paper_experiment", {"links": {"profile": "tello"}}, rig="emulated-lab"), None
    )
    starts = {}
    for k, d in enumerate(mission.drones):  # as the emulated-lab rig starts them (sim_backend.emulated_lab)
        above = initial_drone_pose(mission, k)
        starts[d.id] = ((float(above.p[0]), float(above.p[1]), DRONE_STARTS[1][0][2]), float(above.theta))
    doc = mission_to_dict(mission)
    doc["start_emulators"] = False
    seen: dict[float, int] = {}
    lines: list[str] = []
    say_lock = threading.Lock()

    def say(line: str) -> None:
        with say_lock:
            lines.append(line)

    with EmulatedLab(
        tmp_path / "lab", experiment=doc, seed=mission.seed, links=mission.links, starts=starts
    ) as lab:
        wall0 = time.perf_counter()
        video, rc, flown_s, wall_s = fly_latency_calibration(
            lab.mission(), say=say, wrap_backend=lambda b: TappedBackend(b, seen)
        )
        wall = time.perf_counter() - wall0
        emu = lab.tellos[mission.drones[0].id]
        log = list(emu.video_capture_log)
        acted = list(emu.rc_acted)
    v_est, r_est = video.estimate(), rc.estimate()
    ages = [true_age(log, t, seen[t]) for t in video.t_frames if t in seen]
    truth = np.array([a for a in ages if a is not None])
    v_err_ms = 1e3 * (v_est.mean_s - truth.mean())
    gains = RcGains(**mission.drones[0].rc_gains.model_dump())
    r_truth = []
    for k in np.flatnonzero(np.diff(rc.cmd) != 0) + 1:
        yaw_rc = velocity_to_rc(np.array([0.0, 0.0, 0.0, rc.cmd[k]]), gains)[3]
        began = [t for t, c in acted if t >= rc.t_cmd[k] - TelloEmulator.MAX_STEP_S and c[3] == yaw_rc]
        if began:
            r_truth.append(began[0] - rc.t_cmd[k])
    r_true = np.array(r_truth)
    r_err_ms = 1e3 * (r_est.mean_s - r_true.mean())
    print(
        f"flight: {flown_s:.1f} s of station and patterns, {wall_s:.1f} s in all ({wall:.1f} s here, "
        f"on a loaded 2-core machine); video: true {1e3 * truth.mean():.1f} ms (sd {1e3 * truth.std():.1f}) "
        f"over {truth.size} of {video.t_frames.size} frames, estimate {1e3 * v_est.mean_s:.1f} ms (sd "
        f"{1e3 * v_est.sd_s:.1f}, {v_est.n_used} timed), error {v_err_ms:+.1f} ms; rc: true "
        f"{1e3 * r_true.mean():.1f} ms over {r_true.size} changes, estimate {1e3 * r_est.mean_s:.1f} ms over "
        f"{r_est.n_steps}, error {r_err_ms:+.1f} ms"
    )
    assert truth.size > 0.9 * video.t_frames.size and truth.size > 150, (truth.size, video.t_frames.size)
    assert v_est.n_used > 0.5 * video.t_frames.size, v_est
    assert abs(v_err_ms) <= 10.0, v_err_ms
    assert r_true.size >= 25 and r_est.n_steps >= 25, (r_true.size, r_est)
    assert abs(r_err_ms) <= 10.0, r_err_ms
    safety_bound("latency calibration flight, wall clock (s)", wall_s, 120.0)


def test_the_command_writes_a_links_file_the_rig_includes(tmp_path: Path) -> None:
    rig = yaml.safe_load((MISSIONS / "rigs" / "emulated-lab.yaml").read_text())
    rig["cameras"] = {k: str((MISSIONS / "rigs" / v).resolve()) for k, v in rig["cameras"].items()}
    rig["links"] = {"profile": "tello"}  # the links the emulators apply
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    out = tmp_path / "links.yaml"
    t0 = time.perf_counter()
    res = run_cli("calibrate", "latency", "--rig", str(tmp_path / "rig.yaml"), "--out", str(out), timeout=240)
    wall = time.perf_counter() - t0
    print(res.stdout[-3000:], res.stderr[-3000:], f"command: {wall:.1f} s (loaded 2-core machine)", sep="\n")
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "links.session.npz").is_file()
    written = yaml.safe_load(out.read_text())
    assert set(written["links"]) == {"video", "rc"} and written["measured"]["date"]
    assert 0.33 < written["measured"]["video"]["mean_s"] < 0.42, written  # 350 ms + the pipeline's own
    # the rig that includes it (relative to the rig's folder), an rc written out beside it wins
    rig["links"] = {"include": "links.yaml", "rc": {"latency_s": 0.07}}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(rig))
    m = load_mission("paper_experiment", rig=tmp_path / "lab.yaml")
    assert m.links.link("video").latency_s == written["links"]["video"]["latency_s"]
    assert m.links.link("video").jitter_s == written["links"]["video"]["jitter_s"]
    assert m.links.link("rc").latency_s == 0.07
