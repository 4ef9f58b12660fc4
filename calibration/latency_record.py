"""Recording a latency calibration on a flying drone (what `calibrate latency --session` reads): the
drone, already hovering over the still target, yaws one way at a varying rate while the decoded frames'
markers and the motion-capture poses are kept (`record_video`), then flies yaw-rate steps while its yaw
is kept (`record_rc`). Over the hal interfaces, so one recorder serves the real lab and the emulated one.

Clock: the camera's stamps, the poses' stamps and `clock` must be one clock (time.monotonic() on the
hardware backend). A frame is timed when it became available: by default its stamp, so the camera must
stamp its plain decode time (TelloCamera(latency_s=0)); a camera that stamps capture times (the simulated
lab) is timed when it is first seen instead (`frame_time=first_seen`).
Commands: hal body velocities [v_x, v_y, v_z, ω_z] (m/s, rad/s, FLU: ω_z > 0 turns left); a `Station`
adds the velocity that keeps the drone over the target (motion capture) to every command.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flightstack.calibration.latency_session import RcRecord, VideoRecord
from flightstack.hal import Camera, Drone, Frame, PoseSource
from flightstack.paper.geometry import Pose, compose, inverse, rot_z

FREQS_HZ = (0.37, 0.83, 1.31)
"""The yaw pattern's wobble: incommensurate frequencies (no common period under 10 s)."""


@dataclass(frozen=True)
class Geometry:
    """What predicts the markers' pixels: the camera's calibration file, its mount (R_ic (3, 3), t_ic (3,)
    in the body frame), the markers P0 (m, 3) in the target's frame, and the motion capture's bodies."""

    calibration: str
    R_ic: np.ndarray
    t_ic: np.ndarray
    P0: np.ndarray
    drone_body: str
    target_body: str


def decode_stamp(frame: Frame, now: float) -> float:
    """A frame's availability time: its stamp (a camera that stamps its decode time)."""
    return frame.stamp


def first_seen(frame: Frame, now: float) -> float:
    """A frame's availability time: when the recorder first saw it (a camera that stamps capture times)."""
    return now


class Station:
    """Keeps a drone at `g_d` from the still target (g_wi = g_w0 g_d⁻¹, position only; yaw free) from the
    motion-capture poses: `velocity(now)` is the body-frame [v_x, v_y, v_z] (m/s) toward it, gain × the
    position error (1/s) capped at max_speed (m/s); zeros without fresh poses of both bodies."""

    def __init__(
        self,
        poses: PoseSource,
        geometry: Geometry,
        g_d: Pose,
        gain: float = 1.0,
        max_speed: float = 0.2,
    ) -> None:
        self.poses, self.geometry, self.g_d = poses, geometry, g_d
        self.gain, self.max_speed = gain, max_speed

    def error(self) -> np.ndarray | None:
        """The station's position minus the drone's (m, Σw), or None without both poses."""
        d, g = self.poses.latest(self.geometry.drone_body), self.poses.latest(self.geometry.target_body)
        if d is None or g is None:
            return None
        goal = compose(g.pose, inverse(self.g_d))
        return np.asarray(goal.p, float) - np.asarray(d.pose.p, float)

    def velocity(self) -> np.ndarray:
        e = self.error()
        d = self.poses.latest(self.geometry.drone_body)
        if e is None or d is None:
            return np.zeros(3)
        v = self.gain * e
        speed = float(np.linalg.norm(v))
        if speed > self.max_speed:
            v *= self.max_speed / speed
        return rot_z(float(d.pose.theta)).T @ v  # world → body (yaw only)


def settle(
    drone: Drone,
    station: Station,
    now: Callable[[], float],
    sleep: Callable[[float], None],
    tolerance_m: float = 0.05,
    timeout_s: float = 15.0,
    command_period_s: float = 0.05,
) -> float:
    """Fly to the station until within tolerance_m (m) for 1 s, or timeout_s (s); returns the distance
    (m) left (inf without poses). Hovers (zero velocity) at the end."""
    t0, inside_since, dist = now(), None, math.inf
    try:
        while (t := now()) < t0 + timeout_s:
            e = station.error()
            dist = math.inf if e is None else float(np.linalg.norm(e))
            if dist > tolerance_m:
                inside_since = None
            elif inside_since is None:
                inside_since = t
            if inside_since is not None and t - inside_since >= 1.0:
                break
            drone.send_body_velocity(np.array([*station.velocity(), 0.0]))
            sleep(command_period_s)
    finally:
        drone.send_body_velocity(np.zeros(4))
    return dist


def yaw_rate(t: float, mean_rad_s: float = 1.0, wobble: float = 0.3) -> float:
    """The video pattern's yaw rate (rad/s) at t (s): one way, mean ± about 0.9 × mean, never back."""
    return mean_rad_s * (
        1.0 + wobble * sum(math.cos(2 * math.pi * f * t + k) for k, f in enumerate(FREQS_HZ))
    )


def _pose_row(p: object) -> list[float]:
    pose = p.pose  # type: ignore[attr-defined]
    return [*np.asarray(pose.p, dtype=float).tolist(), float(pose.theta)]


