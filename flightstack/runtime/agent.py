"""One drone's pursuit step (DESIGN §2): a control tick in two phases.

Phase 1, `sense_and_publish(t)`: read the own pose g_wi, advance the observer over the elapsed time,
read the camera, compute e_e = J⁺(f − f̄), evaluate the own GP expert at the own estimate ḡ_w,i and
publish (ḡ_w,i, μ, var). Phase 2, `fuse_control_act(t)`: take the neighbours' fresh messages, fuse the
predictions (mode `dgp`), form the consensus term c_i, compute (u_c, u_e) and send V_wi = −Ad_{g_d} u_c.

Modes: `none` (μ = 0), `local` (own expert only), `dgp` (own + neighbours fused by the mission's rule),
`oracle` (μ from a supplied ground-truth predictor: the sim-only reference for tests).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from flightstack.comms.bus import PredictionBus
from flightstack.comms.messages import PredictionMessage
from flightstack.config.types import Mode
from flightstack.hal import Camera, Drone, Frame, PoseSource, StampedPose
from flightstack.paper import kernels as kern
from flightstack.paper.control import Gains
from flightstack.paper.delay_compensation import (
    CURRENT_S,
    TIME_NOT_FINITE,
    CommandModel,
    Compensation,
    EstimateHistory,
    PoseHistory,
    carry_error,
    stamp_refusal,
)
from flightstack.paper.fusion import FUSION_RULES
from flightstack.paper.geometry import Pose
from flightstack.paper.projection import CameraModel
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity
from flightstack.safety import SafetyLimits
from flightstack.safety.rules import saturate
from flightstack.vision.camera_file import CameraCalibration
from flightstack.vision.detect import detect_markers
from flightstack.vision.fiducial import NOT_FOUND, distorted_pixels, track_fiducial
from flightstack.vision.gate import OFF_PREDICTION, DetectionGate, GateSpec
from flightstack.vision.markers import features_from_detection

UNINFORMATIVE_VAR = np.ones(4)


class Predictor(Protocol):
    """A GP expert (flightstack.paper.gp.GPExpert) or anything with the same two calls."""

    def predict_one(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def prior_var(self) -> np.ndarray: ...


@dataclass(frozen=True)
class AgentConfig:
    mission: str
    drone_id: int
    body_name: str
    g_d: Pose
    P0: np.ndarray  # (m, 3) feature points in Σ0, metres
    camera: CameraModel
    gains: Gains
    mode: str
    fusion_rule: str
    neighbour_ids: tuple[int, ...]
    stale_after: float
    calibration: CameraCalibration | None = None  # image cameras: marker colours and intrinsics
    max_frame_age_s: float = math.inf  # a frame older than this (s, vs the tick time) counts as none
    compensation: Compensation | None = None  # None: the paper's law (docs/equations.md §11)
    command_limits: SafetyLimits | None = None  # what the safety layer lets through (the command model's)
    gate: GateSpec | None = None  # image detections checked against a prediction (vision.gate); None: not


@dataclass
class TickRecord:
    """What the agent did in its last tick (for recordings and metrics)."""

    g_bar_w: Pose
    visible: bool = False
    e_e_meas: np.ndarray = field(default_factory=lambda: np.zeros(4))
    mu_own: np.ndarray = field(default_factory=lambda: np.zeros(4))
    var_own: np.ndarray = field(default_factory=lambda: UNINFORMATIVE_VAR.copy())
    mu_used: np.ndarray = field(default_factory=lambda: np.zeros(4))
    u_c: np.ndarray = field(default_factory=lambda: np.zeros(4))
    u_e: np.ndarray = field(default_factory=lambda: np.zeros(4))
    V_cmd: np.ndarray = field(default_factory=lambda: np.zeros(4))
    n_fused: int = 0
    neighbours_used: tuple[int, ...] = ()  # neighbours whose fresh message entered consensus (and fusion)
    rejection: str | None = None  # why the image gave no features (None: seen, or no image)
    # samples refused this tick for their time (delay_compensation.stamp_refusal), each counted once
    dropped: list[str] = field(default_factory=list)
    own_pose_fresh: bool = True  # False: motion capture lost the drone; it hovers (V = 0) this tick
    # ages at use (s, mission clock): t − stamp; a sample that arrived after the tick's start t counts 0
    frame_age: float = math.nan  # the camera frame looked at; NaN: no frame
    pose_age: float = math.nan  # the own pose used; NaN: none this tick (dropout)
    # the detection gate (flightstack.vision.gate), for a tick whose image gave all the markers
    coasted: bool = False  # the detection was off its prediction: the observer coasted on its estimate
    tracked: bool = False  # the fiducial was found from where the gate expected it (vision.fiducial)
    frame_damaged: bool = False  # the frame looked at was decoded through a detected stream loss
    gate_residual_px: float = math.nan  # the marker farthest from its prediction (px); NaN: not gated
    gate_px: float = math.nan  # the gate it was held to (px)
    gate_shape_px: float = math.nan  # the markers' shape residual q against the prediction (px)
    mended: bool = False  # a damaged frame's board had one marker off the others' shape, mended (vision.gate)
    detection_error_px: float = math.nan  # farthest marker from the truth (simulated cameras only; px)


class Agent:
    """One drone's control tick; its math is two compiled kernels (flightstack.paper.kernels.agent_sense
    and agent_act, the copy the compiled simulator also calls), its glue the devices and the bus.

    State: the agent's tick buffer `_T` (10, 4) (rows kernels.G_BAR_W … V_CMD; ḡ_w,i in row G_BAR_W is
    the observer state), the last u_e and its time."""

    def __init__(
        self,
        cfg: AgentConfig,
        drone: Drone,
        camera: Camera,
        poses: PoseSource,
        bus: PredictionBus,
        predictor: Predictor | None,
        g_bar_w0: Pose,
    ) -> None:
        if Mode(cfg.mode).needs_predictor and predictor is None:
            raise ValueError(f"mode {cfg.mode!r} needs a predictor (GP expert)")
        self.cfg = cfg
        self.drone = drone
        self.camera = camera
        self.poses = poses
        self.bus = bus
        self.predictor = predictor
        self.seq = 0
        self._T = np.zeros((10, 4))
        self._T[kern.G_BAR_W] = g_bar_w0.as_vector()
        self._u_e_prev: np.ndarray | None = None
        self._t_prev: float | None = None
        self._g_wi: np.ndarray | None = None  # the own pose g_wi as a vector (last one measured)
        self._g_wi_t = -math.inf  # when it was measured (s)
        # the newest frame and own pose whose stamps were accepted (`_checked`), and per kind the stamp
        # (its bytes) of the last one refused: read again, it is not counted again
        self._frame_ok: Frame | None = None
        self._pose_ok: StampedPose | None = None
        self._refused: dict[str, bytes] = {}
        limits, comp = cfg.command_limits, cfg.compensation
        # the oldest own pose the loop steers by (s): the safety layer's pose_timeout, and never older than
        # the compensation's history (a prediction from an older pose integrates commands it no longer has)
        self._max_pose_age_s = min(
            math.inf if limits is None else limits.pose_timeout, math.inf if comp is None else comp.history_s
        )
        self._delays = None if comp is None else _Delays(comp)
        self._P0 = np.ascontiguousarray(cfg.P0, dtype=float)
        self._cam = cfg.camera.packed
        self._g_d = cfg.g_d.as_vector()
        self._mode = MODE_CODES[Mode(cfg.mode)]
        self.rule_code = FUSION_RULES.index(cfg.fusion_rule)  # the kernels' fusion rule
        self._no_features = np.zeros(2 * len(self._P0))
        k = max(1, len(cfg.neighbour_ids))
        self._N = np.zeros((4, k, 4))  # neighbour messages: field (ḡ_w, μ, var, σ_f²) × neighbour × 4
        self._NG, self._NMU, self._NVAR, self._NPRIOR = self._N  # (k, 4) C-contiguous views: agent_act's
        self.last = TickRecord(g_bar_w0)
        # the marker centres (m, 2) in pixels of the distorted image the last tick detected; None when
        # it had no image, or the image was rejected (a viewer draws them over the frame)
        self.markers_px: np.ndarray | None = None
        self.hold = False  # set by the safety supervisor: hover instead of pursuing
        cal = cfg.calibration
        self.gate = (
            None
            if cfg.gate is None or cal is None
            else DetectionGate(cfg.gate, cal.fx, cfg.camera.focal_length)
        )

    @property
    def g_bar_w(self) -> Pose:
        """ḡ_w,i: the observer's estimate of the target pose in the world frame."""
        return pose_of(self._T[kern.G_BAR_W])

    def reset_estimate(self, g_bar_w: Pose, t: float | None = None) -> None:
        """Restart the observer from ḡ_w,i (e.g. at pursuit start on hardware, from the own pose and g_d).

        t: when (s, mission clock) it restarts. With delay compensation, ḡ_w,i is then also the estimate
        before t, back over the history (the observer's prior: it had nothing else), so that a frame
        captured up to history_s before the start is judged against it instead of being too old (a
        Tello's frames arrive 0.3–0.45 s after capture: the first 6–9 ticks of every mode saw nothing).
        """
        self._T[kern.G_BAR_W] = g_bar_w.as_vector()
        self._u_e_prev = None
        self._t_prev = None
        if self._delays is not None:
            self._delays.estimates.clear()
            if t is not None:
                self._delays.estimates.add(t - self._delays.c.history_s, self._T[kern.G_BAR_W], _ZERO4)
        if self.gate is not None:  # the new estimate has predicted nothing yet
            self.gate.reset()

    def seed_own_pose(self, own: StampedPose) -> None:
        """The own pose measured at pursuit start (the runner's, after takeoff) as the last one seen: a
        motion-capture dropout at the first tick is then a dropout like any other (keep it, hover; the
        safety layer decides beyond pose_timeout), not a missing pose that ends the mission."""
        self._g_wi, self._g_wi_t = own.pose.as_vector(), own.stamp
        self._pose_ok = own

    def record_own_pose(self, t: float) -> None:
        """Keep the own pose measured now (motion capture, its stamp no later than the clock's t, s) for
        the delay compensation: called while the drones climb, so that a frame captured before pursuit
        starts finds the pose it was taken from. Nothing without compensation."""
        own = self.poses.latest(self.cfg.body_name)
        if self._delays is not None and own is not None and stamp_refusal(own.stamp, t, "pose") is None:
            self._delays.poses.add(own.stamp, own.pose.as_vector())

    # ---- phase 1 -------------------------------------------------------------------------------
    def sense_and_publish(self, t: float) -> None:
        cfg, T = self.cfg, self._T
        dropped: list[str] = []
        own = self._checked_pose(self.poses.latest(cfg.body_name), t, dropped)
        fresh = own is not None
        if own is not None:
            self._g_wi, self._g_wi_t = own.pose.as_vector(), own.stamp
            if self._delays is not None:
                self._delays.poses.add(own.stamp, self._g_wi)
        elif self._g_wi is None:
            raise RuntimeError(f"no pose for {cfg.body_name}")
        # else a motion-capture dropout: keep the last pose, hover; the safety layer decides beyond that
        frame = self._checked_frame(self.camera.latest(), t, dropped)
        features, rejection = self._features(frame, t)
        tracked = False
        if features is None and frame is not None and rejection is not None and rejection.endswith(NOT_FOUND):
            features, rejection = self._tracked(frame, rejection)
            tracked = features is not None
        gated = _Gated()
        if features is not None and frame is not None and frame.features is None:
            features, rejection, gated = self._gated(features, rejection, frame)
        late = None  # a frame captured before the tick, compensated: its capture time (s)
        if self._delays is not None and features is not None and frame is not None:
            late, why = self._delays.frame_time(frame.stamp, t)
            if why is not None:
                features, rejection, late = None, why, None
        step = self._u_e_prev is not None and self._t_prev is not None and t > self._t_prev
        visible = kern.agent_sense(
            T,
            self._u_e_prev if self._u_e_prev is not None else _ZERO4,
            t - self._t_prev if step and self._t_prev is not None else 0.0,
            self._g_wi,
            features if features is not None and late is None else self._no_features,
            features is not None and late is None,
            self._P0,
            self._cam,
        )
        if late is not None and features is not None and self._delays is not None:
            visible, rejection = self._delays.sense_late(T, features, late, t, self._P0, self._cam)
        g_bar_w = pose_of(T[kern.G_BAR_W])  # the estimate after the observer step
        x = T[kern.G_BAR_W].copy()
        if self.predictor is not None and cfg.mode != Mode.NONE:
            mu, var = self.predictor.predict_one(x)
            prior = self.predictor.prior_var()
        else:
            mu, var, prior = np.zeros(4), UNINFORMATIVE_VAR, UNINFORMATIVE_VAR
        T[kern.MU_OWN], T[kern.VAR_OWN], T[kern.PRIOR] = mu, var, prior
        rec = TickRecord(
            g_bar_w,
            visible=bool(visible),
            e_e_meas=T[kern.E_E].copy(),
            mu_own=mu,
            var_own=var,
            rejection=rejection,
            dropped=dropped,
            own_pose_fresh=fresh,
            frame_age=math.nan if frame is None else max(0.0, t - frame.stamp),
            pose_age=math.nan if own is None else max(0.0, t - own.stamp),
            coasted=gated.coasted,
            tracked=tracked,
            frame_damaged=frame is not None and frame.damaged,
            gate_residual_px=gated.residual_px,
            gate_px=gated.gate_px,
            gate_shape_px=gated.shape_px,
            mended=gated.mended,
            detection_error_px=gated.error_px,
        )
        self.last = rec
        self.seq += 1
        self.bus.publish(
            PredictionMessage(cfg.mission, cfg.drone_id, self.seq, t, rec.visible, x, mu, var, prior)
        )

    def _checked_pose(self, own: StampedPose | None, t: float, dropped: list[str]) -> StampedPose | None:
        """The own pose to use at the tick of time t (s): the newest of `own` (if its stamp may enter,
        `_admitted`) and the last one accepted, while it is no older than the safety layer's pose_timeout
        (else None: a dropout, the drone hovers). A pose stamped in the past is as stale as its stamp:
        taken as fresh, the compensated command predicted the own pose over every command since that
        stamp (4.8 m/s commanded from a pose 1 s old, 8.4e7 m/s when its old stamp repeated)."""
        if own is None:
            return None
        if self._admitted("pose", own.stamp, t, dropped) and (
            self._pose_ok is None or own.stamp >= self._pose_ok.stamp
        ):
            self._pose_ok = own
        last = self._pose_ok
        return last if last is not None and t - last.stamp <= self._max_pose_age_s else None

    def _checked_frame(self, frame: Frame | None, t: float, dropped: list[str]) -> Frame | None:
        """The frame to look at at the tick of time t (s): `frame` if its stamp may enter, else, as if it
        had not arrived, the last one accepted (its age is checked as any frame's: `_features`)."""
        if frame is None:
            return None
        if self._admitted("frame", frame.stamp, t, dropped):
            self._frame_ok = frame
            return frame
        return self._frame_ok

    def _admitted(self, kind: str, stamp: float, t: float, dropped: list[str]) -> bool:
        """Whether a sample of `kind` stamped `stamp` (s) may enter at the tick of time t (s)
        (delay_compensation.stamp_refusal). A refusal is appended to `dropped` once per refused sample:
        the same stamp read again (the source has nothing newer) is not counted again."""
        why = stamp_refusal(stamp, t, kind)
        if why is None:
            self._refused.pop(kind, None)
            return True
        key = struct.pack("<d", stamp)
        if self._refused.get(kind) != key:
            self._refused[kind] = key
            dropped.append(why)
        return False

    def _features(self, frame: Frame | None, t: float) -> tuple[np.ndarray | None, str | None]:
        """(f (2m,), None) from the frame: given directly (ideal camera) or extracted from the image; or
        (None, why the image gave no features: TickRecord.rejection)."""
        self.markers_px = None
        if frame is None:
            return None, "no frame"
        if t - frame.stamp > self.cfg.max_frame_age_s:
            return None, "stale frame"
        if frame.features is not None:
            f = np.array(frame.features, dtype=float).reshape(-1)  # a writable copy: the kernels' type
            if f.shape != self._no_features.shape or not all(map(math.isfinite, f.tolist())):
                return None, "bad features"  # e.g. a served frame with another marker count
            return f, None
        if frame.image is None or self.cfg.calibration is None:
            return None, None
        det = detect_markers(frame.image, self.cfg.calibration, roi=frame.roi)
        self.markers_px = det.pixels
        seen = features_from_detection(det, self.cfg.camera.focal_length)
        return (None if seen is None else np.array(seen, dtype=float).reshape(-1)), det.reason

    def _prediction(self, frame: Frame) -> tuple[np.ndarray, float] | None:
        """(f̄ (2m,) image-plane units, the points' mean depth m) of the target in `frame`, predicted for its
        capture time from outside the image: from the agent's pose and estimate histories when it keeps
        them (delay compensation), else from the own pose last measured and the estimate moved on to the
        frame's time by the observer's own prediction step. None when the estimate puts it out of view."""
        if self._g_wi is None:
            return None
        g_wi, g_bar = self._g_wi, self._T[kern.G_BAR_W]
        g_c = g_bar_c = None
        if self._delays is not None:
            g_c, g_bar_c = self._delays.poses.at(frame.stamp), self._delays.estimates.at(frame.stamp)
        if g_c is not None and g_bar_c is not None:
            g_wi, g_bar = g_c, g_bar_c
        elif self._u_e_prev is not None and self._t_prev is not None:  # the estimate moved on to the frame
            g_bar = np.empty(4)  # as the observer's own prediction step moves it (−u_e held)
            kern.integrate4(
                self._T[kern.G_BAR_W], -self._u_e_prev, max(0.0, frame.stamp - self._t_prev), g_bar
            )
        rel, pc = np.empty(4), np.empty_like(self._P0)
        kern.relative4(g_wi, g_bar, rel)
        kern.points_in_camera(rel, self._P0, self._cam, pc)
        f_pred = np.empty(2 * len(self._P0))
        if not kern.measure(rel, self._P0, self._cam, f_pred):
            return None
        return f_pred, float(pc[:, 2].mean())

    def _tracked(self, frame: Frame, rejection: str) -> tuple[np.ndarray | None, str | None]:
        """When the fiducial detector did not find the target: look for it where the detection gate
        expects it (flightstack.vision.fiducial.track_fiducial). (features or None, the rejection)."""
        cal = self.cfg.calibration
        if self.gate is None or cal is None or cal.fiducial is None or frame.image is None:
            return None, rejection
        pred = self._prediction(frame)
        expected = None if pred is None else self.gate.expected(pred[0], frame.stamp)
        if expected is None:
            return None, rejection
        lam = self.cfg.camera.focal_length
        det = track_fiducial(frame.image, distorted_pixels(expected.reshape(-1, 2) / lam, cal), cal)
        seen = features_from_detection(det, lam)
        if seen is None:
            return None, det.reason or rejection
        self.markers_px = det.pixels
        return np.array(seen, dtype=float).reshape(-1), None

    def _gated(
        self, features: np.ndarray, rejection: str | None, frame: Frame
    ) -> tuple[np.ndarray | None, str | None, _Gated]:
        """The image's features through the detection gate (flightstack.vision.gate) against `_prediction`:
        (features or None, the rejection, what the gate saw). A board the gate mended (a damaged frame's,
        off its shape) is used as mended, and its markers' pixels become the mended ones: the truth error
        is that of the measurement the observer gets."""
        out = _Gated(error_px=_truth_error(self.markers_px, frame.truth_px))
        if self.gate is None:
            return features, rejection, out
        pred = self._prediction(frame)
        if pred is None:  # the estimate puts the target out of view
            return features, rejection, out
        verdict = self.gate.check(features, pred[0], pred[1], frame.stamp, frame.damaged)
        out.residual_px, out.gate_px, out.shape_px = verdict.residual_px, verdict.gate_px, verdict.shape_px
        cal = self.cfg.calibration
        if verdict.accepted and verdict.mended is not None:
            out.mended = True
            lam = self.cfg.camera.focal_length
            self.markers_px = (
                None if cal is None else distorted_pixels(verdict.mended.reshape(-1, 2) / lam, cal)
            )
            out.error_px = _truth_error(self.markers_px, frame.truth_px)
        if out.mended:
            return verdict.mended, rejection, out
        if verdict.accepted:
            return features, rejection, out
        out.coasted = True
        return None, OFF_PREDICTION, out

    # ---- phase 2 -------------------------------------------------------------------------------
    def fuse_control_act(self, t: float) -> np.ndarray:
        cfg, rec, T = self.cfg, self.last, self._T
        if self._g_wi is None:
            raise RuntimeError("fuse_control_act before sense_and_publish")
        n = 0
        used = []
        for j in cfg.neighbour_ids:
            m = self.bus.latest(j, t, cfg.stale_after)
            if m is not None:
                body = m.body()
                if body is not None:  # a decoded message: its four fields are one array
                    self._N[:, n] = body.reshape(4, 4)
                else:
                    self._NG[n], self._NMU[n], self._NVAR[n], self._NPRIOR[n] = (
                        m.g_bar_w,
                        m.mu,
                        m.var,
                        m.prior_var,
                    )
                used.append(m.sender)
                n += 1
        rec.neighbours_used = tuple(used)
        hover = self.hold or not rec.own_pose_fresh
        rec.n_fused = self._law(T, n, hover)
        if self._delays is not None:
            if not self._delays.estimates.add(t, T[kern.G_BAR_W], T[kern.U_E]):
                rec.dropped.append(TIME_NOT_FINITE)
            if not hover and self._g_wi is not None:
                self._delays.command_ahead(T, self._g_wi, self._g_wi_t, t, lambda T2: self._law(T2, n, False))
        V = T[kern.V_CMD].copy()
        self.drone.send_body_velocity(V)
        if self._delays is not None:  # the command as the drone gets it, past the safety layer's limits
            lim = self.cfg.command_limits
            if not self._delays.commands.sent(t, V if lim is None else saturate(V, lim)[0]):
                rec.dropped.append(TIME_NOT_FINITE)
        rec.mu_used, rec.u_c, rec.u_e, rec.V_cmd = (
            T[kern.MU_USED].copy(),
            T[kern.U_C].copy(),
            T[kern.U_E].copy(),
            V,
        )
        self._u_e_prev, self._t_prev = rec.u_e, t
        return V

    def _law(self, T: np.ndarray, n: int, hover: bool) -> int:
        """agent_act on the tick buffer T with the first n neighbour messages; how many experts fused."""
        g = self.cfg.gains
        return int(kern.agent_act(
            T, self.last.visible, self._NG, self._NMU, self._NVAR, self._NPRIOR, n, self._mode,
            self.rule_code, self._g_d, g.k_c, g.k_e, g.k_s, hover,
        ))  # fmt: skip


