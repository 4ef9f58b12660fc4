"""Is a detection where the target should be? Every detection from an image is checked against a
prediction that does not come from the image before the observer uses it.

A frame of the Tello's H.264 stream decoded after a lost datagram is concealed by the decoder: parts of
it are copied from older frames, and a marker there can sit pixels away from where it is (ghosting
moves all the markers of a frame together, so their own geometry does not show it). A lost middle
datagram is not even detectable in the stream (drivers/tello/video_check.py). So no frame is trusted by
its tag alone: the prediction is the target's feature points p0^j seen from the drone's own pose g_wi
(motion capture) under the observer's estimate ḡ_w, both for the frame's capture time, projected as the
paper's measurement f̄ = f(g_wi⁻¹ ḡ_w) (flightstack.paper.projection), moved by the lag b̂ by which the
recent accepted detections lay beside it. A detection f is accepted when (pixels)

    d^j = (f^j − f̄^j) · fx/λ,    r = max_j ‖d^j − b̂^j‖  ≤  gate = n_σ · sqrt(σ_cal² + σ_track²) + s·τ

* d^j: marker j's offset from its prediction, in pixels at the image centre (f in the paper's image-plane
  units λ·(x/z, y/z); fx the calibration's focal length in pixels; the lens distortion is left out, a few
  % at the image's corners);
* b̂^j: where the lag puts marker j: the estimate's error is a 4-DOF pose (the paper's g_e: position and
  yaw), which moves the image of a level target by a similarity, so the offsets of the recent accepted
  detections are fitted as one, θ = (t_x, t_y, a, c) with b^j = t + [[a, −c], [c, a]] q^j (q^j the
  predicted marker's pixels from the markers' centroid; t the shift, a the scale, c the rotation: rad),
  followed by an α-β tracker (OFFSET_GAIN α, OFFSET_RATE_GAIN β: θ and its rate θ̇) and predicted to the
  frame, θ̂ = θ + θ̇·min(τ, OFFSET_HORIZON_S). That is the estimate's lag behind a moving target, which
  changes smoothly (and on a real drone its tilt, which the paper's 4-DOF pose does not carry). The
  rate and the rotation matter where the target turns: paper_experiment's robot stops at a corner and
  turns in place, the lag then grows by tens of px/s, shifting and rotating the markers, until the
  observer catches up; a shift held constant made the gate reject the detections of every turn (5–9 %
  of the good detections, coasting 0.5–0.7 s each time). Taking b̂ out leaves what the estimate cannot
  explain; a concealed frame's ghost, which jumps the markers from one frame to the next, is then seen
  against the detector's noise rather than against the lag (in a pursuit without GP the lag alone was
  3–5 px, wider than many ghosts);
* σ_cal: the calibration's reprojection RMS (`rms_px`; DEFAULT_NOISE_PX for a simulated camera without
  one): the detector's own noise;
* σ_track: the RMS per axis of d^j − b̂^j over the recent accepted detections (an exponential window of
  TRACK_WINDOW): how well the shifted prediction predicts;
* s·τ: how far the target may have moved in a way the estimate did not predict since the last accepted
  detection, τ s of capture time ago: a bound, not a noise, so it is added outside n_σ, and it starts
  at once (a robot that stops, starts or turns changes its image velocity between two frames: with the
  bound held back for the first 0.1 s, the first frames of every such change were rejected, 21–27 per
  30 s mode). s = v_drift·fx/z̄ + ω_drift·ρ̄ px/s, z̄ the predicted mean depth of the points (m), ρ̄ their
  mean distance from their centroid (px), v_drift and ω_drift the change of speed and the turn rate the
  estimate may miss (GateSpec.drift_mps, drift_radps: by default paper_experiment's robot's 0.1 m/s and
  its 0.5 rad/s turn in place). The gate opens further the longer the observer coasts, for every frame:
  a coasting observer's estimate moves on without the target (the paper's u_e without a measurement is
  its consensus and GP terms only, which a blind neighbour's estimate drives; measured on the emulated
  lab, the prediction left the true markers at 25–80 px/s while coasting), so a frame tagged damaged
  widens it as a clean one does, or a turn during a concealment (up to 2.2 s on a Tello) would lock the
  target out; a ghost is caught when it jumps, not after the estimate has had time to drift as far;
* the warm-up: after a (re)start the estimate is only a guess from the desired pose, converging; the
  detections are taken (the gate learns θ and σ_track from them) until at least TRACK_WINDOW were and
  the lag's shift has slowed to s (its rate ‖(ṫ_x, ṫ_y)‖ ≤ s): judged from then on. With a fixed count of
  10 the gate closed while the estimate was still converging at 40 px/s and coasted for 2 s. A detection
  taken after a coast longer than OFFSET_HORIZON_S re-acquires: θ is set to its fit, θ̇ to 0 (the lag
  learnt before the coast no longer applies; α-β would keep half of it and reject the next frame); such a
  θ̇ = 0 is not a learnt rate, so only a detection that makes an α-β step can end the warm-up (when a
  re-acquisition could, a stream with gaps over OFFSET_HORIZON_S closed the gate while still converging);
* n_σ = 4 (GateSpec.sigmas): with Gaussian pixel noise of σ per axis a marker's distance exceeds 4σ with
  probability e^(−8) ≈ 3.4e-4, the largest of m = 4 with ≈ 1.3e-3.

The shape of a concealed frame's board. A concealed picture's ghost is often not a rigid copy: where the
board is partly copied from an older picture, its corners move apart, by a shape no pose of a level target
gives. `benchmarks/concealed_frames.py` (six 30 s streams, 0.2 % and 2 % of the datagrams lost) finds 69 of
the 1,633 boards detected in damaged frames more than 3 px off the truth; in 60 of them all corners but one
lie where a pose puts them, the odd one off, and no board within 1 px is so. So in a frame decoded through
a detected loss the frame's own fit, not the lag, judges the shape:

    e^j = d^j − (M θ_f)^j,    q = max_j ‖e^j‖  ≤  shape gate = n_σ · sqrt((σ_cal² + σ_shape²) · k_m)

* θ_f: the least-squares similarity of this frame's offsets d (the pose error of a level target, whatever
  the estimate's lag). It takes 4 of the 2m offsets' degrees of freedom, so under pixel noise σ per axis
  Σ_j ‖e^j‖² has mean (2m − 4)σ² and each e^j a variance of σ²·k_m per axis, k_m = (2m − 4)/(2m) (1/2
  for m = 4 markers, 1/3 for the m − 1 = 3 of a mended board);
* σ_shape²: the mean of ‖e^j‖²/(2 k_m) over the recent accepted detections (TRACK_WINDOW), as seen (not
  mended): the noise the prediction's own shape error implies (the drone's tilt, which the paper's 4-DOF
  pose does not carry), learnt as σ_track is, from the detections the warm-up takes on: like the gate,
  the shape gate judges only once the warm-up is over (a shape error larger than the gate at the start
  would otherwise refuse every detection, and nothing would teach σ_shape), and it outlives a coast (it is
  the camera's and the prediction's, not the lag's).

A board off its shape whose markers but one fit a pose is mended: of the m leave-one-out similarities,
the one whose m − 1 markers lie closest to it, if within the shape gate of m − 1 markers, replaces the odd
marker by where the others put it (the measurement becomes the prediction moved by their similarity), and
the position gate judges the mended board as any other. Concealment damages the picture from the lost
datagram's macroblock on, so a board across that line keeps some corners intact. In the benchmark the 60
mended boards were all more than 3 px off as detected, 29 after; the boards more than 3 px off in damaged
frames fell from 69 to 38 (more than 10 px: 3 to 1). A board that no m − 1 markers explain is judged as
detected: replacing it by its own least-squares pose brought none of the 5 such boards within 3 px, and it
would shrink a wild detection's residual before the position gate sees it. No board is refused for its
shape: refusing them (tried on the `lab-wifi` twin) coasted the observer through whole concealed
stretches, up to the next keyframe 2.2 s on, and a coast during a turn drifts farther than a ghost's few
pixels (56 px in one turn; one `dgp` mode lost the target in both runs).

A level camera over a level board sees every pose error as a similarity (a translation of the plane: a
shift; of the depth: a scale about the principal point; a yaw: a rotation), so the check asks nothing the
4-DOF estimate cannot give. A tilted one does not: the drone's roll and pitch (it tilts to accelerate;
the twin's camera stays level) change the board's shape by up to 1.5 px at 5° and 3.1 px at 10° (fx =
260 px, the board 0.7 m below, anywhere in the picture: OpenCV's projection, tests/test_vision_gate.py).
σ_shape follows that error as the clean frames show it, but a tilt that changes faster than its window
would mend good detections; so the shape is judged only in frames tagged damaged, where
concealment is known to have happened (every frame tagged clean had the board within 1 px in
`benchmarks/concealed_frames.py`), and the position gate judges every frame.

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
"""Accepted detections in σ_track's exponential window (0.5 s at the 20 Hz loop), and the warm-up."""
OFFSET_GAIN = 0.5
"""α of the lag's α-β tracker: the share of a detection's surprise that moves θ."""
OFFSET_RATE_GAIN = OFFSET_GAIN**2 / (2.0 - OFFSET_GAIN)
"""β of the lag's α-β tracker (Benedict–Bordner: β = α²/(2 − α), the least-squares-optimal pair)."""
MIN_STEP_S = 0.01
"""Shortest capture-time step (s) the rate is learnt over: two frames stamped closer are not a rate."""
OFFSET_HORIZON_S = 0.1
"""Longest time (s) over which θ is extrapolated with its rate (two ticks at 20 Hz, three frames at 30 fps):
past it the observer has coasted, its estimate no longer follows the measurements whose lag the rate was
learnt from, and what it may have missed is the drift term's to cover."""
OFF_PREDICTION = "off prediction"
"""The rejection reason of a detection outside the gate (TickRecord.rejection, counted per drone)."""


