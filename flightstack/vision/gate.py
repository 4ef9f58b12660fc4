"""Is a detection where the target should be? Every detection from an image is checked against a
prediction that does not come from the image before the observer uses it.

A frame of the Tello's H.264 stream decoded after a lost datagram is concealed by the decoder: parts of
it are copied from older frames, and a marker there can sit pixels away from where it is (ghosting
moves all the markers of a frame together, so their own geometry does not show it). A lost middle
datagram is not even detectable in the stream (drivers/tello/video_check.py). So no frame is trusted by
its tag alone: the prediction is the target's feature points p0^j seen from the drone's own pose g_wi
(motion capture) under the observer's estimate ḡ_w, both for the frame's capture time, projected as the
paper's measurement f̄ = f(g_wi⁻¹ ḡ_w) (flightstack.paper.projection), shifted by the offset b by which
the recent accepted detections lay beside it. A detection f is accepted when (pixels)

    d^j = (f^j − f̄^j) · fx/λ,    r = max_j ‖d^j − b‖  ≤  gate = n_σ · sqrt(σ_cal² + σ_track² + (s·τ')²),
    τ' = max(0, τ − τ₀)

* d^j: marker j's offset from its prediction, in pixels at the image centre (f in the paper's image-plane
  units λ·(x/z, y/z); fx the calibration's focal length in pixels; the lens distortion is left out, a few
  % at the image's corners);
* b: the mean offset of the markers of the recent accepted detections (an exponential window of
  TRACK_WINDOW detections): the estimate's systematic lag behind a moving target, which shifts all the
  markers alike and changes slowly (and on a real drone its tilt, which the paper's 4-DOF pose does not
  carry). Taking it out leaves what the estimate cannot explain; a concealed frame's ghost, which jumps
  all the markers together from one frame to the next, is then seen against the detector's noise rather
  than against the lag (in a pursuit without GP the lag alone was 3–5 px, wider than many ghosts);
* σ_cal: the calibration's reprojection RMS (`rms_px`; DEFAULT_NOISE_PX for a simulated camera without
  one): the detector's own noise;
* σ_track: the RMS per axis of d^j − b over the recent accepted detections (same window): how well the
  shifted prediction predicts;
* s·τ': how far the estimate may have drifted since the last accepted detection, τ s of
  capture time ago, beyond the usual spacing of detections τ₀ (GateSpec.grace_s, 0.1 s: three frames at
  30 fps, two ticks at 20 Hz), whose prediction error σ_track already measures: s = v_drift · fx / z̄
  px/s, z̄ the predicted mean depth of the points (m), v_drift the target speed the estimate may have
  missed (m/s, GateSpec.drift_mps). Not for a frame tagged damaged: concealment can hold a ghost in
  place for every frame up to the next keyframe (2.2 s on a Tello), so a gate that widened while the
  observer coasts would end up taking it; only a frame not known to be damaged may move the estimate
  beyond what it predicts. The first TRACK_WINDOW detections after a (re)start are taken (the
  estimate is then only a guess from the desired pose, converging; the gate learns b and σ_track from
  them) and judged from then on;
* n_σ = 4 (GateSpec.sigmas): with Gaussian pixel noise of σ per axis a marker's distance exceeds 4σ with
  probability e^(−8) ≈ 3.4e-4, the largest of m = 4 with ≈ 1.3e-3.

A rejected detection is not a lost target: the observer coasts on its estimate (the tick counts as not
seen, `coasted`), and the safety layer's target-lost timers run as for any tick without the target.
Pure: numbers in, verdicts out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_NOISE_PX = 0.5
"""σ_cal of a camera whose calibration states no reprojection RMS (the simulated cameras; px)."""
TRACK_WINDOW = 10
"""Accepted detections in σ_track's exponential window (0.5 s at the 20 Hz loop)."""
OFF_PREDICTION = "off prediction"
"""The rejection reason of a detection outside the gate (TickRecord.rejection, counted per drone)."""


