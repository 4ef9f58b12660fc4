"""Velocity step identification of a Tello: per-axis rc gain, time constant and dead time.

For each axis the drone flies an rc step (`measure_step`), the measured velocity is fitted with a
first-order step response with dead time (`fit_first_order_step`)

    v(t) = gain · u · (1 − exp(−(t − t_step − delay) / τ))   for t > t_step + delay,   0 before,

and `identify` repeats this forward and back on every axis and averages the two fits. `fits_to_rc_gains`
turns the result into the `RcGains` of flightstack.drivers.tello.rc and `save_identification` writes it as
YAML.

Axes and signs (body FLU frame, as in flightstack.drivers.tello.rc): "x" forward (rc b), "y" left (−rc a),
"z" up (rc c), "yaw" counter-clockwise seen from above (−rc d); the identified gains are positive, m/s
(x, y, z) or rad/s (yaw) per rc unit. Time: monotonic seconds (time.monotonic).

Velocity: position differencing, not the vg* fields. The default source differences the state's x/y/z (cm)
and unwrapped yaw (deg) between consecutive packets, stamped at the middle of their arrival times. The vg*
fields are integers in dm/s, so a speed that is not a multiple of 10 cm/s is biased for the whole step
(35 cm/s reads 3 dm/s) and the transient often hides τ; there is no yaw-rate field at all. Differenced
integer positions are coarse per sample (±10 cm/s at 10 Hz) but unbiased (the rounding errors telescope),
so `identify` fits them with `differenced=True` (residuals weighted through their running sum). The
measurements behind this: docs/lab_notes.md ("drivers/tello/identify.py");
`state_velocity_source(driver, axis, field="vg")` gives the vg* alternative for comparison.

Frames of the state stream: vgx/vgy in the horizontal frame of yaw 0 (x along yaw 0, y to its right), vgz
positive **down**, yaw clockwise in degrees, as a recorded real flight shows them
(sim_backend/emulators/tello/recorded.py: vgz −8 dm/s during the climb; at yaw −26° `forward 50` read
vgx +3, vgy −1); the horizontal velocity is rotated into the body frame with the reported yaw. x/y/z
(the position source) follow the emulator's convention: x, y as vgx, vgy, z up. On a real Tello x/y/z
are mission-pad coordinates, so hardware identification needs an external `velocity_source` (e.g.
motion capture).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from scipy.optimize import least_squares

from flightstack.drivers.tello.rc import RC_LIMIT, RcGains

AXES: tuple[str, ...] = ("x", "y", "z", "yaw")
"""The identifiable axes: x forward, y left, z up (m/s), yaw counter-clockwise (rad/s); body FLU frame."""

# axis → (slot in rc a b c d, sign): rc[slot] = sign · u for a command u along the axis
_RC_SLOT: dict[str, tuple[int, int]] = {"x": (1, 1), "y": (0, -1), "z": (2, 1), "yaw": (3, -1)}

TAU_BOUNDS_S = (0.01, 5.0)
DELAY_BOUNDS_S = (0.0, 1.0)
MIN_SAMPLES_AFTER_STEP = 5

VelocitySource = Callable[[], tuple[float, float]]
"""`() -> (stamp, value)`: the latest velocity sample along one axis, stamp in monotonic seconds, value in
m/s (x, y, z) or rad/s (yaw) along the axis's positive direction. Returns the same stamp until a new sample
exists; (nan, nan) before the first one."""


@dataclass(frozen=True)
class StepFit:
    """First-order-with-dead-time fit of one axis's velocity step response.

    axis: "x" (forward, rc b), "y" (left, −rc a), "z" (up, rc c), "yaw" (counter-clockwise, −rc d).
    gain: steady-state velocity per rc unit, m/s (x, y, z) or rad/s (yaw).
    tau_s: first-order time constant, s.
    delay_s: dead time between the rc step and the start of the response, s.
    rms_residual: RMS of the fit residual, m/s (rad/s).
    samples: number of velocity samples in the fit (before and after the step).
    """

    axis: str
    gain: float
    tau_s: float
    delay_s: float
    rms_residual: float
    samples: int


def _check_axis(axis: str) -> None:
    if axis not in _RC_SLOT:
        raise ValueError(f"unknown axis {axis!r}: expected one of {AXES}")


def first_order_step(
    t: np.ndarray, t_step: float, u: float, gain: float, tau_s: float, delay_s: float
) -> np.ndarray:
    """Closed-form response gain·u·(1 − exp(−(t − t_step − delay_s)/tau_s)), 0 before t_step + delay_s.

    t and t_step in seconds (same clock); u in rc units along the axis; returns m/s (rad/s).
    """
    s = np.maximum(np.asarray(t, dtype=float) - t_step - delay_s, 0.0)
    return gain * u * -np.expm1(-s / tau_s)


def fit_first_order_step(
    t: np.ndarray,
    v: np.ndarray,
    t_step: float,
    u: float,
    axis: str,
    *,
    min_response: float = 0.01,
    differenced: bool = False,
) -> StepFit:
    """Least-squares fit of `first_order_step` to velocity samples of one rc step.

    Args:
        t: sample times, s (monotonic clock, same as t_step); samples before the step are used as the
            zero baseline.
        v: velocity along `axis` at t, m/s (x, y, z) or rad/s (yaw), body FLU frame.
        t_step: time the rc step was sent, s.
        u: the step in rc units along the axis (u > 0 = forward/left/up/counter-clockwise).
        axis: "x", "y", "z" or "yaw" (only recorded in the result).
        min_response: smallest steady-state |gain·u| (m/s or rad/s) accepted as a response.
        differenced: True when v are differences of consecutive rounded positions (the default state
            source). Their noise is then negatively correlated between neighbours (each rounding error
            enters two differences with opposite signs), and the residuals are weighted through their
            running sum — a fit in the position domain, the generalised least squares for that noise.
            False (white noise, e.g. motion-capture velocities): plain least squares on v.

    τ is bounded to TAU_BOUNDS_S and the delay to DELAY_BOUNDS_S (scipy.optimize.least_squares, a few
    starting points, the lowest cost wins). Non-finite samples are dropped.

    Raises:
        ValueError: u = 0, mismatched arrays, fewer than MIN_SAMPLES_AFTER_STEP samples after the step,
            or an axis that does not respond (|gain·u| < min_response).
    """
    t = np.asarray(t, dtype=float).ravel()
    v = np.asarray(v, dtype=float).ravel()
    if t.shape != v.shape:
        raise ValueError(f"{axis}: t and v differ in length ({t.size} vs {v.size})")
    if u == 0 or not math.isfinite(u):
        raise ValueError(f"{axis}: the step u must be a non-zero rc value, got {u}")
    ok = np.isfinite(t) & np.isfinite(v)
    order = np.argsort(t[ok], kind="stable")
    t, v = t[ok][order], v[ok][order]
    after = t > t_step
    n_after = int(after.sum())
    if n_after < MIN_SAMPLES_AFTER_STEP:
        raise ValueError(
            f"{axis}: only {n_after} velocity samples after the step at t = {t_step:.3f} s; the fit needs "
            f"at least {MIN_SAMPLES_AFTER_STEP} (longer step or faster velocity source?)"
        )
    # steady-state level from the later half of the response
    tail = v[after][n_after // 2 :]
    level = float(np.mean(tail))
    if abs(level) < min_response:
        raise ValueError(
            f"{axis}: no response to the rc step u = {u:g}: steady-state |v| = {abs(level):.4f} "
            f"< {min_response:g} (drone not flying, axis blocked, or wrong velocity source?)"
        )

    dt = float(np.median(np.diff(t)))  # scales the running sum to metres (rad); weighting only

    def residual(p: np.ndarray) -> np.ndarray:
        r = first_order_step(t, t_step, u, p[0], p[1], p[2]) - v
        return np.cumsum(r) * dt if differenced else r

    g0 = level / u
    lower = [-np.inf, TAU_BOUNDS_S[0], DELAY_BOUNDS_S[0]]
    upper = [np.inf, TAU_BOUNDS_S[1], DELAY_BOUNDS_S[1]]
    best = None
    for tau0 in (0.1, 0.5):
        for delay0 in (0.0, 0.15):
            res = least_squares(
                residual,
                x0=[g0, tau0, delay0],
                bounds=(lower, upper),
                x_scale=[abs(g0), 0.1, 0.1],
                method="trf",
            )
            if best is None or res.cost < best.cost:
                best = res
    assert best is not None
    gain, tau_s, delay_s = (float(x) for x in best.x)
    if abs(gain * u) < min_response:
        raise ValueError(
            f"{axis}: no response to the rc step u = {u:g}: fitted |gain·u| = {abs(gain * u):.4f} "
            f"< {min_response:g}"
        )
    rms = float(np.sqrt(np.mean((first_order_step(t, t_step, u, gain, tau_s, delay_s) - v) ** 2)))
    return StepFit(axis, gain, tau_s, delay_s, rms, int(t.size))


# ------------------------------------------------------------------------------------ velocity sources
class _StateVelocity:
    """VelocitySource over the Tello state stream (see state_velocity_source)."""

    def __init__(self, driver: Any, axis: str, field: str) -> None:
        self.driver = driver
        self.axis = axis
        self.field = field
        self._last_obj: object = None
        self._prev: tuple[float, float, float, float, float, float] | None = None  # t, x, y, z, yaw raw/unw
        self._sample: tuple[float, float] = (math.nan, math.nan)

    def __call__(self) -> tuple[float, float]:
        st = self.driver.current_state()
        if st is self._last_obj or not st:  # the driver stores a new dict per state packet
            return self._sample
        now = time.monotonic()
        self._last_obj = st
        try:
            yaw_raw = float(st["yaw"])
            if self.field == "vg":
                self._sample = (now, self._from_vg(st, yaw_raw))
            else:
                self._from_position(st, now, yaw_raw)
        except KeyError as exc:
            raise ValueError(f"Tello state packet has no field {exc} (not a Tello state stream?)") from None
        return self._sample

    def _from_vg(self, st: Mapping[str, Any], yaw_deg: float) -> float:
        # vg* in dm/s: x, y in the frame of yaw 0 (y right of x), vgz positive down (module docstring)
        wx, wy, wz = 0.1 * float(st["vgx"]), 0.1 * float(st["vgy"]), -0.1 * float(st["vgz"])
        return self._body(wx, wy, wz, yaw_deg)

    def _from_position(self, st: Mapping[str, Any], now: float, yaw_raw: float) -> None:
        x, y, z = (0.01 * float(st[k]) for k in ("x", "y", "z"))  # cm → m
        if self._prev is None:
            self._prev = (now, x, y, z, yaw_raw, yaw_raw)
            return
        t0, x0, y0, z0, yaw0_raw, yaw0 = self._prev
        yaw = yaw0 + ((yaw_raw - yaw0_raw + 180.0) % 360.0 - 180.0)  # unwrapped, deg clockwise
        self._prev = (now, x, y, z, yaw_raw, yaw)
        dt = now - t0
        if dt <= 0.0:
            return
        if self.axis == "yaw":
            value = -math.radians(yaw - yaw0) / dt  # clockwise deg → counter-clockwise rad/s
        else:
            value = self._body((x - x0) / dt, (y - y0) / dt, (z - z0) / dt, 0.5 * (yaw + yaw0))
        self._sample = (0.5 * (t0 + now), value)

    def _body(self, wx: float, wy: float, wz: float, yaw_deg: float) -> float:
        """World (x forward at takeoff, y right, z up; m/s) → the velocity along this body axis."""
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        if self.axis == "x":
            return c * wx + s * wy
        if self.axis == "y":
            return -(-s * wx + c * wy)  # body right → left
        return wz


def state_velocity_source(
    driver: Any, axis: str, field: Literal["position", "vg"] = "position"
) -> VelocitySource:
    """VelocitySource along `axis` from the driver's Tello state stream (a sample per new state packet).

    field="position" (default): differences of x/y/z (cm) and unwrapped yaw (deg) between consecutive
    packets, stamped at the middle of their arrival times; the first packet gives no sample.
    field="vg": the vgx/vgy/vgz fields (integer dm/s, vgz positive down) stamped at arrival; x, y, z only
    (no yaw rate field).
    Both rotate horizontal velocities into the body frame with the reported yaw (module docstring).
    Units: m/s, or rad/s counter-clockwise for yaw.
    """
    _check_axis(axis)
    if field not in ("position", "vg"):
        raise ValueError(f"field must be 'position' or 'vg', got {field!r}")
    if field == "vg" and axis == "yaw":
        raise ValueError("the Tello state has no yaw-rate field: use field='position' for yaw")
    return _StateVelocity(driver, axis, field)


# ------------------------------------------------------------------------------------------ experiments
def _rc_for(axis: str, u: int) -> tuple[int, int, int, int]:
    slot, sign = _RC_SLOT[axis]
    rc = [0, 0, 0, 0]
    rc[slot] = sign * u
    return (rc[0], rc[1], rc[2], rc[3])


def measure_step(
    driver: Any,
    axis: str,
    rc_amplitude: int = 40,
    duration_s: float = 2.0,
    rate_hz: float = 20.0,
    velocity_source: VelocitySource | None = None,
    *,
    baseline_s: float = 0.5,
    settle_s: float = 0.5,
    poll_s: float = 0.002,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Fly one rc step on `axis` and record the velocity along it.

    Sequence (rc re-sent at rate_hz throughout, so neither the driver's loop watchdog nor the Tello's
    auto-land interferes): `rc 0 0 0 0` for baseline_s (recorded: the zero level before the step), the
    step of rc_amplitude units along the axis for duration_s (recorded), then `rc 0 0 0 0` for settle_s
    (not recorded: the fit models a step, not a pulse). Any exception sends `rc 0 0 0 0` before it
    propagates. Takes baseline_s + duration_s + settle_s seconds.

    Args:
        driver: a connected, flying flightstack.drivers.tello.TelloDriver (uses `send_rc` and
        `current_state`).
        axis: "x" (forward), "y" (left), "z" (up) or "yaw" (counter-clockwise).
        rc_amplitude: the step in rc units along the axis, 1..100 in magnitude (sign = direction).
        duration_s: length of the step, s.
        rate_hz: rc send rate, Hz.
        velocity_source: where samples come from (default: state_velocity_source(driver, axis)); polled
            every poll_s, a sample is kept whenever its stamp is new.

    Returns:
        (t, v, t_step): sample stamps (monotonic s), velocities along the axis (m/s or rad/s), and the
        monotonic time the first step rc was sent.
    """
    _check_axis(axis)
    if not (isinstance(rc_amplitude, int | np.integer) and 0 < abs(rc_amplitude) <= RC_LIMIT):
        raise ValueError(f"rc_amplitude must be a non-zero integer within ±{RC_LIMIT}, got {rc_amplitude!r}")
    rc_amplitude = int(rc_amplitude)
    if not (duration_s > 0 and rate_hz > 0 and baseline_s >= 0 and settle_s >= 0 and poll_s > 0):
        raise ValueError("duration_s and rate_hz must be > 0; baseline_s, settle_s ≥ 0; poll_s > 0")
    source = velocity_source if velocity_source is not None else state_velocity_source(driver, axis)
    period = 1.0 / rate_hz
    samples: list[tuple[float, float]] = []
    last_stamp = -math.inf

    def phase(rc: tuple[int, int, int, int], length_s: float, record: bool) -> float:
        """Send rc every period for length_s (bounded by the monotonic clock); returns the start time."""
        nonlocal last_stamp
        start = time.monotonic()
        end = start + length_s
        next_send = start
        while True:
            now = time.monotonic()
            if now >= end:
                return start
            if now >= next_send:
                driver.send_rc(rc)
                next_send = max(next_send + period, now)
            if record:
                stamp, value = source()
                if stamp > last_stamp and math.isfinite(value):
                    last_stamp = stamp
                    samples.append((stamp, value))
            time.sleep(max(0.0, min(poll_s, end - time.monotonic(), next_send - time.monotonic())))

    try:
        phase((0, 0, 0, 0), baseline_s, record=True)
        t_step = phase(_rc_for(axis, rc_amplitude), duration_s, record=True)
        phase((0, 0, 0, 0), settle_s, record=False)
    finally:
        driver.send_rc((0, 0, 0, 0))
    arr = np.asarray(samples, dtype=float).reshape(-1, 2)
    return arr[:, 0].copy(), arr[:, 1].copy(), t_step


