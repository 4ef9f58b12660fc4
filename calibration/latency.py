"""How late a measurement stream is: time series in, delay estimate out (pure functions, no I/O).

A reference signal y_ref(t) (e.g. the markers' pixels predicted from the motion-capture poses, sampled at
t_ref) and an observed one (the markers' pixels found in each decoded frame, stamped with its decode time
t_obs) are taken to satisfy y_obs_i ≈ y_ref(t_obs_i − d_i): frame i shows the world as it was d_i seconds
before it was stamped. `estimate_delay` finds the common lag by normalised cross-correlation (peak on a
grid, refined by a parabola), then each frame's own d_i by aligning it alone within a window around that
peak; the mean and spread of the d_i are the link's latency and jitter. A frame is timed only where its
value is passed once in that window: frames taken while the reference stands still, or near where it
turns back, are left out. A pattern that moves one way at varying speed (a yaw turning on, faster and
slower) times nearly every frame. Pixel noise spreads the per-frame delays too (by σ/|dy/dt| each, σ
taken from the fits' residuals): that part is taken out of the spread.

`cross_correlation_lag` alone serves signals of different shapes (a commanded yaw rate against the
measured one: its peak is the delay plus the response's own lag).

Units: seconds for times; y in any unit, the same for both signals (vectors: one column per component).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

AMBIGUOUS = 4.0
"""A frame whose cost has a second minimum below this many times its best (or the median best) is not
timed: two delays fit it about as well."""
SEPARATION_S = 0.02
"""How far from the best delay (s) another minimum counts as a second one (closer: the same, noisy)."""
MAX_SEARCH_S = 5.0
"""Largest delay (s) the estimators look for, and widest window: a Tello's video is about 0.3-0.5 s late
and its rc about 0.1-0.2 s; the cost grows with the delays tried (one per ms)."""
MAX_FIT_CELLS = 50_000_000
"""Bound on the delays tried × the samples fitted in one pass of estimate_command_delay (400 MB of
float64): a larger fit is refused with ValueError rather than allocated."""


def check_search(name: str, value: float) -> float:
    """`value` if it is a finite number of seconds in (0, MAX_SEARCH_S], else ValueError naming `name`."""
    if not (isinstance(value, int | float) and math.isfinite(value) and 0 < value <= MAX_SEARCH_S):
        raise ValueError(f"{name} must be a number of seconds in (0, {MAX_SEARCH_S:g}], got {value!r}")
    return float(value)


@dataclass(frozen=True)
class DelayEstimate:
    """A stream's delay (s): `mean_s` and `sd_s` of the per-frame delays (the spread without the timing
    noise `noise_s`, the rms of what pixel noise alone adds to each frame's delay), their 5th/95th
    percentiles (`p5_s`, `p95_s`, with the noise), the cross-correlation's peak lag (`peak_s`) and value
    (`correlation`, −1..1), and `n_used` of `n_frames` frames timed (the others: the reference too still,
    or two delays fit about as well)."""

    mean_s: float
    sd_s: float
    p5_s: float
    p95_s: float
    peak_s: float
    correlation: float
    n_used: int
    n_frames: int
    noise_s: float = 0.0

    def as_link(self) -> tuple[float, float]:
        """(latency_s, jitter_s) of a link `latency_s + U(0, jitter_s)` with the same mean and standard
        deviation (flightstack.config.links); latency_s is clipped at 0."""
        jitter = math.sqrt(12.0) * self.sd_s
        return max(0.0, self.mean_s - jitter / 2.0), jitter


def _columns(y: np.ndarray) -> np.ndarray:
    a = np.asarray(y, dtype=float)
    return a.reshape(len(a), -1)


def _interp(t_ref: np.ndarray, y_ref: np.ndarray, t: np.ndarray) -> np.ndarray:
    """y_ref (n, k) linearly interpolated at t (any shape) → (*t.shape, k)."""
    flat = t.ravel()
    out = np.empty((flat.size, y_ref.shape[1]))
    for j in range(y_ref.shape[1]):
        out[:, j] = np.interp(flat, t_ref, y_ref[:, j])
    return out.reshape(*t.shape, y_ref.shape[1])


def _parabola(c_m: float, c_0: float, c_p: float) -> float:
    """Offset (in grid steps, −1..1) of the extremum of the parabola through three equally spaced values."""
    den = c_m - 2.0 * c_0 + c_p
    return 0.0 if den == 0.0 else float(np.clip(0.5 * (c_m - c_p) / den, -1.0, 1.0))


def cross_correlation_lag(
    t_ref: np.ndarray,
    y_ref: np.ndarray,
    t_obs: np.ndarray,
    y_obs: np.ndarray,
    max_lag_s: float,
    step_s: float = 0.001,
    min_lag_s: float = 0.0,
) -> tuple[float, float]:
    """(lag s, correlation) maximising the normalised cross-correlation of y_obs(t) with y_ref(t − lag)
    over lags in [min_lag_s, max_lag_s] (grid step_s, parabola-refined). t_ref must increase; only
    observations with t_obs − lag inside t_ref for every lag count. ValueError with fewer than 3."""
    check_search("max_lag_s", max_lag_s)
    t_ref = np.asarray(t_ref, dtype=float)
    t_obs = np.asarray(t_obs, dtype=float)
    yr, yo = _columns(y_ref), _columns(y_obs)
    if yr.shape[1] != yo.shape[1] or len(yr) != len(t_ref) or len(yo) != len(t_obs):
        raise ValueError("reference and observation must have matching lengths and components")
    keep = (t_obs - max_lag_s >= t_ref[0]) & (t_obs - min_lag_s <= t_ref[-1]) & np.isfinite(yo).all(axis=1)
    if keep.sum() < 3:
        raise ValueError(f"only {int(keep.sum())} observations overlap the reference")
    t, y = t_obs[keep], yo[keep]
    y = y - y.mean(axis=0)
    lags = np.arange(min_lag_s, max_lag_s + step_s / 2, step_s)
    z = _interp(t_ref, yr, t[None, :] - lags[:, None])  # (lags, n, k)
    z = z - z.mean(axis=1, keepdims=True)
    num = np.einsum("lnk,nk->l", z, y)
    den = np.sqrt(np.einsum("lnk,lnk->l", z, z) * float(np.sum(y * y)))
    corr = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    i = int(np.argmax(corr))
    frac = _parabola(corr[i - 1], corr[i], corr[i + 1]) if 0 < i < len(lags) - 1 else 0.0
    return float(lags[i] + frac * step_s), float(corr[i])


def frame_delays(
    t_ref: np.ndarray,
    y_ref: np.ndarray,
    t_obs: np.ndarray,
    y_obs: np.ndarray,
    peak_s: float,
    window_s: float = 0.3,
    step_s: float = 0.001,
    min_speed_ratio: float = 0.3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(delays (m,) s, timed (m,) bool, noise (m,) s): each observation aligned alone with the reference
    within peak_s ± window_s (estimate_delay's arguments); NaN delay where it is outside the reference or
    unseen; timed False where it cannot be timed (estimate_delay); noise: the standard deviation pixel
    noise alone gives its delay (σ/|dy/dt|, σ² per component from the timed fits' mean residual)."""
    t_ref, t_obs = np.asarray(t_ref, dtype=float), np.asarray(t_obs, dtype=float)
    yr, yo = _columns(y_ref), _columns(y_obs)
    peak = peak_s
    lo, hi = max(0.0, peak - window_s), peak + window_s
    keep = (t_obs - hi >= t_ref[0]) & (t_obs - lo <= t_ref[-1]) & np.isfinite(yo).all(axis=1)
    t, y = t_obs[keep], yo[keep]
    if t.size == 0:
        return np.full(len(t_obs), np.nan), np.zeros(len(t_obs), dtype=bool), np.full(len(t_obs), np.nan)
    lags = np.arange(lo, hi + step_s / 2, step_s)
    z = _interp(t_ref, yr, t[:, None] - lags[None, :])  # (n, lags, k)
    cost = np.sum((z - y[:, None, :]) ** 2, axis=2)  # (n, lags)
    best = np.argmin(cost, axis=1)
    inner = (best > 0) & (best < len(lags) - 1)  # a minimum on the window's edge is no minimum
    rows = np.arange(len(t))
    b = np.clip(best, 1, len(lags) - 2)
    c_m, c_0, c_p = cost[rows, b - 1], cost[rows, b], cost[rows, b + 1]
    den = c_m - 2.0 * c_0 + c_p
    frac = np.where(den > 0, np.clip(0.5 * (c_m - c_p) / np.where(den > 0, den, 1.0), -1, 1), 0.0)
    d = lags[b] + frac * step_s
    # a frame is timed only where the reference moves at its aligned time (min_speed_ratio of the median
    # speed: no standstill) and passes the frame's value once within the window (no other minimum of the
    # cost, away from the best, as low as AMBIGUOUS × the best or the typical fit: no turning back)
    v = np.diff(z, axis=1) / step_s  # (n, lags - 1, k): the reference's velocity along each window
    speed = np.linalg.norm(v[rows, np.clip(b, 0, v.shape[1] - 1)], axis=1)
    fast = speed >= min_speed_ratio * float(np.median(speed))
    is_min = np.zeros_like(cost, dtype=bool)
    is_min[:, 1:-1] = (cost[:, 1:-1] <= cost[:, :-2]) & (cost[:, 1:-1] <= cost[:, 2:])
    is_min[:, 0], is_min[:, -1] = cost[:, 0] <= cost[:, 1], cost[:, -1] <= cost[:, -2]  # or beyond the edge
    apart = np.abs(np.arange(len(lags))[None, :] - best[:, None]) * step_s > SEPARATION_S
    second = np.where(is_min & apart, cost, np.inf).min(axis=1)
    floor = AMBIGUOUS * max(float(np.median(c_0)), 1e-12)
    fast &= second > np.maximum(AMBIGUOUS * c_0, floor)
    timed = inner & fast
    dof = max(yr.shape[1] - 1, 1)  # one of the k components' freedom goes into fitting the delay
    var = float(np.mean(c_0[timed])) / dof if timed.any() else 0.0
    out, ok, noise = (
        np.full(len(t_obs), np.nan),
        np.zeros(len(t_obs), dtype=bool),
        np.full(len(t_obs), np.nan),
    )
    out[keep], ok[keep], noise[keep] = d, timed, math.sqrt(var) / np.maximum(speed, 1e-12)
    return out, ok, noise


