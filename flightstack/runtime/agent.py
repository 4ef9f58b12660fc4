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
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from flightstack.comms.bus import PredictionBus
from flightstack.comms.messages import PredictionMessage
from flightstack.config.types import Mode
from flightstack.hal import Camera, Drone, Frame, PoseSource
from flightstack.paper.control import (
    Gains,
    consensus_term,
    control_error,
    drone_velocity_command,
    pursuit_law,
)
from flightstack.paper.fusion import fuse
from flightstack.paper.geometry import Pose, relative
from flightstack.paper.observer import estimation_error, observer_step
from flightstack.paper.projection import CameraModel, TargetNotVisibleError
from flightstack.vision.camera_file import CameraCalibration
from flightstack.vision.markers import extract_markers, features_from_detection

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
    own_pose_fresh: bool = True  # False: motion capture lost the drone; it hovers (V = 0) this tick


class Agent:
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
        self.g_bar_w = g_bar_w0  # ḡ_w,i: the observer state
        self.seq = 0
        self._u_e_prev: np.ndarray | None = None
        self._t_prev: float | None = None
        self._g_wi: Pose | None = None
        self._g_bar_i0 = g_bar_w0
        self.last = TickRecord(g_bar_w0)
        self.hold = False  # set by the safety supervisor: hover instead of pursuing

    def reset_estimate(self, g_bar_w: Pose) -> None:
        """Restart the observer from ḡ_w,i (e.g. at pursuit start on hardware, from the own pose and g_d)."""
        self.g_bar_w = g_bar_w
        self._u_e_prev = None
        self._t_prev = None

    # ---- phase 1 -------------------------------------------------------------------------------
    def sense_and_publish(self, t: float) -> None:
        cfg = self.cfg
        if self._u_e_prev is not None and self._t_prev is not None and t > self._t_prev:
            self.g_bar_w = observer_step(self.g_bar_w, self._u_e_prev, t - self._t_prev)
        own = self.poses.latest(cfg.body_name)
        rec = TickRecord(self.g_bar_w)
        if own is not None:
            self._g_wi = own.pose
        elif self._g_wi is None:
            raise RuntimeError(f"no pose for {cfg.body_name}")
        else:  # a motion-capture dropout: keep the last pose, hover; the safety layer decides beyond that
            rec.own_pose_fresh = False
        g_bar_i0 = relative(self._g_wi, self.g_bar_w)  # ḡ_i0 = g_wi⁻¹ ḡ_w,i
        self._g_bar_i0 = g_bar_i0
        frame = self.camera.latest()
        features = self._features(frame, rec, t)
        if features is not None:
            try:
                xi = estimation_error(features, g_bar_i0, cfg.P0, cfg.camera)  # ≈ [p_e, θ_e]
                rec.e_e_meas = np.array([xi[0], xi[1], xi[2], math.sin(xi[3])])
                rec.visible = True
            except TargetNotVisibleError:
                rec.visible = False
        x = self.g_bar_w.as_vector()
        if self.predictor is not None and cfg.mode != Mode.NONE:
            mu, var = self.predictor.predict_one(x)
            prior = self.predictor.prior_var()
        else:
            mu, var, prior = np.zeros(4), UNINFORMATIVE_VAR, UNINFORMATIVE_VAR
        rec.mu_own, rec.var_own = mu, var
        self.last = rec
        self.seq += 1
        self.bus.publish(
            PredictionMessage(cfg.mission, cfg.drone_id, self.seq, t, rec.visible, x, mu, var, prior)
        )

    def _features(self, frame: Frame | None, rec: TickRecord, t: float) -> np.ndarray | None:
        """f (2m,) from the frame: given directly (ideal camera) or extracted from the image."""
        if frame is None:
            rec.rejection = "no frame"
            return None
        if t - frame.stamp > self.cfg.max_frame_age_s:
            rec.rejection = "stale frame"
            return None
        if frame.features is not None:
            f = np.asarray(frame.features, dtype=float).reshape(-1)
            if f.shape != (2 * len(self.cfg.P0),) or not np.all(np.isfinite(f)):
                rec.rejection = "bad features"  # e.g. a served frame with another marker count (issue 16)
                return None
            return f
        if frame.image is None or self.cfg.calibration is None:
            return None
        det = extract_markers(frame.image, self.cfg.calibration)
        rec.rejection = det.reason
        return features_from_detection(det, self.cfg.camera.focal_length)

    # ---- phase 2 -------------------------------------------------------------------------------
    def fuse_control_act(self, t: float) -> np.ndarray:
        cfg = self.cfg
        rec = self.last
        if self._g_wi is None:
            raise RuntimeError("fuse_control_act before sense_and_publish")
        msgs: list[PredictionMessage] = []
        for j in cfg.neighbour_ids:
            m = self.bus.latest(j, t, cfg.stale_after)
            if m is not None:
                msgs.append(m)
        rec.neighbours_used = tuple(m.sender for m in msgs)
        c_i = consensus_term(self.g_bar_w, [Pose.from_vector(m.g_bar_w) for m in msgs])
        if cfg.mode == Mode.DGP:
            mus = np.vstack([rec.mu_own, *[m.mu for m in msgs]])
            vars_ = np.vstack([rec.var_own, *[m.var for m in msgs]])
            priors = np.vstack([self.predictor.prior_var(), *[m.prior_var for m in msgs]])  # type: ignore[union-attr]
            mu, _ = fuse(mus, vars_, cfg.fusion_rule, priors)
            rec.n_fused = len(msgs) + 1
        elif cfg.mode in (Mode.LOCAL, Mode.ORACLE):
            mu = rec.mu_own
            rec.n_fused = 1
        else:
            mu = np.zeros(4)
        e_c, th_c = control_error(cfg.g_d, self._g_bar_i0)
        th_e = math.asin(max(-1.0, min(1.0, rec.e_e_meas[3])))
        u_c, u_e = pursuit_law(e_c, th_c, rec.e_e_meas, th_e, c_i, mu, cfg.gains, rec.visible)
        hover = self.hold or not rec.own_pose_fresh
        V = drone_velocity_command(u_c, cfg.g_d) if not hover else np.zeros(4)
        self.drone.send_body_velocity(V)
        rec.mu_used, rec.u_c, rec.u_e, rec.V_cmd = mu, u_c, u_e, V
        self._u_e_prev, self._t_prev = u_e, t
        return V