def similarity_basis(p: np.ndarray) -> np.ndarray:
    """M (2m, 4) with M θ the offsets (px, interleaved x, y) that θ = (t_x, t_y, a, c) gives points p (m, 2)
    (px): t + [[a, −c], [c, a]] (p^j − p̄), p̄ their centroid."""
    q = p - p.mean(axis=0)
    M = np.zeros((2 * len(p), 4))
    M[0::2, 0] = 1.0
    M[1::2, 1] = 1.0
    M[0::2, 2], M[0::2, 3] = q[:, 0], -q[:, 1]
    M[1::2, 2], M[1::2, 3] = q[:, 1], q[:, 0]
    return M


@dataclass(frozen=True)
class GateSpec:
    """The gate's settings: sigmas n_σ; drift_mps v_drift (m/s); drift_radps ω_drift (rad/s); noise_px
    σ_cal (px)."""

    sigmas: float = 4.0
    drift_mps: float = 0.1
    drift_radps: float = 0.5
    noise_px: float = DEFAULT_NOISE_PX

    def __post_init__(self) -> None:
        values = (self.sigmas, self.drift_mps, self.drift_radps, self.noise_px)
        if not (self.sigmas > 0 and self.drift_mps >= 0 and self.drift_radps >= 0 and self.noise_px > 0):
            raise ValueError(f"need sigmas > 0, drift_mps >= 0, drift_radps >= 0, noise_px > 0, got {self}")
        if not all(map(math.isfinite, values)):
            raise ValueError(f"gate settings must be finite, got {self}")