def estimate_delay(
    t_ref: np.ndarray,
    y_ref: np.ndarray,
    t_obs: np.ndarray,
    y_obs: np.ndarray,
    max_lag_s: float = 1.0,
    window_s: float = 0.3,
    step_s: float = 0.001,
    min_speed_ratio: float = 0.3,
) -> DelayEstimate:
    """The delay of the observed stream behind the reference (module docstring).

    t_ref (n,) increasing, y_ref (n,) or (n, k): the reference; t_obs (m,), y_obs (m,) or (m, k): each
    observation stamped when it became available (NaN rows: not seen, skipped). max_lag_s: the largest
    delay looked for; window_s: each frame's own delay is searched within the peak ± window_s (wider than
    the jitter's half-range); step_s: the grid; min_speed_ratio: frames where the reference moves slower than
    this fraction of its median speed are not timed, nor those two delays in the window fit about as well
    (AMBIGUOUS). ValueError when fewer than 3 frames can be timed.
    """
    check_search("max_lag_s", max_lag_s)
    check_search("window_s", window_s)
    t_ref = np.asarray(t_ref, dtype=float)
    t_obs = np.asarray(t_obs, dtype=float)
    yr, yo = _columns(y_ref), _columns(y_obs)
    peak, corr = cross_correlation_lag(t_ref, yr, t_obs, yo, max_lag_s, step_s)
    d, timed, noise = frame_delays(t_ref, yr, t_obs, yo, peak, window_s, step_s, min_speed_ratio)
    used = d[timed]
    noise_var = float(np.mean(noise[timed] ** 2)) if timed.any() else 0.0
    if used.size < 3:
        raise ValueError(f"only {used.size} frames could be timed (the reference moves too little?)")
    return DelayEstimate(
        mean_s=float(used.mean()),
        sd_s=math.sqrt(max(0.0, float(used.var(ddof=1)) - noise_var)),
        p5_s=float(np.percentile(used, 5)),
        p95_s=float(np.percentile(used, 95)),
        peak_s=peak,
        correlation=corr,
        n_used=int(used.size),
        n_frames=len(t_obs),
        noise_s=math.sqrt(noise_var),
    )


