"""The ground robot's target laws: the paper's square (Sec. 6, eq. scamper_vel) and the same square as a
path a non-holonomic robot can follow.

Which law a robot is given follows its kinematics (`KINEMATICS`, the rig's `robot.kinematics`;
flightstack.config.mission `Mission.target_law`): `SquareLaw` (the paper's, below) commands sideways body
velocity, which only an omnidirectional target follows (the ideal rig's); `UnicycleSquareLaw` commands
forward speed and turn rate only (v_y = 0), for a differential-drive or Ackermann robot.

SquareLaw — reference g_d(t): a point moving at `speed` (m/s) along a square of side `side` (m) centred at the
origin of Σw, counter-clockwise, starting at the square's corner (−side/2, −side/2), with yaw
θ_d(t) = θ_d(0) + 2π t / T_lap (one full rotation per lap, T_lap = 4·side/speed).
v_d is the reference's body velocity, so R(θ_d) v_d is its world velocity.

Robot command (the paper's eq. scamper_vel, with Ad_{−R(θ)} read as Ad_{Rᵀ(θ)}, world → body):
    V_w0 = Ad_{Rᵀ(θ_w0)} ( [R(θ_d) v_d ; ω_d] − k vec(g_w0 g_d⁻¹) ),   k = 0.05 s⁻¹ in the paper.
The robot moves in the plane: the z components are zeroed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightstack.paper.geometry import Pose, compose, inverse, rotate_twist, vec, wrap_angle

KINEMATICS = ("omni", "differential", "ackermann")
"""How a ground robot can move: `omni` follows any planar body velocity [v_x, v_y, ω] (the paper's idealised
target); `differential` (a unicycle: forward speed and turn rate, turns in place; skid steer included)
and `ackermann` (forward speed and turn rate with |v/ω| ≥ its minimum turn radius) never move sideways."""
LAWS = ("paper", "unicycle")
"""The target laws: `paper` = SquareLaw (eq. scamper_vel, holonomic), `unicycle` = UnicycleSquareLaw."""


@dataclass(frozen=True)
class SquareLaw:
    side: float = 1.0  # m
    speed: float = 0.1  # m/s
    gain: float = 0.05  # 1/s, the paper's 0.05
    theta0: float = 0.0  # rad, reference yaw at t = 0

    @property
    def lap_time(self) -> float:
        return 4.0 * self.side / self.speed

    def distance(self, t: float) -> float:
        """Path length (m) of the reference over [0, t] (s): speed · t."""
        return self.speed * t

    def reference(self, t: float) -> tuple[Pose, np.ndarray]:
        """(g_d(t), world velocity [ẋ, ẏ, 0, ω_d]) of the reference at time t (s)."""
        h = self.side / 2.0
        s = (t * self.speed) % (4.0 * self.side)  # arc length along the lap
        leg, r = int(s // self.side), s % self.side
        corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
        dirs = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)]
        (x0, y0), (dx, dy) = corners[leg], dirs[leg]
        omega = 2.0 * math.pi / self.lap_time
        g = Pose.make([x0 + r * dx, y0 + r * dy, 0.0], self.theta0 + omega * t)
        return g, np.array([self.speed * dx, self.speed * dy, 0.0, omega])

    def command(self, t: float, g_w0: Pose) -> np.ndarray:
        """Body-velocity command V_w0 (m/s, rad/s) for the robot at measured pose g_w0."""
        g_d, v_world = self.reference(t)
        err = vec(compose(g_w0, inverse(g_d)))
        V_world = v_world - self.gain * err
        V = rotate_twist(-g_w0.theta, V_world)  # Ad_{Rᵀ(θ_w0)}
        V[2] = 0.0
        return V


@dataclass(frozen=True)
class _Segment:
    """A piece of the reference path: from pose (x0, y0, θ0) at lap time t0 (s), for `duration` s, at
    forward speed v (m/s) and turn rate ω (rad/s), both constant: a straight (ω = 0), a turn in place
    (v = 0) or a circular arc of radius v/ω."""

    t0: float
    duration: float
    x0: float
    y0: float
    th0: float
    v: float
    w: float

    def at(self, tau: float) -> tuple[float, float, float]:
        """(x, y, θ) τ seconds into the segment: the unicycle's closed-form motion at constant v, ω."""
        th = self.th0 + self.w * tau
        if self.w == 0.0:
            return (
                self.x0 + self.v * tau * math.cos(self.th0),
                self.y0 + self.v * tau * math.sin(self.th0),
                th,
            )
        r = self.v / self.w
        return (
            self.x0 + r * (math.sin(th) - math.sin(self.th0)),
            self.y0 - r * (math.cos(th) - math.cos(self.th0)),
            th,
        )


