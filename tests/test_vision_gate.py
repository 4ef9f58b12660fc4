"""The detection gate (flightstack.vision.gate): its size in closed form, what it accepts and rejects, its
false rejections under the detector's noise, and the residual's pixels against an independent projection
(OpenCV's projectPoints through the calibration's intrinsics)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from flightstack.paper.geometry import Pose
from flightstack.paper.projection import CameraModel, measure, points_in_camera
from flightstack.vision.gate import TRACK_WINDOW, DetectionGate, GateSpec

pytestmark = pytest.mark.unit

FX = 260.0
P0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])
CAM = CameraModel(focal_length=1.0)
G_I0 = Pose.make([0.02, -0.03, 0.85], 0.3)  # the target 0.85 m ahead along the optical axis


def _learn(
    gate: DetectionGate, f: np.ndarray, offset_px: np.ndarray, t0: float, noise_px: float = 0.0
) -> float:
    """TRACK_WINDOW detections every 0.05 s from t0, each marker `offset_px` (2,) off the prediction f
    (plus Gaussian noise): the gate's warm-up, all accepted. Returns the time of the last."""
    rng = np.random.default_rng(1)
    t = t0
    for _ in range(TRACK_WINDOW):
        noisy = f + np.tile(offset_px / FX, 4) + rng.normal(0, noise_px / FX, 8)
        v = gate.check(noisy, f, 0.85, t)
        assert v.accepted and v.gate_px == math.inf  # taken while the gate learns
        t += 0.05
    return t - 0.05


def test_the_gate_is_the_closed_form() -> None:
    """After the warm-up the offset shared by the markers is the estimate's lag (here 5 px, (3, 4)): a
    detection at it has residual 0, one 2 px beside it 2 px, and the gate is
    n_σ·sqrt(σ_cal² + σ_track²) + (v·fx/z̄ + ω·ρ̄)·τ (σ_track 0: no scatter learned)."""
    spec = GateSpec(sigmas=4.0, drift_mps=0.2, drift_radps=0.5, noise_px=0.7)
    gate = DetectionGate(spec, FX, 1.0)
    assert gate.gate_px(1.0, 0.8) == math.inf
    f = measure(G_I0, P0, CAM)
    t = _learn(gate, f, np.array([3.0, 4.0]), 1.0)
    for tau in (0.0, 0.05, 0.4):
        want = 4.0 * 0.7 + (0.2 * FX / 0.8 + 0.5 * 40.0) * tau
        assert gate.gate_px(t + tau, 0.8, 40.0) == pytest.approx(want, rel=1e-9)
    v = gate.check(f + np.tile([3.0 / FX, 4.0 / FX], 4), f, 0.8, t + 0.05)
    assert v.accepted and v.residual_px == pytest.approx(0.0, abs=1e-9)
    v = gate.check(f + np.tile([5.0 / FX, 4.0 / FX], 4), f, 0.8, t + 0.1)
    assert v.accepted and v.residual_px == pytest.approx(2.0, rel=1e-6)