@dataclass(frozen=True)
class ResponseEstimate:
    """A command's effect: each change of the command acts `delay` s later (mean `mean_s`, spread `sd_s`
    over `n_steps` changes timed), then the measured rate follows gain × command through a first-order lag
    of `tau_s` (s). `peak_s`: the best common delay of the whole fit."""

    mean_s: float
    sd_s: float
    tau_s: float
    gain: float
    peak_s: float
    n_steps: int

    def as_link(self) -> tuple[float, float]:
        """(latency_s, jitter_s) of `latency_s + U(0, jitter_s)` with the same mean and spread."""
        jitter = math.sqrt(12.0) * self.sd_s
        return max(0.0, self.mean_s - jitter / 2.0), jitter


def _lagged(u: np.ndarray, tau_s: float, dt: float) -> np.ndarray:
    """u (on a grid of step dt) through a first-order lag of tau_s (exact for a piecewise-constant u)."""
    if tau_s <= 0:
        return u.copy()
    a = math.exp(-dt / tau_s)
    out = np.empty_like(u)
    acc = u[0]
    for i, v in enumerate(u):  # a Python loop over ≤ a few 10^4 samples: fast enough for a calibration
        acc = a * acc + (1.0 - a) * v
        out[i] = acc
    return out


def estimate_command_delay(
    t_cmd: np.ndarray,
    cmd: np.ndarray,
    t_meas: np.ndarray,
    angle: np.ndarray,
    max_delay_s: float = 0.5,
    taus_s: np.ndarray | None = None,
    window_s: float = 0.1,
    step_s: float = 0.001,
) -> ResponseEstimate:
    """How late a rate command acts: cmd (n,) sent at t_cmd (n,) (each held until the next), the angle it
    drives (any unit, unwrapped) measured at t_meas (m,). The measured rate (angle differenced) is fitted
    by gain × lag_tau(cmd(t − d)) over d in [0, max_delay_s] and tau in taus_s (default 0..0.5 s); then
    each change of the command is timed alone within d ± window_s on the measurements up to the next
    change. ValueError without changes to time."""
    check_search("max_delay_s", max_delay_s)
    t_cmd, cmd = np.asarray(t_cmd, float), np.asarray(cmd, float)
    t_meas, angle = np.asarray(t_meas, float), np.asarray(angle, float)
    if len(t_cmd) < 2 or len(t_meas) < 3:
        raise ValueError(f"{len(t_cmd)} commands and {len(t_meas)} measurements: need at least 2 and 3")
    taus = np.arange(0.0, 0.5001, 0.01) if taus_s is None else np.asarray(taus_s, float)
    rate = np.diff(angle) / np.diff(t_meas)
    tm = 0.5 * (t_meas[1:] + t_meas[:-1])
    t0 = t_cmd[0]
    span = max(tm[-1], t_cmd[-1]) - t0
    if not (math.isfinite(span) and span / step_s <= MAX_FIT_CELLS):
        raise ValueError(f"the commands and measurements span {span:g} s: more than {MAX_FIT_CELLS:,} steps")
    grid = np.arange(t0, max(tm[-1], t_cmd[-1]) + step_s, step_s)
    u = cmd[np.clip(np.searchsorted(t_cmd, grid, side="right") - 1, 0, len(cmd) - 1)]
    shifts = np.arange(0, round(max_delay_s / step_s) + 1)
    keep = tm - max_delay_s >= t0
    tm, rate = tm[keep], rate[keep]
    if len(shifts) * len(tm) > MAX_FIT_CELLS:
        raise ValueError(
            f"{len(shifts)} delays × {len(tm)} measurements to fit: more than {MAX_FIT_CELLS:,} (shorten the "
            "session or the largest delay)"
        )
    idx = np.round((tm - t0) / step_s).astype(int)
    best = (math.inf, 0.0, 0, 0.0)  # (sse, tau, shift, gain)
    for tau in taus:
        f = _lagged(u, float(tau), step_s)
        x = f[idx[None, :] - shifts[:, None]]  # (shifts, m)
        xx = np.einsum("sm,sm->s", x, x)
        xr = x @ rate
        gains = np.where(xx > 0, xr / np.where(xx > 0, xx, 1.0), 0.0)
        sse_fit = float(rate @ rate) - gains * xr
        j = int(np.argmin(sse_fit))
        if sse_fit[j] < best[0]:
            best = (float(sse_fit[j]), float(tau), int(shifts[j]), float(gains[j]))
    _, tau, shift, gain = best
    f = _lagged(u, tau, step_s)
    changes = np.flatnonzero(np.diff(cmd) != 0) + 1
    w = round(window_s / step_s)
    local = np.arange(max(0, shift - w), shift + w + 1)
    delays = []
    for n, k in enumerate(changes):
        end = t_cmd[changes[n + 1]] if n + 1 < len(changes) else t_cmd[k] + 1.0
        seg = (tm >= t_cmd[k]) & (tm < end + shift * step_s)
        if seg.sum() < 3 or idx[seg].min() - local.max() < 0:
            continue
        x = gain * f[idx[seg][None, :] - local[:, None]]
        sse = np.sum((x - rate[seg]) ** 2, axis=1)
        j = int(np.argmin(sse))
        if 0 < j < len(local) - 1:
            delays.append((local[j] + _parabola(sse[j - 1], sse[j], sse[j + 1])) * step_s)
    if len(delays) < 2:
        raise ValueError(f"only {len(delays)} command changes could be timed")
    d = np.array(delays)
    return ResponseEstimate(float(d.mean()), float(d.std(ddof=1)), tau, gain, shift * step_s, int(d.size))


__all__ = [
    "MAX_FIT_CELLS",
    "MAX_SEARCH_S",
    "DelayEstimate",
    "ResponseEstimate",
    "check_search",
    "cross_correlation_lag",
    "estimate_command_delay",
    "estimate_delay",
    "frame_delays",
]
