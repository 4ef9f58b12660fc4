"""The latency calibration flight on the simulated lab (`calibrate latency --rig lab-sim --links tello`), on
its virtual clock: its frames carry their capture times and its `tello` links known latencies (video
300 ms + U(0, 100 ms) at 30 fps, 2 % lost; rc 50 ms + U(0, 30 ms)). A frame is timed when the recorder
first sees it; the truth is that time minus the frame's capture stamp, for the frames the estimate used.
The rc truth is the link's mean, 65 ms (29 draws: its sample mean is within ±3 ms at 95 %)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from flightstack.calibration.latency_flight import fly_latency_calibration
from flightstack.config.mission import load_mission
from flightstack.hal import Frame


class FirstSeen:
    """The backend with its cameras tapped: each frame's capture stamp by the time it was first seen."""

    def __init__(self, inner: Any, seen: dict[float, float]) -> None:
        self.inner, self.seen = inner, seen
        self.simulated, self.clock = inner.simulated, inner.clock

    def camera(self, drone_id: int) -> Any:
        tap = self

        class Tapped:
            def latest(self) -> Frame | None:
                f = tap.inner.camera(drone_id).latest()
                if f is not None and f.stamp not in tap.seen.values():
                    tap.seen[tap.clock.now()] = f.stamp
                return f

        return Tapped()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_the_flown_calibration_recovers_the_simulated_labs_links() -> None:
    mission = load_mission("paper_experiment", {"links": {"profile": "tello"}}, rig="lab-sim")
    seen: dict[float, float] = {}
    t0 = time.perf_counter()
    video, rc, flown_s, _ = fly_latency_calibration(
        mission, say=lambda line: None, wrap_backend=lambda b: FirstSeen(b, seen)
    )
    wall = time.perf_counter() - t0
    v_est, r_est = video.estimate(), rc.estimate()
    truth = np.array([t - seen[t] for t in video.t_frames])
    v_err_ms = 1e3 * (v_est.mean_s - truth.mean())
    link = mission.links.link("rc")
    r_err_ms = 1e3 * (r_est.mean_s - (link.latency_s + link.jitter_s / 2))
    print(
        f"{flown_s:.1f} s flown in {wall:.1f} s of wall clock (loaded 2-core machine); video: true "
        f"{1e3 * truth.mean():.1f} ms over {truth.size} frames, estimate {1e3 * v_est.mean_s:.1f} ms "
        f"({v_est.n_used} timed), error {v_err_ms:+.1f} ms; rc: estimate {1e3 * r_est.mean_s:.1f} ms over "
        f"{r_est.n_steps} changes, error {r_err_ms:+.1f} ms"
    )
    assert truth.size > 200 and v_est.n_used > 0.5 * truth.size, (truth.size, v_est)
    assert abs(v_err_ms) <= 10.0, v_err_ms
    assert abs(1e3 * (v_est.sd_s - truth.std())) <= 10.0, (v_est, truth.std())
    assert r_est.n_steps >= 25 and abs(r_err_ms) <= 10.0, (r_est, r_err_ms)
    assert abs(r_est.tau_s - mission.sim.tello.time_constant_s) <= 0.03, r_est


def test_a_procedure_lands_the_drone_whatever_ends_it() -> None:
    """Flight.fly_procedure takes off, runs the procedure and lands, also when it raises (error, Ctrl-C)."""
    import pytest

    from flightstack.calibration.latency_flight import one_drone
    from flightstack.hal import FlightPhase
    from flightstack.runtime.flight import Flight
    from flightstack.sim_backend.build_lab import build_lab

    mission = one_drone(load_mission("paper_experiment", rig="lab-sim"), None)
    for error in (None, RuntimeError("a device failed"), KeyboardInterrupt()):
        backend = build_lab(mission)
        heights: list[float] = []

        def hover(
            f: Any, pause: Any, error: BaseException | None = error, heights: list[float] = heights
        ) -> str:
            pause(1.0)
            heights.append(float(f.backend.truth()[1][1].p[2]))
            if error is not None:
                raise error
            return "done"

        with Flight(mission, None, modes=["none"], backend=backend) as flight:
            if error is None:
                assert flight.fly_procedure(hover) == "done"
            else:
                with pytest.raises(type(error)):
                    flight.fly_procedure(hover)
        assert heights and heights[0] > 0.8, heights  # it flew
        assert backend.drone(1).state().phase == FlightPhase.GROUND, error  # and it landed


def test_the_command_flies_the_simulated_lab_and_refuses_what_it_cannot_fly(
    tmp_path: Any, capsys: Any
) -> None:
    import yaml

    from flightstack.cli.app import main

    out = tmp_path / "links.yaml"
    assert main(["calibrate", "latency", "--rig", "lab-sim", "--links", "tello", "--out", str(out)]) == 0
    written = yaml.safe_load(out.read_text())
    assert 0.33 < written["measured"]["video"]["mean_s"] < 0.37, written
    assert (tmp_path / "links.session.npz").is_file()
    # the session re-estimates to the same numbers
    again = tmp_path / "again.yaml"
    session = str(tmp_path / "links.session.npz")
    assert main(["calibrate", "latency", "--session", session, "--out", str(again)]) == 0
    assert yaml.safe_load(again.read_text())["links"] == written["links"]
    capsys.readouterr()
    assert main(["calibrate", "latency"]) == 2  # neither --rig nor --session
    assert main(["calibrate", "latency", "--rig", "lab-sim", "--drone", "2"]) == 2  # a forward camera
    assert "downward camera" in capsys.readouterr().err