@dataclass(frozen=True)
class UnicycleSquareLaw:
    """The paper's square (side `side` m, mean speed `speed` m/s, centred at the origin of Σw,
    counter-clockwise, one rotation per lap) as a path a non-holonomic robot follows, and a tracking law
    that commands only forward speed and turn rate.

    Reference path, heading along the path (θ_d = direction of travel, so one rotation per lap):
    - `differential` (turn_radius = 0): the four sides from the corner (−side/2, −side/2), driven at
      `speed` (the paper's "moves at 0.1 m/s"), each followed by a turn in place of π/2 at `turn_rate`
      (rad/s). Path length per lap 4·side; lap time 4·side/speed + 2π/turn_rate (52.6 s for the paper's
      square at 0.5 rad/s): the turns add their time, so the mean speed over the time it moves is `speed`
      and over the whole lap 4·side / lap time (0.076 m/s). Keeping the paper's 40 s lap instead would
      drive the sides at 0.146 m/s, half as fast again as the paper's robot.
    - `ackermann` (turn_radius = R > 0): each corner rounded by the quarter circle of radius R tangent to
      both sides, driven at `speed` throughout. Path length per lap 4·side − (8 − 2π)·R, lap time
      length/speed (the mean speed is `speed`); the path passes R(√2 − 1) ≤ R inside each corner. Starts
      at (−side/2 + R, −side/2).

    Tracking law (Kanayama, Kimura, Miyazaki, Noguchi, "A stable tracking control method for an autonomous
    mobile robot", IEEE ICRA 1990, eq. (4)), with the error e = [e_x, e_y, e_θ] of the reference pose
    (x_d, y_d, θ_d) in the robot's body frame:
        e_x = cos θ (x_d − x) + sin θ (y_d − y),   e_y = −sin θ (x_d − x) + cos θ (y_d − y),   e_θ = θ_d − θ
        v = v_d cos e_θ + k_x e_x
        ω = ω_d + k_y v_d e_y + k_θ sin e_θ
    One change from the paper cited: its heading term is v_d k_θ sin e_θ; here k_θ sin e_θ, so that the
    heading is also corrected during a turn in place (v_d = 0). With V = (e_x² + e_y²)/2 + (1 − cos e_θ)/k_y
    (Kanayama's Lyapunov function) dV/dt = −k_x e_x² − (k_θ/k_y) sin² e_θ ≤ 0 for v_d ≥ 0 either way.
    Command: the body velocity [v, 0, 0, ω] (m/s, rad/s): no sideways component."""

    side: float = 1.0  # m
    speed: float = 0.1  # m/s, mean over a lap
    turn_radius: float = 0.0  # m: 0 = corners turned in place (differential), R > 0 = rounded (ackermann)
    turn_rate: float = 0.5  # rad/s of a turn in place (differential only)
    k_x: float = 1.0  # 1/s
    k_y: float = 16.0  # 1/m²
    k_theta: float = 1.5  # 1/s

    def __post_init__(self) -> None:
        if not 0.0 <= self.turn_radius <= self.side / 2.0:
            raise ValueError(
                f"turn radius {self.turn_radius:g} m: must lie in [0, side/2 = {self.side / 2:g}] m"
            )
        if not self.turn_rate > 0.0:
            raise ValueError(f"turn rate {self.turn_rate:g} rad/s: must be > 0")

    @property
    def path_length(self) -> float:
        """Length of one lap of the reference path (m): 4·side − (8 − 2π)·R."""
        return 4.0 * self.side - (8.0 - 2.0 * math.pi) * self.turn_radius

    @property
    def turning_time(self) -> float:
        """Seconds per lap spent turning in place: 2π/turn_rate (differential), 0 (ackermann)."""
        return 2.0 * math.pi / self.turn_rate if self.turn_radius == 0.0 else 0.0

    @property
    def lap_time(self) -> float:
        """Seconds per lap: path_length / speed + turning_time."""
        return self.path_length / self.speed + self.turning_time

    @property
    def segments(self) -> tuple[_Segment, ...]:
        """One lap's segments, lap time 0 at the start (cached per instance)."""
        cached = self.__dict__.get("_segments")
        if cached is None:
            cached = self._build()
            object.__setattr__(self, "_segments", cached)
        return cached

    def _build(self) -> tuple[_Segment, ...]:
        h, R, out = self.side / 2.0, self.turn_radius, []
        t, th = 0.0, 0.0
        x, y = -h + R, -h
        if R == 0.0:
            straight = (self.side / self.speed, self.speed, 0.0)
            corner = ((math.pi / 2.0) / self.turn_rate, 0.0, self.turn_rate)
        else:
            straight = ((self.side - 2.0 * R) / self.speed, self.speed, 0.0)
            corner = ((math.pi / 2.0) * R / self.speed, self.speed, self.speed / R)
        for _ in range(4):
            for duration, v, w in (straight, corner):
                seg = _Segment(t, duration, x, y, th, v, w)
                out.append(seg)
                x, y, th = seg.at(duration)
                t += duration
        return tuple(out)

    def _state(self, t: float) -> tuple[float, float, float, float, float]:
        """(x_d, y_d, θ_d, v_d, ω_d) of the reference at time t (s); θ_d grows by 2π per lap."""
        T = self.lap_time
        laps = math.floor(t / T)
        tl = t - laps * T
        segs = self.segments
        seg = segs[-1]
        for s in segs:
            if tl < s.t0 + s.duration:
                seg = s
                break
        x, y, th = seg.at(min(max(tl - seg.t0, 0.0), seg.duration))
        return x, y, th + 2.0 * math.pi * laps, seg.v, seg.w

    def distance(self, t: float) -> float:
        """Path length (m) of the reference over [0, t] (s), t ≥ 0."""
        laps = math.floor(t / self.lap_time)
        tl = t - laps * self.lap_time
        done = sum(s.v * min(max(tl - s.t0, 0.0), s.duration) for s in self.segments)
        return laps * self.path_length + done

    def reference(self, t: float) -> tuple[Pose, np.ndarray]:
        """(g_d(t), world velocity [ẋ, ẏ, 0, ω_d]) of the reference at time t (s)."""
        x, y, th, v, w = self._state(t)
        return Pose.make([x, y, 0.0], th), np.array([v * math.cos(th), v * math.sin(th), 0.0, w])

    def command(self, t: float, g_w0: Pose) -> np.ndarray:
        """Body-velocity command [v, 0, 0, ω] (m/s, rad/s) for the robot at measured pose g_w0."""
        xd, yd, thd, vd, wd = self._state(t)
        th = g_w0.theta
        dx, dy = xd - float(g_w0.p[0]), yd - float(g_w0.p[1])
        c, s = math.cos(th), math.sin(th)
        ex, ey, eth = c * dx + s * dy, -s * dx + c * dy, wrap_angle(thd - th)
        v = vd * math.cos(eth) + self.k_x * ex
        w = wd + self.k_y * vd * ey + self.k_theta * math.sin(eth)
        return np.array([v, 0.0, 0.0, w])