@dataclass(frozen=True)
class GateVerdict:
    """One detection judged: accepted, its residual r and the gate it was held to, its shape residual q
    and the shape gate (px); for a damaged frame's board whose one marker is off the others' shape, the
    features mended (2m,) (image-plane units: the prediction moved by the others' similarity), which the
    residual r judged, and that marker; else None."""

    accepted: bool
    residual_px: float
    gate_px: float
    shape_px: float = math.nan
    shape_gate_px: float = math.nan
    mended: np.ndarray | None = None
    replaced_marker: int | None = None  # the marker mended, None when not


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
        self._lag = np.zeros(4)  # θ = (t_x px, t_y px, a, c) at the last accepted detection
        self._lag_rate = np.zeros(4)  # θ̇ (per s)
        self._track_var = 0.0  # σ_track² (px² per axis)
        self._shape_var = 0.0  # σ_shape² (px² per axis)
        self._judged: tuple[float, GateVerdict] | None = None  # the last frame judged (capture time, verdict)
        self._t_accepted = -math.inf  # capture time of the last accepted detection (s)
        self._learned = 0  # accepted detections since the (re)start
        self._settled = False  # the warm-up is over: the estimate converged (module docstring)
        self.accepted = 0
        self.rejected = 0

    def gate_px(self, t_capture: float, depth_m: float, spread_px: float = 0.0) -> float:
        """The gate (px) for a frame captured at t_capture (s) whose points lie depth_m ahead (m), spread_px
        from their centroid on average (px) (module docstring)."""
        tau = t_capture - self._t_accepted
        if not self._settled or not math.isfinite(tau):
            return math.inf
        noise = self.spec.sigmas * math.sqrt(self.spec.noise_px**2 + self._track_var)
        return noise + self.drift_px_per_s(depth_m, spread_px) * max(tau, 0.0)

    def shape_gate_px(self, m: int = 4) -> float:
        """The shape gate of m markers with the σ_shape learnt (px; shape_gate_px); infinite during the
        warm-up."""
        if not self._settled:
            return math.inf
        return shape_gate_px(m, self.spec.sigmas, math.sqrt(self.spec.noise_px**2 + self._shape_var))

    def drift_px_per_s(self, depth_m: float, spread_px: float) -> float:
        """s = v_drift·fx/z̄ + ω_drift·ρ̄ (px/s) of points depth_m ahead (m), spread_px from their centroid."""
        return self.spec.drift_mps * self.fx_px / max(depth_m, 1e-3) + self.spec.drift_radps * spread_px

    def expected(self, f_pred: np.ndarray, t_capture: float) -> np.ndarray | None:
        """Where the gate expects the features (2m,) (image-plane units) of a frame captured at t_capture
        (s) whose prediction is f_pred: f̄ moved by the lag b̂ as `check` moves it (module docstring).
        None during the warm-up, when the gate judges nothing and has learnt no lag."""
        tau = t_capture - self._t_accepted
        if not self._settled or not math.isfinite(tau):
            return None
        p = np.asarray(f_pred, dtype=float).reshape(-1, 2) * self.px_per_unit
        lag = self._lag + self._lag_rate * min(max(tau, 0.0), OFFSET_HORIZON_S)
        return (p + (similarity_basis(p) @ lag).reshape(-1, 2)).reshape(-1) / self.px_per_unit

    def check(
        self, f: np.ndarray, f_pred: np.ndarray, depth_m: float, t_capture: float, damaged: bool = False
    ) -> GateVerdict:
        """Judge features f against their prediction f_pred (both (2m,), image-plane units) for a frame
        captured at t_capture (s) with its points depth_m ahead (m); damaged: the frame was decoded through
        a detected loss, its shape is judged too (module docstring)."""
        if self._judged is not None and self._judged[0] == t_capture:
            return self._judged[1]  # the same frame again (no newer one yet): judged once, counted once
        verdict = self._judge(f, f_pred, depth_m, t_capture, damaged)
        self._judged = (t_capture, verdict)
        return verdict

    def _judge(
        self, f: np.ndarray, f_pred: np.ndarray, depth_m: float, t_capture: float, damaged: bool
    ) -> GateVerdict:
        d = (np.asarray(f, dtype=float) - np.asarray(f_pred, dtype=float)).reshape(-1, 2) * self.px_per_unit
        p = np.asarray(f_pred, dtype=float).reshape(-1, 2) * self.px_per_unit
        M = similarity_basis(p)
        first = self._learned == 0
        tau = t_capture - self._t_accepted
        fit, shape2 = similarity_fit(d, M)
        m = len(d)
        q, shape_gate = math.sqrt(float(shape2.max())), self.shape_gate_px(m)
        mended = replaced = None
        one = mend_board(d, M, self.shape_gate_px(m - 1)) if damaged and q > shape_gate else None  # NaN: no
        if one is not None:
            fit, replaced = one
            d = (M @ fit).reshape(-1, 2)
            mended = (p + d).reshape(-1) / self.px_per_unit
        lag = fit if first else self._lag + self._lag_rate * min(max(tau, 0.0), OFFSET_HORIZON_S)
        dev = d - (M @ lag).reshape(-1, 2)
        dist2 = (dev * dev).sum(axis=1)
        r = math.sqrt(float(dist2.max()))
        spread = float(np.linalg.norm(p - p.mean(axis=0), axis=1).mean())
        gate = self.gate_px(t_capture, depth_m, spread)
        if not (r <= gate):  # NaN too
            self.rejected += 1
            return GateVerdict(False, r, gate, q, shape_gate, mended, replaced)
        self.accepted += 1
        reacquired = first or tau > OFFSET_HORIZON_S
        if reacquired:  # after a coast: the lag learnt before is stale
            self._lag, self._lag_rate = fit, np.zeros(4)
        else:
            surprise = fit - lag
            self._lag = lag + OFFSET_GAIN * surprise
            self._lag_rate = self._lag_rate + OFFSET_RATE_GAIN * surprise / max(tau, MIN_STEP_S)
        a = 1.0 if first else 1.0 / TRACK_WINDOW
        self._track_var = (1 - a) * self._track_var + a * float(dist2.mean()) / 2.0
        if mended is None and m > 2:  # of shapes as seen
            self._shape_var = (1 - a) * self._shape_var + a * float(shape2.mean()) / (2.0 * _shape_share(m))
        self._learned += 1
        if not (self._settled or reacquired):  # the warm-up ends once the lag's shift, as learnt, has slowed
            slowed = float(np.linalg.norm(self._lag_rate[:2])) <= self.drift_px_per_s(depth_m, spread)
            self._settled = self._learned >= TRACK_WINDOW and slowed
        self._t_accepted = max(self._t_accepted, t_capture)
        return GateVerdict(True, r, gate, q, shape_gate, mended, replaced)


