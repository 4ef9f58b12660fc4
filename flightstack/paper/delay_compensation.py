"""Delay-aware observer and command: beyond the paper (docs/equations.md §11).

The paper's observer compares the image with the estimate as if both were of the same instant, and its
law commands the drone as if the command acted at once. On a Tello the image is 0.3–0.4 s old when it is
used and a command acts ~0.05 s after it is sent, through a ~0.25 s velocity response. This module holds
the pieces that put each at its own time (poses as vectors [x, y, z, θ] in Σw, times in s on the
mission clock, twists [v_x, v_y, v_z, ω] in the body frame):

- `PoseHistory`: the own pose g_wi as motion capture measured it, at any recent time (interpolated);
- `EstimateHistory`: the observer's ḡ_w,i at any recent time (each tick's ḡ_w,i with the u_e held after
  it: exact, the observer is integrated that way);
- `carry_error`: an estimation error measured at capture time t_c, carried forward to now;
- `CommandModel`: the drone's response to the commands already sent (delay, then first order), which
  predicts the own pose at the time a command takes effect;
- `stamp_refusal`: whether a time that enters them (a frame's or a pose's stamp) may, against the tick's
  own clock.

Every time stored is finite: a time that is not, or a stamp more than AHEAD_TOLERANCE_S after the tick,
is refused before it is stored (one sample stamped far ahead would otherwise become the newest and hold
every later one back as "older"). The delays and so the prediction horizon are bounded by MAX_DELAY_S,
and a prediction costs O(commands kept) whatever its horizon (MAX_STEPS_PER_SEGMENT).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from flightstack.paper import kernels as kern

CURRENT_S = 1e-6
"""A frame captured within this (s) of the tick is current: the paper's observer uses it as it is."""

SUBSTEP_S = 0.01
"""The command model integrates the own pose in steps of at most this (s)."""

MAX_STEPS_PER_SEGMENT = 200
"""Steps of SUBSTEP_S per span of one acting command (2 s: twenty time constants of the simulated and
emulated Tellos' 0.1 s response); what a longer span has beyond them is one step at the exact mean
velocity of the response (the velocity has settled on the command by then, so that step is the constant
twist's exact motion). A prediction then costs O(commands kept), not O(how far ahead it looks). Spans
up to 2 s, every one of a horizon below 2 s, are stepped exactly as without the bound."""

MAX_DELAY_S = 10.0
"""Largest command delay and response time constant (s) the compensator is told, and largest history_s:
the prediction horizon is at most 2 × this. Ten seconds is orders of magnitude beyond a drone's (a
Tello's rc acts after ~0.05 s through a ~0.1–0.3 s response); a longer one is a wrong setting (the rc
link's latency standing in for the command delay is held to it at validation, config/mission.py)."""

AHEAD_TOLERANCE_S = 0.1
"""How far after the tick's time t (s) a sample's stamp may be. Simulated sources stamp at most t; on
hardware a sample stamped with its receive time (motion capture) or decode time (video) can arrive
after the tick started and before the tick reads it: by the tick's own run time up to the read,
milliseconds on the lab's 20 Hz loop, and at most a period or two when the loop overruns. Further
ahead it is on another clock or forged; one within the tolerance holds the histories back by at most
this (a sample stamped before it is then "older")."""

FRAME_NOT_FINITE = "frame stamp not finite"
FRAME_AHEAD = "frame stamp ahead of the tick"
POSE_NOT_FINITE = "pose stamp not finite"
POSE_AHEAD = "pose stamp ahead of the tick"
TIME_NOT_FINITE = "compensation time not finite"
"""Reasons a time is refused, counted with the recording's rejections (frame, own pose; an estimate's
or a command's time is the tick's own: only a non-finite one is refused)."""