TargetLaw = SquareLaw | UnicycleSquareLaw

HEADING_WEIGHT_M_PER_RAD = 0.1
"""How much a heading error counts against a position error when `start_phase` looks for the robot on its
path (m per rad): enough to tell the ends of a turn in place apart, small beside a side's length."""


START_PHASE_COARSE = 5
"""`start_phase` searches every START_PHASE_COARSE-th sample first, then the samples around the nearest."""


def start_phase(law: TargetLaw, g_w0: Pose, step_s: float = 0.02) -> tuple[float, float, float]:
    """Where on its lap the robot at g_w0 is: (t0, distance, heading error), t0 ∈ [0, lap_time) (s) the lap
    time whose reference pose g_d(t0) is nearest (|p − p_d|² + (HEADING_WEIGHT_M_PER_RAD · Δθ)², sampled every
    step_s s), the distance |p − p_d| (m, in the plane) and the wrapped heading error θ − θ_d (rad) there.

    A robot that is a device stays where the last mode left it: its next mode's law starts at t0, not at
    the lap's start, so that the reference does not jump away from it (flightstack.runtime.phases).

    It runs on the flight's thread before takeoff, between two of the guardian's heartbeats, so it searches
    every START_PHASE_COARSE-th sample (1 cm and 0.05 rad apart at the paper's 0.1 m/s and 0.5 rad/s), then
    the samples beside the nearest: 535 poses instead of 2 630 for the 52.6 s lap (10 ms instead of 55 ms
    on an idle core of the 2-core CI machine; several times that on a loaded one)."""
    ts = np.arange(0.0, law.lap_time, step_s)

    def nearest(idx: np.ndarray) -> tuple[int, float, float]:
        ref = np.array([law.reference(float(ts[i]))[0].as_vector() for i in idx])  # (n, 4): x, y, z, θ
        d_xy = np.hypot(ref[:, 0] - float(g_w0.p[0]), ref[:, 1] - float(g_w0.p[1]))
        d_th = np.array([wrap_angle(g_w0.theta - th) for th in ref[:, 3]])
        j = int(np.argmin(d_xy**2 + (HEADING_WEIGHT_M_PER_RAD * d_th) ** 2))
        return int(idx[j]), float(d_xy[j]), float(d_th[j])

    k, _, _ = nearest(np.arange(0, ts.size, START_PHASE_COARSE))
    k, dist, dth = nearest(
        np.arange(max(0, k - START_PHASE_COARSE + 1), min(ts.size, k + START_PHASE_COARSE))
    )
    return float(ts[k]), dist, dth


def square_law(
    law: str,
    kinematics: str,
    side: float,
    speed: float,
    gain: float,
    theta0: float,
    turn_radius: float,
) -> TargetLaw:
    """The square law `law` (LAWS) for a robot of `kinematics` (KINEMATICS). `gain` (1/s) and `theta0`
    (rad) are the paper law's; `turn_radius` (m) the Ackermann robot's minimum turn radius. Raises
    ValueError for a law the kinematics cannot follow (the paper's on a non-holonomic robot)."""
    if law == "paper":
        if kinematics != "omni":
            raise ValueError(
                f"the paper's law (eq. scamper_vel) commands sideways body velocity, which a {kinematics} "
                "robot cannot follow: use law 'unicycle'"
            )
        return SquareLaw(side, speed, gain, theta0)
    if law == "unicycle":
        return UnicycleSquareLaw(side, speed, turn_radius if kinematics == "ackermann" else 0.0)
    raise ValueError(f"unknown target law {law!r} (one of {', '.join(LAWS)})")