def test_it_expects_the_detection_where_it_would_judge_it() -> None:
    """`expected`: nothing during the warm-up; after it the prediction moved by the lag the gate learnt
    (here (3, 4) px, closed form), which a detection there meets with residual 0."""
    gate = DetectionGate(GateSpec(noise_px=0.7), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    assert gate.expected(f, 0.0) is None
    t = _learn(gate, f, np.array([3.0, 4.0]), 1.0)
    for _ in range(TRACK_WINDOW):  # a still lag: the warm-up ends
        t += 0.05
        gate.check(f + np.tile([3.0 / FX, 4.0 / FX], 4), f, 0.85, t)
    e = gate.expected(f, t + 0.05)
    assert e is not None
    np.testing.assert_allclose(e, f + np.tile([3.0 / FX, 4.0 / FX], 4), atol=1e-9)
    assert gate.check(e, f, 0.85, t + 0.05).residual_px == pytest.approx(0.0, abs=1e-6)


def test_a_ghost_beside_a_lagging_estimate_is_rejected_then_taken_once_the_estimate_may_have_drifted() -> (
    None
):
    """The estimate lags by 6 px (all markers alike) with 0.3 px of noise: those detections pass; a
    concealed frame's ghost 8 px further (14 px off the prediction, 8 px off the lag) is rejected.
    Coasting widens the gate by the drift the estimate may have missed, s = v·fx/z̄ + ω·ρ̄ px/s, so the
    same offset is taken once τ is long enough (no lock-out); a rejection teaches the gate nothing."""
    spec = GateSpec(sigmas=4.0, drift_mps=0.1, drift_radps=0.5, noise_px=0.5)
    gate = DetectionGate(spec, FX, 1.0)
    f = measure(G_I0, P0, CAM)
    lag = np.array([6.0, 0.0])
    t = _learn(gate, f, lag, 0.05, noise_px=0.3)
    rng = np.random.default_rng(3)
    for _ in range(3 * TRACK_WINDOW):  # tracking, lagging
        t += 0.05
        assert gate.check(f + np.tile(lag / FX, 4) + rng.normal(0, 0.3 / FX, 8), f, 0.85, t).accepted
    ghost = f + np.tile((lag + np.array([8.0, 0.0])) / FX, 4)
    v = gate.check(ghost, f, 0.85, t + 0.05)
    spread = float(np.linalg.norm((f.reshape(-1, 2) - f.reshape(-1, 2).mean(axis=0)) * FX, axis=1).mean())
    s = 0.1 * FX / 0.85 + 0.5 * spread
    noise = v.gate_px - s * 0.05
    assert not v.accepted and v.residual_px == pytest.approx(8.0, abs=0.3) and noise < 3.0
    tau_open = (v.residual_px - noise) / s
    assert 0.08 < tau_open < 0.25, tau_open
    assert not gate.check(ghost, f, 0.85, t + 0.9 * tau_open).accepted
    assert gate.check(ghost, f, 0.85, t + 0.05 + 1e-6).gate_px == pytest.approx(v.gate_px, abs=1e-3)
    assert gate.check(ghost, f, 0.85, t + 1.1 * tau_open).accepted
    assert (gate.accepted, gate.rejected) == (4 * TRACK_WINDOW + 1, 3)


def test_a_turning_target_is_followed_and_a_ghost_during_the_turn_rejected() -> None:
    """The target turns: the lag grows at 43 px/s (Δv ≈ 0.14 m/s at a corner of paper_experiment's square,
    fx/z̄ ≈ 306 px/m) for 1 s, 30 frames/s, 0.3 px of noise. The offset's rate is tracked: every frame of the
    turn is taken and, once the rate is learnt, predicted to within the noise (without the rate the
    residual stays 3 px behind the ramp). A ghost 6 px beside the ramp is still rejected."""
    gate = DetectionGate(GateSpec(noise_px=0.5), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    t = _learn(gate, f, np.zeros(2), 0.0, noise_px=0.3)
    rng = np.random.default_rng(5)
    lag = np.zeros(2)
    residuals = []
    for k in range(1, 31):
        lag = np.array([43.0 * k / 30.0, 0.0])
        v = gate.check(f + np.tile(lag / FX, 4) + rng.normal(0, 0.3 / FX, 8), f, 0.85, t + k / 30.0)
        residuals.append(v.residual_px)
        assert v.accepted, (k, v)
    print(f"residual during the turn: max {max(residuals):.2f} px, last {residuals[-1]:.2f} px")
    assert residuals[-1] < 1.5  # the rate learnt: the ramp is predicted
    t += 1.0
    ghost = f + np.tile((lag + np.array([43.0 / 30.0 + 6.0, 0.0])) / FX, 4)
    assert not gate.check(ghost, f, 0.85, t + 1 / 30.0).accepted


def test_a_target_turning_in_place_is_followed() -> None:
    """The robot turns in place at 0.5 rad/s for 1.5 s (paper_experiment's unicycle square turns at each
    corner) while the estimate stays put: the markers, 43 px from their centre, rotate by 21 px/s in
    opposite directions, which no common shift explains. The lag's rotation is tracked: every frame is
    taken, and by the end the rotation is predicted to within the noise."""
    gate = DetectionGate(GateSpec(noise_px=0.5), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    t = _learn(gate, f, np.zeros(2), 0.0, noise_px=0.3)
    rng = np.random.default_rng(6)
    residuals = []
    for k in range(1, 46):
        turned = measure(Pose.make(G_I0.p, 0.3 + 0.5 * k / 30.0), P0, CAM)
        v = gate.check(turned + rng.normal(0, 0.3 / FX, 8), f, 0.85, t + k / 30.0)
        residuals.append(v.residual_px)
        assert v.accepted, (k, v)
    print(f"residual during the turn: max {max(residuals):.2f} px, last {residuals[-1]:.2f} px")
    assert residuals[-1] < 1.5


def test_the_warm_up_lasts_while_the_estimate_converges() -> None:
    """At the start the estimate converges: the lag shrinks at 80 px/s, faster than the drift bound s
    (≈ 52 px/s here). The gate stays open (every detection taken, gate ∞) past TRACK_WINDOW detections
    while it does, and judges once the lag has settled."""
    gate = DetectionGate(GateSpec(), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    t = 0.0
    for k in range(2 * TRACK_WINDOW):  # 1 s converging: 80 → 0 px
        lag = np.array([80.0 - 4.0 * k, 0.0])
        v = gate.check(f + np.tile(lag / FX, 4), f, 0.85, t)
        assert v.accepted and v.gate_px == math.inf, k
        t += 0.05
    for _ in range(TRACK_WINDOW):  # converged: the rate decays, the gate closes
        t += 0.05
        v = gate.check(f, f, 0.85, t)
        assert v.accepted
    assert math.isfinite(v.gate_px)
    assert not gate.check(f + np.tile([30.0 / FX, 0.0], 4), f, 0.85, t + 0.05).accepted  # judged now


def test_the_warm_up_on_a_gappy_stream_lasts_while_the_estimate_converges() -> None:
    """A lossy stream: detections 0.15 s apart (past OFFSET_HORIZON_S, each re-acquires with θ̇ = 0) while
    the lag shrinks at 80 px/s. A re-acquired θ̇ = 0 is no learnt rate: the gate stays open until detections
    close enough to learn one show the lag settled (the former gate closed after TRACK_WINDOW of them)."""
    gate = DetectionGate(GateSpec(), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    t = 0.0
    for k in range(2 * TRACK_WINDOW):  # 3 s converging: 240 → 12 px
        lag = np.array([240.0 - 12.0 * k, 0.0])
        v = gate.check(f + np.tile(lag / FX, 4), f, 0.85, t)
        assert v.accepted and v.gate_px == math.inf, k
        t += 0.15
    for _ in range(TRACK_WINDOW):  # converged, frames 0.05 s apart: the rate is learnt, the gate closes
        t += 0.05
        v = gate.check(f, f, 0.85, t)
        assert v.accepted
    assert math.isfinite(v.gate_px)


def test_a_frame_judged_again_is_judged_once() -> None:
    """The loop reads the camera's newest frame every tick; when no newer frame came, the same frame (its
    capture time) gets the same verdict and is counted once."""
    gate = DetectionGate(GateSpec(), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    t = _learn(gate, f, np.zeros(2), 0.0)
    ghost = f + np.tile([10.0 / FX, 0.0], 4)
    first = gate.check(ghost, f, 0.85, t + 0.05)
    assert gate.check(ghost, f, 0.85, t + 0.05) == first and not first.accepted
    assert (gate.accepted, gate.rejected) == (TRACK_WINDOW, 1)


def test_false_rejections_under_the_detectors_noise_are_rare() -> None:
    """20,000 detections at 20 Hz with Gaussian noise of σ_cal per axis on every marker: the gate learns
    σ_track ≈ σ_cal (the scatter about b, itself a mean of noise) and rejects at most the 4σ tail of the
    largest of four Rayleigh distances (1 − (1 − e^−8)^4 ≈ 1.3e-3 at σ_track = 0; less with it)."""
    gate = DetectionGate(GateSpec(noise_px=0.5), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    rng = np.random.default_rng(7)
    n = 20_000
    rejected = sum(
        not gate.check(f + rng.normal(0, 0.5 / FX, 8), f, 0.85, 0.05 * k).accepted for k in range(n)
    )
    print(f"false rejections: {rejected} of {n}")
    assert rejected / n <= 1.3e-3


def test_the_residual_is_in_pixels_of_the_calibrated_image() -> None:
    """The residual of features in the paper's image-plane units (λ = 2.5 here) is their distance in
    pixels: checked against cv2.projectPoints of the same points moved 0.01 m (no distortion)."""
    cam = CameraModel(focal_length=2.5)
    K = np.array([[FX, 0, 160], [0, FX, 120], [0, 0, 1.0]])
    pc = points_in_camera(G_I0, P0, cam)
    moved = pc + np.array([0.01, 0.0, 0.0])
    px0, _ = cv2.projectPoints(pc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.zeros(5))
    px1, _ = cv2.projectPoints(moved.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.zeros(5))
    want = float(np.linalg.norm((px1 - px0).reshape(-1, 2), axis=1).max())
    f0 = (2.5 * pc[:, :2] / pc[:, 2:]).reshape(-1)
    f1 = (2.5 * moved[:, :2] / moved[:, 2:]).reshape(-1)
    gate = DetectionGate(GateSpec(), FX, 2.5)
    for k in range(TRACK_WINDOW):  # the warm-up on exact detections: b = 0
        assert gate.check(f0, f0, 0.85, 0.05 * k).accepted
    v = gate.check(f1, f0, 0.85, 0.05 * TRACK_WINDOW)
    assert v.residual_px == pytest.approx(want, rel=1e-9)


def test_every_pose_error_of_a_level_target_is_a_similarity() -> None:
    """The shape residual q asks nothing of the 4-DOF estimate: the target's image under 200 random errors
    of its position (±0.2 m) and yaw (±0.5 rad), projected independently (paper.projection.measure), has
    q < 1e-6 px against the true pose's image, however far it moved."""
    rng = np.random.default_rng(11)
    f = measure(G_I0, P0, CAM)
    worst_q = moved = 0.0
    for k in range(200):
        gate = DetectionGate(GateSpec(), FX, 1.0)
        dp, dyaw = rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.5, 0.5)
        x, y, z, yaw = G_I0.as_vector()
        g = Pose.make([x + dp[0], y + dp[1], z + dp[2]], yaw + dyaw)
        fg = measure(g, P0, CAM)
        v = gate.check(fg, f, 0.85, 0.05 * k)
        worst_q = max(worst_q, v.shape_px)
        moved = max(moved, float(np.linalg.norm((fg - f).reshape(-1, 2), axis=1).max()) * FX)
    print(f"largest shape residual {worst_q:.2e} px for images up to {moved:.0f} px away")
    assert worst_q < 1e-6 and moved > 50.0


def test_a_tilted_camera_changes_the_boards_shape_as_the_docstring_says() -> None:
    """Why the shape is judged only in damaged frames: a camera tilted 5° or 10° (roll, pitch or both) over
    the 0.2 m board 0.7 m below, the board anywhere in the 320 × 240 picture (fx = 260 px), projected by
    OpenCV, against the level camera's image: the shape residual reaches 1.5 px and 3.1 px (the figures in
    flightstack.vision.gate's docstring), beyond the 1.41 px shape gate of a level camera's σ."""
    K = np.array([[FX, 0, 160], [0, FX, 120], [0, 0, 1.0]])
    square = np.array([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0], [0.1, -0.1, 0.0]])
    worst = {}
    for deg in (5.0, 10.0):
        q = 0.0
        for cx in np.linspace(-0.2, 0.2, 5):
            for cy in np.linspace(-0.15, 0.15, 5):
                for axis in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [math.sqrt(0.5), math.sqrt(0.5), 0.0]):
                    pts = (square + np.array([cx, cy, 0.7])).reshape(-1, 1, 3)
                    level, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.zeros(5))
                    rvec = np.array(axis) * math.radians(deg)
                    tilted, _ = cv2.projectPoints(pts, rvec, np.zeros(3), K, np.zeros(5))
                    tilted = tilted.reshape(-1, 2)
                    if (tilted < 0).any() or (tilted > [320, 240]).any():
                        continue  # the board left the picture
                    gate = DetectionGate(GateSpec(), FX, FX)
                    v = gate.check(
                        (tilted - [160, 120]).reshape(-1),
                        (level.reshape(-1, 2) - [160, 120]).reshape(-1),
                        0.7,
                        0.0,
                    )
                    q = max(q, v.shape_px)
        worst[deg] = q
    print(f"largest shape residual of a tilted camera: {worst}")
    assert 1.45 < worst[5.0] < 1.55 and 3.05 < worst[10.0] < 3.2


def test_a_board_of_the_wrong_shape_in_a_damaged_frame_is_mended() -> None:
    """After the warm-up on exact detections (σ_shape = 0), the shape gate is n_σ·σ_cal/√2 (closed form,
    4·0.5/√2 = 1.41 px). In a frame tagged damaged, a ghost that moves one corner 4 px (within the position
    gate) leaves q = 2 px once the frame's own similarity takes its share (half, for a square): the other
    three fit a pose exactly, so that corner is replaced where they put it (here the true board). Two
    corners moved apart leave no three that fit: the board is judged as detected (its farthest corner 4 px
    off). In a frame tagged clean the one-corner ghost is taken as it is; during the warm-up too (the shape
    gate is open: σ_shape is learnt from what the warm-up takes)."""
    gate = DetectionGate(GateSpec(sigmas=4.0, noise_px=0.5), FX, 1.0)
    f = measure(G_I0, P0, CAM)
    corner = np.zeros(8)
    corner[0] = 4.0 / FX
    v = gate.check(f + corner, f, 0.85, 0.0, damaged=True)
    assert v.accepted and v.shape_gate_px == math.inf and v.shape_px == pytest.approx(2.0, rel=1e-6)
    assert v.mended is None
    gate.reset()
    t = _learn(gate, f, np.zeros(2), 0.0)
    for _ in range(TRACK_WINDOW):  # a still lag: the warm-up ends
        t += 0.05
        v = gate.check(f, f, 0.85, t)
    assert v.accepted and v.shape_px == pytest.approx(0.0, abs=1e-6)
    assert v.shape_gate_px == pytest.approx(4.0 * 0.5 / math.sqrt(2.0), rel=1e-9)
    v = gate.check(f + corner, f, 0.85, t + 0.05, damaged=True)
    assert v.accepted and v.shape_px == pytest.approx(2.0, rel=1e-6) and v.replaced_marker == 0
    assert v.mended is not None and v.residual_px == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(v.mended, f, atol=1e-9)
    two = corner.copy()
    two[3] = -4.0 / FX  # marker 1 moved down as marker 0 moves right
    v = gate.check(f + two, f, 0.85, t + 0.1, damaged=True)
    assert (v.mended, v.replaced_marker) == (None, None) and v.shape_px > v.shape_gate_px
    assert v.accepted and v.residual_px == pytest.approx(4.0, rel=1e-6)
    v = gate.check(f + corner, f, 0.85, t + 0.15)  # a frame tagged clean: its shape is not judged
    assert v.accepted and v.mended is None and v.shape_px == pytest.approx(2.0, rel=1e-6)


def test_settings_out_of_range_are_refused() -> None:
    for bad in (
        {"sigmas": 0.0},
        {"drift_mps": -1.0},
        {"drift_radps": -0.1},
        {"noise_px": 0.0},
        {"sigmas": math.inf},
    ):
        with pytest.raises(ValueError):
            GateSpec(**bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        DetectionGate(GateSpec(), 0.0, 1.0)