def record_video(
    drone: Drone,
    camera: Camera,
    poses: PoseSource,
    geometry: Geometry,
    find: Callable[[Frame], np.ndarray | None],
    now: Callable[[], float],
    sleep: Callable[[float], None],
    duration_s: float = 10.0,
    command_period_s: float = 0.05,
    poll_s: float = 0.003,
    mean_rad_s: float = 1.0,
    frame_time: Callable[[Frame, float], float] = decode_stamp,
    station: Station | None = None,
) -> VideoRecord:
    """Yaw in the pattern (yaw_rate, mean mean_rad_s) for duration_s (a command every
    command_period_s, plus the station's velocity), polling the camera and the poses every poll_s; find:
    a frame's markers' pixels (m, 2) or None; frame_time: when a new frame became available (its stamp,
    or when first seen). Stops the yaw at the end."""
    t_pose: list[float] = []
    g_wi: list[list[float]] = []
    g_w0: list[list[float]] = []
    t_frames: list[float] = []
    pixels: list[np.ndarray] = []
    m = len(geometry.P0)
    t0 = now()
    next_cmd, last_pose, last_frame = t0, -math.inf, -math.inf
    try:
        while (t := now()) < t0 + duration_s:
            if t >= next_cmd:
                v = np.zeros(3) if station is None else station.velocity()
                drone.send_body_velocity(np.array([*v, yaw_rate(t - t0, mean_rad_s)]))
                next_cmd += command_period_s
            d, g = poses.latest(geometry.drone_body), poses.latest(geometry.target_body)
            if d is not None and g is not None and d.stamp > last_pose:
                last_pose = d.stamp
                t_pose.append(d.stamp)
                g_wi.append(_pose_row(d))
                g_w0.append(_pose_row(g))
            frame = camera.latest()
            # a frame concealed after a stream loss is left out: parts of it may be an older frame's
            if frame is not None and frame.stamp > last_frame and not frame.damaged:
                last_frame = frame.stamp
                px = find(frame)
                t_frames.append(frame_time(frame, t))
                pixels.append(np.full((m, 2), np.nan) if px is None else np.asarray(px, float).reshape(m, 2))
            sleep(poll_s)
    finally:
        drone.send_body_velocity(np.zeros(4))
    return VideoRecord(
        t_pose=np.array(t_pose),
        g_wi=np.array(g_wi).reshape(-1, 4),
        g_w0=np.array(g_w0).reshape(-1, 4),
        t_frames=np.array(t_frames),
        pixels=np.array(pixels).reshape(-1, m, 2),
        calibration=geometry.calibration,
        R_ic=np.asarray(geometry.R_ic, float),
        t_ic=np.asarray(geometry.t_ic, float),
        P0=np.asarray(geometry.P0, float),
    )


def rc_levels(n: int, amplitude_rad_s: float = 0.6, seed: int = 0) -> list[float]:
    """n yaw-rate levels (rad/s) from {−1, −½, 0, ½, 1} × amplitude, never the same twice in a row."""
    rng = np.random.default_rng(seed)
    out = [0.0]
    for _ in range(n):
        out.append(
            float(rng.choice([v for v in (-1.0, -0.5, 0.0, 0.5, 1.0) if v != out[-1] / amplitude_rad_s]))
        )
        out[-1] *= amplitude_rad_s
    return out[1:]


def record_rc(
    drone: Drone,
    poses: PoseSource,
    body: str,
    now: Callable[[], float],
    sleep: Callable[[float], None],
    levels: list[float],
    step_s: float = 0.6,
    command_period_s: float = 0.05,
    poll_s: float = 0.003,
    station: Station | None = None,
) -> RcRecord:
    """Fly the yaw-rate levels (rad/s, step_s each, a command every command_period_s, plus the station's
    velocity) while keeping the body's yaw (unwrapped, rad) from the poses; stops the yaw at the end."""
    t_cmd: list[float] = []
    cmd: list[float] = []
    t_yaw: list[float] = []
    yaw: list[float] = []
    t0 = now()
    next_cmd, last = t0, -math.inf
    try:
        while (t := now()) < t0 + step_s * len(levels) + 0.3:
            k = int((t - t0) / step_s)
            if t >= next_cmd and k < len(levels):
                t_cmd.append(now())
                cmd.append(levels[k])
                v = np.zeros(3) if station is None else station.velocity()
                drone.send_body_velocity(np.array([*v, levels[k]]))
                next_cmd += command_period_s
            p = poses.latest(body)
            if p is not None and p.stamp > last:
                last = p.stamp
                t_yaw.append(p.stamp)
                yaw.append(float(p.pose.theta))
            sleep(poll_s)
    finally:
        drone.send_body_velocity(np.zeros(4))
    return RcRecord(np.array(t_cmd), np.array(cmd), np.array(t_yaw), np.unwrap(np.array(yaw)))


__all__ = [
    "FREQS_HZ",
    "Geometry",
    "Station",
    "decode_stamp",
    "first_seen",
    "rc_levels",
    "record_rc",
    "record_video",
    "settle",
    "yaw_rate",
]