def _average(a: StepFit, b: StepFit) -> StepFit:
    n = a.samples + b.samples
    rms = math.sqrt((a.samples * a.rms_residual**2 + b.samples * b.rms_residual**2) / n)
    return StepFit(
        a.axis,
        0.5 * (a.gain + b.gain),
        0.5 * (a.tau_s + b.tau_s),
        0.5 * (a.delay_s + b.delay_s),
        rms,
        n,
    )


def identify(
    driver: Any,
    axes: Sequence[str] = AXES,
    rc_amplitude: int = 40,
    duration_s: float = 2.0,
    *,
    velocity_source_for: Callable[[str], VelocitySource] | None = None,
    **step_kw: float,
) -> dict[str, StepFit]:
    """Identify each axis: a step of +rc_amplitude, then −rc_amplitude (back towards the start), both
    fitted with fit_first_order_step and averaged (gain, τ, delay; RMS pooled; samples summed).

    The drone must be flying. Axes run in the given order; with the default order yaw comes last, so
    the x/y steps are flown at the takeoff heading. Each axis takes about 2 · (baseline_s + duration_s +
    settle_s) s (6 s with the defaults). `velocity_source_for(axis)` makes a fresh VelocitySource per
    step, fitted with plain least squares (white noise); by default the state stream's differenced
    positions (state_velocity_source), fitted with differenced=True. step_kw go to measure_step
    (baseline_s, settle_s, rate_hz, poll_s). Returns {axis: StepFit}; ValueError names the axis that
    failed. The rc amplitude trades the distance flown (rc 40 ≈ 0.4 m/s for duration_s, then back)
    against the resolution of the 1 cm / 1° state rounding (module docstring; numbers in docs/lab_notes.md).
    """
    for axis in axes:
        _check_axis(axis)
    if not driver.state().flying:
        raise RuntimeError("identify needs a flying drone: call driver.takeoff() first")
    fits: dict[str, StepFit] = {}
    for axis in axes:
        pair = []
        for u in (rc_amplitude, -rc_amplitude):
            source = velocity_source_for(axis) if velocity_source_for is not None else None
            t, v, t_step = measure_step(driver, axis, u, duration_s, velocity_source=source, **step_kw)
            pair.append(fit_first_order_step(t, v, t_step, u, axis, differenced=source is None))
        fits[axis] = _average(pair[0], pair[1])
    return fits