_ZERO4 = np.zeros(4)


@dataclass
class _Gated:
    """What the detection gate saw in one tick (TickRecord's fields of the same names)."""

    coasted: bool = False
    residual_px: float = math.nan
    gate_px: float = math.nan
    shape_px: float = math.nan
    mended: bool = False
    error_px: float = math.nan


def _truth_error(pixels: np.ndarray | None, truth: np.ndarray | None) -> float:
    """The detected marker farthest from its true pixel (px); NaN without both or with another count."""
    if pixels is None or truth is None or np.shape(pixels) != np.shape(truth):
        return math.nan
    d = np.asarray(pixels, dtype=float) - np.asarray(truth, dtype=float)
    return float(np.sqrt((d * d).sum(axis=1)).max())


VELOCITY_WINDOW_S = 1.0
"""A late frame's error is carried over its delay with the target moving at the estimate's mean velocity
over this window (s): long against the observer's corrections (1/k_e), so they do not feed back."""


class _Delays:
    """The agent's delay compensation (docs/equations.md §11): its own poses, estimates and commands, and
    the two steps that use them."""

    def __init__(self, c: Compensation) -> None:
        self.c = c
        self.poses = PoseHistory(c.history_s)
        self.estimates = EstimateHistory(c.history_s)
        self.commands = CommandModel(c.command_delay_s, c.response_s, c.history_s)
        self.newest_used = -math.inf  # capture time of the newest late frame used (s)

    def frame_time(self, stamp: float, t: float) -> tuple[float | None, str | None]:
        """(capture time if the frame is late, None if current; why it is not used, or None). Only late
        frames are kept in order: a current one (stamped from 1 µs before the tick up to
        AHEAD_TOLERANCE_S after it) is used as it is and leaves the mark where it was, so one stamped
        ahead of a late stream never holds the frames after it back."""
        if stamp >= t - CURRENT_S:
            return None, None
        if stamp < self.newest_used:
            return None, "frame out of order"
        self.newest_used = stamp
        if stamp < t - self.c.history_s:
            return None, "frame too old"
        return stamp, None

    def sense_late(
        self, T: np.ndarray, f: np.ndarray, t_c: float, t: float, P0: np.ndarray, cam: np.ndarray
    ) -> tuple[bool, str | None]:
        """e_e from features captured at t_c (s), carried to t; T[E_E] written. Returns (v_i, why the
        frame was not used or None)."""
        g_wi_c, g_bar_c = self.poses.at(t_c), self.estimates.at(t_c)
        if g_wi_c is None or g_bar_c is None:  # before the poses and estimates kept (e.g. a reset)
            return False, "frame too old"
        g_bar_i0_c = np.empty(4)
        kern.relative4(g_wi_c, g_bar_c, g_bar_i0_c)
        xi_c = np.empty(4)
        if kern.estimation_error(f, g_bar_i0_c, P0, cam, xi_c) != kern.OK:
            return False, None
        V0 = self.estimates.mean_velocity(t, VELOCITY_WINDOW_S)
        xi = carry_error(xi_c, g_bar_c, T[kern.G_BAR_W], V0, t - t_c)
        T[kern.E_E, 0], T[kern.E_E, 1], T[kern.E_E, 2], T[kern.E_E, 3] = xi[0], xi[1], xi[2], math.sin(xi[3])
        return True, None

    def command_ahead(
        self, T: np.ndarray, g_wi: np.ndarray, t_g: float, t: float, law: Callable[[np.ndarray], object]
    ) -> None:
        """Replace (u_c, V) of the law at t by the law at the state of t + horizon: the own pose from
        g_wi (measured at t_g) moved by the commands sent, the estimate moved on with −u_e. u_e stays
        the one at t (the observer is not delayed by the radio). `law` evaluates the law on a buffer."""
        h = self.c.horizon_s
        if h <= 0.0 or not math.isfinite(t):
            return
        g_pred = self.commands.predict(g_wi, t_g, t + h)
        g_bar_pred = np.empty(4)
        kern.integrate4(T[kern.G_BAR_W], -T[kern.U_E], h, g_bar_pred)
        T2 = T.copy()
        kern.relative4(g_pred, g_bar_pred, T2[kern.G_BAR_I0])
        law(T2)
        T[kern.U_C], T[kern.V_CMD] = T2[kern.U_C], T2[kern.V_CMD]


MODE_CODES = {
    # Mode -> the kernels' mode code
    Mode.NONE: kern.MODE_NONE,
    Mode.LOCAL: kern.MODE_LOCAL,
    Mode.DGP: kern.MODE_DGP,
    Mode.ORACLE: kern.MODE_ORACLE,
}


def pose_of(v: np.ndarray) -> Pose:
    """A Pose of a pose vector [x, y, z, θ] the kernels keep wrapped (no second wrap)."""
    return Pose(v[:3].copy(), float(v[3]))


class TruthPredictor:
    """μ = the true target body velocity at the given pose (mode `oracle`; sim-only reference)."""

    def __init__(self, prm: DuffingParams) -> None:
        self.prm = prm

    def predict_one(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return duffing_body_velocity(Pose.from_vector(x), self.prm), np.full(4, 1e-9)

    def prior_var(self) -> np.ndarray:
        return np.ones(4)