@dataclass(frozen=True)
class GateSpec:
    """The gate's settings: sigmas n_σ; drift_mps v_drift (m/s); noise_px σ_cal (px); grace_s τ₀ (s)."""

    sigmas: float = 4.0
    drift_mps: float = 0.1
    noise_px: float = DEFAULT_NOISE_PX
    grace_s: float = 0.1

    def __post_init__(self) -> None:
        if not (self.sigmas > 0 and self.drift_mps >= 0 and self.noise_px > 0 and self.grace_s >= 0):
            raise ValueError(f"need sigmas > 0, drift_mps >= 0, noise_px > 0, grace_s >= 0, got {self}")
        if not all(map(math.isfinite, (self.sigmas, self.drift_mps, self.noise_px, self.grace_s))):
            raise ValueError(f"gate settings must be finite, got {self}")


@dataclass(frozen=True)
class GateVerdict:
    """One detection judged: accepted, its residual r and the gate it was held to (px)."""

    accepted: bool
    residual_px: float
    gate_px: float


class DetectionGate:
    """The gate of one camera (module docstring). `check` judges a detection and, when it is accepted,
    learns its residual; `reset` forgets everything (a new estimate)."""

    def __init__(self, spec: GateSpec, fx_px: float, focal_length: float) -> None:
        """fx_px: the calibration's focal length (px); focal_length: λ of the features (image-plane units)."""
        if not (fx_px > 0 and focal_length > 0):
            raise ValueError(f"need fx_px > 0 and focal_length > 0, got {fx_px}, {focal_length}")
        self.spec = spec
        self.px_per_unit = fx_px / focal_length
        self.fx_px = fx_px
        self.reset()

    def reset(self) -> None:
        self._bias = np.zeros(2)  # b (px)
        self._track_var = 0.0  # σ_track² (px² per axis)
        self._t_accepted = -math.inf  # capture time of the last accepted detection (s)
        self._learned = 0  # accepted detections since the (re)start
        self.accepted = 0
        self.rejected = 0

    def gate_px(self, t_capture: float, depth_m: float, damaged: bool = False) -> float:
        """The gate (px) for a frame captured at t_capture (s) whose points lie depth_m ahead (m); a
        `damaged` frame's gate does not widen with τ (module docstring)."""
        tau = t_capture - self._t_accepted
        if self._learned < TRACK_WINDOW or not math.isfinite(tau):
            return math.inf
        s = self.spec.drift_mps * self.fx_px / max(depth_m, 1e-3)
        drift = 0.0 if damaged else s * max(tau - self.spec.grace_s, 0.0)
        return self.spec.sigmas * math.sqrt(self.spec.noise_px**2 + self._track_var + drift * drift)

    def check(
        self, f: np.ndarray, f_pred: np.ndarray, depth_m: float, t_capture: float, damaged: bool = False
    ) -> GateVerdict:
        """Judge features f against their prediction f_pred (both (2m,), image-plane units) for a frame
        captured at t_capture (s) with its points depth_m ahead (m); `damaged`: the frame was decoded
        through a detected loss (hal.Frame.damaged)."""
        d = (np.asarray(f, dtype=float) - np.asarray(f_pred, dtype=float)).reshape(-1, 2) * self.px_per_unit
        first = self._learned == 0
        dev = d - (d.mean(axis=0) if first else self._bias)
        dist2 = (dev * dev).sum(axis=1)
        r = math.sqrt(float(dist2.max()))
        gate = self.gate_px(t_capture, depth_m, damaged)
        if not (r <= gate):  # NaN too
            self.rejected += 1
            return GateVerdict(False, r, gate)
        self.accepted += 1
        a = 1.0 if first else 1.0 / TRACK_WINDOW
        self._track_var = (1 - a) * self._track_var + a * float(dist2.mean()) / 2.0
        self._bias = (1 - a) * self._bias + a * d.mean(axis=0)
        self._learned += 1
        self._t_accepted = max(self._t_accepted, t_capture)
        return GateVerdict(True, r, gate)


__all__ = ["DEFAULT_NOISE_PX", "OFF_PREDICTION", "TRACK_WINDOW", "DetectionGate", "GateSpec", "GateVerdict"]
