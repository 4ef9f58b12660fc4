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


def test_the_gate_is_the_closed_form() -> None:
    """gate = n_σ·sqrt(σ_cal² + σ_track² + (v·fx/z·max(0, τ − τ₀))²); infinite before the first accepted
    detection."""
    spec = GateSpec(sigmas=4.0, drift_mps=0.2, noise_px=0.7, grace_s=0.1)
    gate = DetectionGate(spec, FX, 1.0)
    assert gate.gate_px(1.0, 0.8) == math.inf
    f = measure(G_I0, P0, CAM)
    offset = np.tile([3.0 / FX, 4.0 / FX], 4)  # every marker 5 px off (3, 4)
    v = gate.check(f + offset, f, 0.8, t_capture=1.0)
    assert v.accepted and v.residual_px == pytest.approx(5.0) and v.gate_px == math.inf
    track_var = 25.0 / 2  # per axis: the first accepted residual
    for tau in (0.0, 0.05, 0.4):
        want = 4.0 * math.sqrt(0.7**2 + track_var + (0.2 * FX / 0.8 * max(0.0, tau - 0.1)) ** 2)
        assert gate.gate_px(1.0 + tau, 0.8) == pytest.approx(want, rel=1e-12)


def test_a_detection_off_its_prediction_is_rejected_then_taken_once_the_estimate_may_have_drifted() -> None:
    """While the estimate tracks (residuals ~0.3 px), a detection 12 px off is rejected; coasting widens
    the gate by the drift the estimate may have missed, so the same offset is taken once τ is long enough
    (no lock-out); a rejection teaches the gate nothing."""
    spec = GateSpec(sigmas=4.0, drift_mps=0.1, noise_px=0.5)
    gate = DetectionGate(spec, FX, 1.0)
    f = measure(G_I0, P0, CAM)
    rng = np.random.default_rng(3)
    t = 0.0
    for _ in range(5 * TRACK_WINDOW):  # tracking: residuals of the detector's noise
        t += 0.05
        assert gate.check(f + rng.normal(0, 0.3 / FX, 8), f, 0.85, t).accepted
    ghost = f + np.tile([12.0 / FX, 0.0], 4)
    v = gate.check(ghost, f, 0.85, t + 0.05)
    assert not v.accepted and v.residual_px == pytest.approx(12.0) and v.gate_px < 3.0
    before = gate.gate_px(t + 0.05, 0.85)
    # the gate reaches 12 px when 4·sqrt(σ_cal² + σ_track² + (0.1·FX/0.85·(τ − 0.1))²) = 12
    base = (gate.gate_px(t, 0.85) / 4.0) ** 2  # σ_cal² + σ_track² (τ = 0)
    tau_open = 0.1 + math.sqrt(3.0**2 - base) / (0.1 * FX / 0.85)
    assert 0.15 < tau_open < 0.25, tau_open
    assert not gate.check(ghost, f, 0.85, t + 0.9 * tau_open).accepted
    assert gate.gate_px(t + 0.05, 0.85) == pytest.approx(before)  # rejections changed nothing
    assert gate.check(ghost, f, 0.85, t + 1.1 * tau_open).accepted
    assert (gate.accepted, gate.rejected) == (5 * TRACK_WINDOW + 1, 2)


def test_false_rejections_under_the_detectors_noise_are_rare() -> None:
    """20,000 detections at 20 Hz with Gaussian noise of σ_cal per axis on every marker: the gate learns
    σ_track ≈ σ_cal and rejects at most the 4σ tail of the largest of four Rayleigh distances
    (1 − (1 − e^−8)^4 ≈ 1.3e-3 at σ_track = 0; less with it)."""
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
    v = DetectionGate(GateSpec(), FX, 2.5).check(f1, f0, 0.85, 0.0)
    assert v.residual_px == pytest.approx(want, rel=1e-9)


def test_settings_out_of_range_are_refused() -> None:
    for bad in ({"sigmas": 0.0}, {"drift_mps": -1.0}, {"noise_px": 0.0}, {"sigmas": math.inf}):
        with pytest.raises(ValueError):
            GateSpec(**bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        DetectionGate(GateSpec(), 0.0, 1.0)
