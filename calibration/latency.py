"""How late a measurement stream is: time series in, delay estimate out (pure functions, no I/O).

A reference signal y_ref(t) (e.g. the markers' pixels predicted from the motion-capture poses, sampled at
t_ref) and an observed one (the markers' pixels found in each decoded frame, stamped with its decode time
t_obs) are taken to satisfy y_obs_i ≈ y_ref(t_obs_i − d_i): frame i shows the world as it was d_i seconds
before it was stamped. `estimate_delay` finds the common lag by normalised cross-correlation (peak on a
grid, refined by a parabola), then each frame's own d_i by aligning it alone within a window around that
peak; the mean and spread of the d_i are the link's latency and jitter. A frame is timed only where its
value is passed once in that window: frames taken while the reference stands still or turns back are
left out. A pattern that moves one way at varying speed (a yaw turning on, faster and slower) times
every frame.

`cross_correlation_lag` alone serves signals of different shapes (a commanded yaw rate against the
measured one: its peak is the delay plus the response's own lag).

Units: seconds for times; y in any unit, the same for both signals (vectors: one column per component).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DelayEstimate:
    """A stream's delay (s): `mean_s` and `sd_s` of the per-frame delays, their 5th/95th percentiles
    (`p5_s`, `p95_s`), the cross-correlation's peak lag (`peak_s`) and value (`correlation`, −1..1), and
    `n_used` of `n_frames` frames timed (the others: the reference too still, or no clear minimum)."""

    mean_s: float
    sd_s: float
    p5_s: float
    p95_s: float
    peak_s: float
    correlation: float
    n_used: int
    n_frames: int

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


def estimate_delay(
    t_ref: np.ndarray,
    y_ref: np.ndarray,
    t_obs: np.ndarray,
    y_obs: np.ndarray,
    max_lag_s: float = 1.0,
    window_s: float = 0.1,
    step_s: float = 0.001,
    min_speed_ratio: float = 0.3,
) -> DelayEstimate:
    """The delay of the observed stream behind the reference (module docstring).

    t_ref (n,) increasing, y_ref (n,) or (n, k): the reference; t_obs (m,), y_obs (m,) or (m, k): each
    observation stamped when it became available (NaN rows: not seen, skipped). max_lag_s: the largest
    delay looked for; window_s: each frame's own delay is searched within the peak ± window_s (wider than
    the jitter's half-range); step_s: the grid; min_speed_ratio: frames whose window has the reference
    slower than this fraction of its median speed, or turning back, are not timed. ValueError when fewer
    than 3 frames can be timed.
    """
    t_ref = np.asarray(t_ref, dtype=float)
    t_obs = np.asarray(t_obs, dtype=float)
    yr, yo = _columns(y_ref), _columns(y_obs)
    peak, corr = cross_correlation_lag(t_ref, yr, t_obs, yo, max_lag_s, step_s)
    lo, hi = max(0.0, peak - window_s), peak + window_s
    keep = (t_obs - hi >= t_ref[0]) & (t_obs - lo <= t_ref[-1]) & np.isfinite(yo).all(axis=1)
    t, y = t_obs[keep], yo[keep]
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
    # a frame is timed only where the reference passes its value once within the window: it moves on
    # every step (no turning point, no standstill: min_speed_ratio of the median speed) in one direction
    v = np.diff(z, axis=1) / step_s  # (n, lags - 1, k): the reference's velocity along each window
    speed = np.linalg.norm(v, axis=2)
    v_best = v[rows, np.clip(b, 0, v.shape[1] - 1)]  # (n, k)
    ahead = np.einsum("nlk,nk->nl", v, v_best) > 0
    fast = (speed.min(axis=1) >= min_speed_ratio * float(np.median(speed))) & ahead.all(axis=1)
    used = d[inner & fast]
    if used.size < 3:
        raise ValueError(f"only {used.size} frames could be timed (the reference moves too little?)")
    return DelayEstimate(
        mean_s=float(used.mean()),
        sd_s=float(used.std(ddof=1)),
        p5_s=float(np.percentile(used, 5)),
        p95_s=float(np.percentile(used, 95)),
        peak_s=peak,
        correlation=corr,
        n_used=int(used.size),
        n_frames=len(t_obs),
    )


__all__ = ["DelayEstimate", "cross_correlation_lag", "estimate_delay"]