def stamp_refusal(stamp: float, t: float, what: str) -> str | None:
    """Why a sample of `what` ('frame' or 'pose') stamped `stamp` (s) may not enter at the tick of time t
    (s, the tick's own clock), or None: not finite, or more than AHEAD_TOLERANCE_S after t."""
    if not math.isfinite(stamp):
        return FRAME_NOT_FINITE if what == "frame" else POSE_NOT_FINITE
    if not stamp <= t + AHEAD_TOLERANCE_S:  # also refuses any stamp against a non-finite t
        return FRAME_AHEAD if what == "frame" else POSE_AHEAD
    return None


@dataclass(frozen=True)
class Compensation:
    """What the compensator is told: command_delay_s, from sending a command to the start of the
    response (s); response_s, the time constant of the first-order velocity response (s); history_s, how
    far back poses and estimates are kept (s)."""

    command_delay_s: float
    response_s: float
    history_s: float = 1.0

    def __post_init__(self) -> None:
        for name, lo_open in (("command_delay_s", False), ("response_s", False), ("history_s", True)):
            v = getattr(self, name)
            if not (math.isfinite(v) and (v > 0 if lo_open else v >= 0) and v <= MAX_DELAY_S):
                raise ValueError(
                    f"{name}: {v!r} s; must be finite, {'>' if lo_open else '>='} 0 and <= {MAX_DELAY_S:g} s"
                )

    @property
    def horizon_s(self) -> float:
        """How far ahead a command is computed for (s): it acts after command_delay_s and has mostly
        taken effect one time constant later."""
        return self.command_delay_s + self.response_s


class PoseHistory:
    """Poses measured at increasing times, kept for `keep_s` seconds behind the newest."""

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s
        self._t: list[float] = []
        self._g: list[np.ndarray] = []

    def clear(self) -> None:
        self._t.clear()
        self._g.clear()

    def add(self, t: float, g: np.ndarray) -> bool:
        """Keep the pose g measured at t (s); a sample not newer than the newest is ignored (the same
        motion-capture frame read again, or one out of order), and so is one at a time not finite.
        Returns whether it was kept. Whether t is ahead of the tick is the caller's (`stamp_refusal`)."""
        if not math.isfinite(t) or (self._t and t <= self._t[-1]):
            return False
        self._t.append(t)
        self._g.append(np.array(g, dtype=float))
        cut = bisect.bisect_left(self._t, t - self.keep_s) - 1  # keep one older than the window
        if cut > 0:
            del self._t[:cut], self._g[:cut]
        return True

    def at(self, t: float) -> np.ndarray | None:
        """The pose at t (s): interpolated between the two samples around it (p linearly, θ along the
        shorter arc), the newest for t after it; None before the oldest (or with none, or t not finite)."""
        if not self._t or not math.isfinite(t) or t < self._t[0]:
            return None
        if t >= self._t[-1]:
            return self._g[-1].copy()
        i = bisect.bisect_right(self._t, t) - 1
        t0, t1 = self._t[i], self._t[i + 1]
        a, b = self._g[i], self._g[i + 1]
        s = (t - t0) / (t1 - t0)
        out = a + s * (b - a)
        out[3] = kern.wrap_angle(a[3] + s * kern.wrap_angle(b[3] - a[3]))
        return out