def similarity_fit(d: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θ_f, ‖e^j‖² (m,) px²): the least-squares similarity of offsets d (m, 2) (px; M their
    similarity_basis) and what it leaves of each marker's offset (module docstring: the shape); NaN for
    offsets that are not finite."""
    if not np.all(np.isfinite(d)):
        return np.full(4, np.nan), np.full(len(d), np.nan)
    fit = np.linalg.lstsq(M, d.reshape(-1), rcond=None)[0]
    e = d - (M @ fit).reshape(-1, 2)
    return fit, (e * e).sum(axis=1)


def shape_gate_px(m: int, sigmas: float, noise_px: float) -> float:
    """n_σ · noise · sqrt(k_m) (px): the shape gate of m markers under pixel noise noise_px per axis
    (sqrt(σ_cal² + σ_shape²); module docstring); infinite for m ≤ 2 (a similarity explains any two)."""
    return math.inf if m <= 2 else sigmas * noise_px * math.sqrt(_shape_share(m))


def _shape_share(m: int) -> float:
    """k_m = (2m − 4)/(2m): the share of the pixel noise's variance per axis that is left in a marker's
    offset after a similarity is fitted to m markers (module docstring)."""
    return (2 * m - 4) / (2 * m)


def _farthest(offsets: np.ndarray) -> float:
    """The largest norm of the rows of offsets (m, 2) (px)."""
    return math.sqrt(float((offsets * offsets).sum(axis=1).max()))


def mend_board(d: np.ndarray, M: np.ndarray, gate_px: float) -> tuple[np.ndarray, int] | None:
    """(θ, the marker replaced) for offsets d (m, 2) (px) off their shape (module docstring): of the m
    leave-one-out similarities (M: similarity_basis of the predicted markers), the one whose m − 1 markers
    lie closest to it, if within gate_px (the shape gate of m − 1 markers); else None."""
    best: tuple[float, int, np.ndarray] | None = None
    for j in range(len(d) if len(d) > 3 else 0):  # m − 1 ≥ 3 markers: a similarity fits any two
        keep = [k for k in range(2 * len(d)) if k // 2 != j]
        theta = np.linalg.lstsq(M[keep], d.reshape(-1)[keep], rcond=None)[0]
        worst = _farthest((d.reshape(-1)[keep] - M[keep] @ theta).reshape(-1, 2))
        if best is None or worst < best[0]:
            best = (worst, j, theta)
    if best is None or not (best[0] <= gate_px):
        return None
    return best[2], best[1]


__all__ = [
    "DEFAULT_NOISE_PX",
    "OFFSET_GAIN",
    "OFFSET_HORIZON_S",
    "OFFSET_RATE_GAIN",
    "OFF_PREDICTION",
    "TRACK_WINDOW",
    "DetectionGate",
    "GateSpec",
    "GateVerdict",
    "mend_board",
    "shape_gate_px",
    "similarity_basis",
    "similarity_fit",
]