def fits_to_rc_gains(fits: Mapping[str, StepFit], base: RcGains | None = None) -> RcGains:
    """RcGains from identified axes: xy = mean of the x and y gains (m/s per unit), z (m/s per unit),
    yaw (rad/s per unit). Axes missing from `fits` are taken from `base`; ValueError if base is None then
    (xy needs x or y)."""
    xy_gains = [fits[a].gain for a in ("x", "y") if a in fits]
    have = {"xy": bool(xy_gains), "z": "z" in fits, "yaw": "yaw" in fits}
    missing = [name for name, ok in have.items() if not ok]
    if missing and base is None:
        raise ValueError(f"no identification for rc gain(s) {missing}: identify those axes or pass base")
    wrong = [a for a, f in fits.items() if not f.gain > 0]
    if wrong:
        raise ValueError(f"axes {wrong} moved against the command (gain ≤ 0): check the state frame or signs")
    b = base if base is not None else RcGains()  # only read for missing axes
    return RcGains(
        xy=float(np.mean(xy_gains)) if xy_gains else b.xy,
        z=fits["z"].gain if "z" in fits else b.z,
        yaw=fits["yaw"].gain if "yaw" in fits else b.yaw,
    )


def save_identification(path: str | Path, fits: Mapping[str, StepFit], drone_host: str) -> None:
    """Write the identification as YAML: rc_gains {xy, z, yaw} (loadable as a mission's drones.N.rc_gains),
    per-axis time constants tau_s, delays delay_s (s), RMS residuals (m/s, rad/s for yaw), sample counts,
    the per-axis gains, the date (UTC, ISO 8601) and the drone's host. Needs x or y, z and yaw."""
    gains = fits_to_rc_gains(fits)
    doc = {
        "drone_host": drone_host,
        "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "rc_gains": {"xy": float(gains.xy), "z": float(gains.z), "yaw": float(gains.yaw)},
        "axis_gains": {a: float(f.gain) for a, f in fits.items()},
        "tau_s": {a: float(f.tau_s) for a, f in fits.items()},
        "delay_s": {a: float(f.delay_s) for a, f in fits.items()},
        "rms_residual": {a: float(f.rms_residual) for a, f in fits.items()},
        "samples": {a: int(f.samples) for a, f in fits.items()},
    }
    header = (
        "# Tello velocity identification (drivers/tello/identify.py): rc_gains in m/s (xy, z)\n"
        "# and rad/s (yaw) per rc unit; axes x forward, y left, z up, yaw counter-clockwise (body FLU);\n"
        "# tau_s, delay_s in s; rms_residual in m/s (rad/s for yaw).\n"
    )
    Path(path).write_text(header + yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