class EstimateHistory:
    """The observer's ḡ_w,i: at each tick t_k the estimate and the u_e held after it, so that
    ḡ_w,i(τ) = ḡ_w,i(t_k) exp(−û_e,k (τ − t_k)) for t_k ≤ τ < t_{k+1}."""

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s
        self._t: deque[float] = deque()
        self._g: deque[np.ndarray] = deque()
        self._u: deque[np.ndarray] = deque()

    def clear(self) -> None:
        self._t.clear()
        self._g.clear()
        self._u.clear()

    def add(self, t: float, g_bar_w: np.ndarray, u_e: np.ndarray) -> bool:
        """The estimate at tick t (s) and the observer input u_e held from t on; it replaces those kept
        at or after t. A time not finite is not kept (returns False)."""
        if not math.isfinite(t):
            return False
        while self._t and t <= self._t[-1]:
            self._t.pop()
            self._g.pop()
            self._u.pop()
        self._t.append(t)
        self._g.append(np.array(g_bar_w, dtype=float))
        self._u.append(np.array(u_e, dtype=float))
        while len(self._t) > 1 and self._t[1] <= t - self.keep_s:
            self._t.popleft()
            self._g.popleft()
            self._u.popleft()
        return True

    def mean_velocity(self, t: float, window_s: float) -> np.ndarray:
        """The estimate's mean body velocity over [t − window_s, t] (the window shortened to what is
        kept; zeros with less than one tick): V̄ with ḡ_w,i(t) = ḡ_w,i(t − w) exp(V̄ w). A velocity of the
        target the observer has already followed, without the corrections of the last instants."""
        if not self._t:
            return np.zeros(4)
        a = max(t - window_s, self._t[0])
        w = t - a
        g_a, g_t = self.at(a), self.at(t)
        if w <= 0.0 or g_a is None or g_t is None:
            return np.zeros(4)
        return log_twist(rel4(g_a, g_t)) / w

    def at(self, t: float) -> np.ndarray | None:
        """ḡ_w,i at t (s), None before the oldest tick kept (or t not finite)."""
        if not self._t or not math.isfinite(t) or t < self._t[0]:
            return None
        i = bisect.bisect_right(self._t, t) - 1
        out = np.empty(4)
        kern.integrate4(self._g[i], -self._u[i], t - self._t[i], out)
        return out


def rel4(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a⁻¹ b of pose vectors."""
    out = np.empty(4)
    kern.relative4(a, b, out)
    return out


def log_twist(g: np.ndarray) -> np.ndarray:
    """V̂ with exp(V̂) = g (the inverse of kernels.exp_twist4 over a unit time; |θ| < π)."""
    th = float(g[3])
    if abs(th) < 1e-6:
        a, b = 1.0 - th * th / 6.0, th / 2.0
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th
    det = a * a + b * b
    vx = (a * g[0] + b * g[1]) / det
    vy = (-b * g[0] + a * g[1]) / det
    return np.array([vx, vy, g[2], th])


def carry_error(
    xi_c: np.ndarray, g_bar_c: np.ndarray, g_bar_now: np.ndarray, V0: np.ndarray, tau: float
) -> np.ndarray:
    """The estimation error now from the one measured at capture time: with g_e = ḡ_w,i⁻¹ g_w0,

        g_e(t) = (ḡ_w,i(t)⁻¹ ḡ_w,i(t_c)) · g_e(t_c) · exp(V̂_0 τ),   τ = t − t_c,

    where g_e(t_c) is the pose (ξ_p, ξ_θ) of ξ = J⁺(f − f̄) measured against ḡ_w,i(t_c) (`g_bar_c`), and
    V_0 the target's body velocity predicted over τ (Σ0, m/s and rad/s). Returns ξ(t) = [p_e, θ_e]."""
    moved = np.empty(4)
    kern.relative4(g_bar_now, g_bar_c, moved)
    g_e = np.empty(4)
    kern.compose4(moved, np.array([xi_c[0], xi_c[1], xi_c[2], xi_c[3]]), g_e)
    if tau > 0.0:
        out = np.empty(4)
        kern.integrate4(g_e, V0, tau, out)
        return out
    return g_e


class CommandModel:
    """The drone's response to the body velocities it was sent (Σ_i): a command acts `delay_s` after it
    was sent, and the velocity follows the acting command with time constant `tau_s` (0: at once)."""

    def __init__(self, delay_s: float, tau_s: float, keep_s: float) -> None:
        self.delay_s, self.tau_s, self.keep_s = delay_s, tau_s, keep_s
        self._sent: deque[tuple[float, np.ndarray]] = deque()  # (acts at, V)
        self._t = -math.inf  # the model's velocity _v is the one at _t
        self._v = np.zeros(4)

    def clear(self) -> None:
        self._sent.clear()
        self._t, self._v = -math.inf, np.zeros(4)

    def sent(self, t: float, V: np.ndarray) -> bool:
        """The body velocity V (m/s, rad/s) was sent at t (s). The model folds in what acted more than
        keep_s ago, so that what it keeps stays bounded however long nothing is predicted (a hover).
        A time not finite is not kept (returns False)."""
        if not math.isfinite(t):
            return False
        if self._t == -math.inf:
            self._t = t
        self._sent.append((t + self.delay_s, np.array(V, dtype=float)))
        self._advance(t - self.keep_s)
        return True

    def __len__(self) -> int:
        """How many commands the model keeps (the one acting at its time and those after it)."""
        return len(self._sent)

    def predict(self, g: np.ndarray, t_g: float, t_end: float) -> np.ndarray:
        """The own pose at t_end (s) from g measured at t_g (s), moved with the model's velocity. Costs
        O(commands kept) however far ahead t_end is (MAX_STEPS_PER_SEGMENT); ValueError for a time that
        is not finite."""
        if not (math.isfinite(t_g) and math.isfinite(t_end)):
            raise ValueError(f"CommandModel.predict: times must be finite (t_g {t_g!r}, t_end {t_end!r})")
        self._advance(t_g)
        t, v = max(t_g, self._t), self._v.copy()
        pose = np.array(g, dtype=float)
        if t > t_g:  # the model is already past the measurement: that gap at its present velocity
            nxt = np.empty(4)
            kern.integrate4(pose, v, t - t_g, nxt)
            pose = nxt
        for a, b, V in self._segments(t, t_end):
            pose, v = self._fly(pose, v, V, a, b)
        return pose

    def _fly(
        self, pose: np.ndarray, v: np.ndarray, V: np.ndarray, a: float, b: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(pose, velocity) at b from those at a under the command V acting over [a, b): steps of
        SUBSTEP_S, at most MAX_STEPS_PER_SEGMENT of them, then the rest in one step."""
        end = min(b, a + MAX_STEPS_PER_SEGMENT * SUBSTEP_S)
        while a < end - 1e-12:
            h = min(SUBSTEP_S, end - a)
            v, mean = self._respond(v, V, h)
            nxt = np.empty(4)
            kern.integrate4(pose, mean, h, nxt)
            pose, a = nxt, a + h
        if a < b - 1e-12:  # a span longer than the steps: its rest at its exact mean velocity
            v, mean = self._respond(v, V, b - a)
            nxt = np.empty(4)
            kern.integrate4(pose, mean, b - a, nxt)
            pose = nxt
        return pose, v

    def _advance(self, t: float) -> None:
        """The model's velocity brought forward to t; commands acting before it are folded in."""
        if self._t == -math.inf:  # nothing sent yet: at rest
            self._t = t
            return
        if t <= self._t:
            return
        for a, b, V in self._segments(self._t, t):
            self._v = self._respond(self._v, V, b - a)[0]
        self._t = t
        while len(self._sent) > 1 and self._sent[1][0] <= t:  # the first is superseded by time t
            self._sent.popleft()

    def _segments(self, t0: float, t1: float) -> list[tuple[float, float, np.ndarray]]:
        """[t0, t1) split where a command starts acting: (start, end, the command acting)."""
        acting = np.zeros(4)
        cuts: list[tuple[float, np.ndarray]] = []
        for at, V in self._sent:
            if at <= t0:
                acting = V
            elif at < t1:
                cuts.append((at, V))
        out, a = [], t0
        for at, V in cuts:
            out.append((a, at, acting))
            a, acting = at, V
        out.append((a, t1, acting))
        return out

    def _respond(self, v: np.ndarray, V: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """(velocity after h seconds, mean velocity over them) following V from v, first order."""
        if self.tau_s <= 0.0 or h <= 0.0:
            return V.copy(), V.copy()
        decay = math.exp(-h / self.tau_s)
        return V + (v - V) * decay, V + (v - V) * (self.tau_s / h) * (1.0 - decay)
