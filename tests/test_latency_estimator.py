"""The delay estimator (flightstack.calibration.latency) on synthetic streams with a known delay: a frame
captured at t_c is stamped t_c + L + U(0, J), so the per-frame delays have mean L + J/2 and standard
deviation J/√12 (closed form); the estimate recovers both, with pixel noise, from a reference sampled
at the motion capture's rate, and leaves out frames taken while the reference stood still."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightstack.calibration.latency import (
    DelayEstimate,
    cross_correlation_lag,
    estimate_command_delay,
    estimate_delay,
)

FREQS_HZ = (0.37, 0.83, 1.31)


def yaw(t: np.ndarray, back_and_forth: bool = False) -> np.ndarray:
    """A yaw (rad) turning one way at 1 rad/s ± 0.8 rad/s of incommensurate sines, or only the sines."""
    wobble = sum(np.sin(2 * math.pi * f * t + k) / (2 * math.pi * f) for k, f in enumerate(FREQS_HZ))
    return (0.0 if back_and_forth else 1.0 * t) + 0.3 * wobble


def pattern(t: np.ndarray, back_and_forth: bool = False) -> np.ndarray:
    """Two image coordinates (px) of a marker 40 px from the image's centre, turned by the yaw."""
    a = yaw(t, back_and_forth)
    return np.stack([100.0 + 40.0 * np.cos(a), 80.0 + 40.0 * np.sin(a)], axis=1)


def stream(
    latency_s: float,
    jitter_s: float,
    noise_px: float,
    seed: int,
    back_and_forth: bool = False,
    fps: float = 30.0,
    duration_s: float = 12.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_ref, y_ref) at 120 Hz, (t_obs, y_obs) stamped late, and the true per-frame delays."""
    rng = np.random.default_rng(seed)
    t_ref = np.arange(0.0, duration_s, 1 / 120.0)
    t_cap = np.arange(1.2, duration_s - 1.0, 1 / fps)
    delays = latency_s + rng.uniform(0.0, jitter_s, t_cap.size)
    y_obs = pattern(t_cap, back_and_forth) + rng.normal(0.0, noise_px, (t_cap.size, 2))
    return t_ref, pattern(t_ref, back_and_forth), t_cap + delays, y_obs, delays


def test_a_constant_delay_is_recovered_to_a_millisecond() -> None:
    t_ref, y_ref, t_obs, y_obs, _ = stream(0.3, 0.0, 0.0, seed=0)
    est = estimate_delay(t_ref, y_ref, t_obs, y_obs)
    assert abs(est.mean_s - 0.3) < 1e-3 and est.sd_s < 1e-3, est
    assert abs(est.peak_s - 0.3) < 1e-3 and est.correlation > 0.999
    assert est.as_link() == pytest.approx((0.3, 0.0), abs=4e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_jittered_delay_gives_its_mean_and_spread_in_closed_form(seed: int) -> None:
    latency, jitter = 0.3, 0.1
    t_ref, y_ref, t_obs, y_obs, delays = stream(latency, jitter, noise_px=0.2, seed=seed)
    est = estimate_delay(t_ref, y_ref, t_obs, y_obs)
    # the sample of delays' own mean is L + J/2 within J/√12/√n (≈ 1.6 ms for 320 frames)
    assert abs(est.mean_s - (latency + jitter / 2)) < 6e-3, est
    assert abs(est.mean_s - delays.mean()) < 3e-3, (est, delays.mean())
    assert abs(est.sd_s - jitter / math.sqrt(12)) < 5e-3, est
    lat, jit = est.as_link()
    assert abs(lat - latency) < 0.012 and abs(jit - jitter) < 0.02, (lat, jit)
    assert est.n_used > 0.8 * est.n_frames


def test_frames_taken_while_the_reference_turns_back_or_stands_still_are_not_timed() -> None:
    """A yaw back and forth: near each turning point a frame's value is passed twice within the window
    (two delays fit it), so it is not timed; nor while the reference stands still."""
    t_ref, y_ref, t_obs, y_obs, delays = stream(0.3, 0.1, 0.2, seed=2, back_and_forth=True)
    est = estimate_delay(t_ref, y_ref, t_obs, y_obs)
    assert abs(est.mean_s - delays.mean()) < 6e-3 and abs(est.sd_s - 0.1 / math.sqrt(12)) < 6e-3, est
    assert est.n_used < 0.9 * est.n_frames
    t_ref, y_ref, t_obs, y_obs, _ = stream(0.2, 0.0, 0.0, seed=3)
    hold = (t_ref > 5.0) & (t_ref < 8.0)
    y_ref[hold] = y_ref[np.argmax(hold)]  # three seconds without motion
    t_cap = t_obs - 0.2
    y_obs = np.where(((t_cap > 5.0) & (t_cap < 8.0))[:, None], y_ref[np.argmax(hold)], y_obs)
    est = estimate_delay(t_ref, y_ref, t_obs, y_obs)
    assert abs(est.mean_s - 0.2) < 2e-3 and est.n_used < 0.85 * est.n_frames, est


def test_unseen_frames_are_skipped_and_a_still_reference_is_refused() -> None:
    t_ref, y_ref, t_obs, y_obs, _ = stream(0.25, 0.0, 0.0, seed=4)
    y_obs[::3] = np.nan  # the markers not found in every third frame
    assert abs(estimate_delay(t_ref, y_ref, t_obs, y_obs).mean_s - 0.25) < 2e-3
    with pytest.raises(ValueError):
        estimate_delay(t_ref, np.zeros_like(y_ref), t_obs, np.zeros_like(y_obs))


def test_cross_correlation_finds_a_command_lag_of_a_step_pattern() -> None:
    """A yaw-rate step pattern (zero-order hold) and a response late by 80 ms: the peak is at 80 ms."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 20.0, 0.005)
    steps = np.repeat(rng.choice([-1.0, 0.0, 1.0], 40), len(t) // 40)
    t_meas = np.arange(0.5, 19.5, 0.01)
    measured = np.interp(t_meas - 0.08, t, steps)
    lag, corr = cross_correlation_lag(t, steps, t_meas, measured, max_lag_s=0.5)
    assert abs(lag - 0.08) < 5e-3 and corr > 0.99  # the reference's 5 ms grid


def test_the_link_of_an_estimate_keeps_its_mean() -> None:
    est = DelayEstimate(0.35, 0.029, 0.3, 0.4, 0.35, 0.9, 100, 110)
    lat, jit = est.as_link()
    assert lat + jit / 2 == pytest.approx(0.35) and jit == pytest.approx(0.1, abs=1e-3)


def test_a_rate_command_late_by_a_jittered_link_through_a_first_order_lag() -> None:
    """Yaw-rate steps (rc units) sent at 20 Hz; each change acts 50 ms + U(0, 30 ms) late, then the yaw
    rate follows 1.2 deg/s per unit through a 0.1 s lag; the yaw is measured at 100 Hz with 0.05° noise.
    The timed changes give the delays' mean (65 ms) and spread (30/√12 ms) in closed form."""
    rng = np.random.default_rng(6)
    t_cmd = np.arange(0.0, 30.0, 0.05)
    steps = [0.0]
    for _ in range(29):  # a new level every second, never the same twice in a row
        steps.append(float(rng.choice([v for v in (-40.0, -20.0, 0.0, 20.0, 40.0) if v != steps[-1]])))
    cmd = np.repeat(steps, 20)[: t_cmd.size]
    act = t_cmd + 0.05 + rng.uniform(0.0, 0.03, t_cmd.size)  # every datagram late by the link
    dt = 0.0005
    grid = np.arange(0.0, 31.0, dt)
    order = np.argsort(act)
    u = np.zeros_like(grid)
    for a, v in zip(act[order], cmd[order], strict=True):
        u[grid >= a] = v
    rate = np.empty_like(u)
    acc, alpha = 0.0, 1.0 - math.exp(-dt / 0.1)
    for i, v in enumerate(1.2 * u):
        acc += alpha * (v - acc)
        rate[i] = acc
    yaw_fine = np.cumsum(rate) * dt
    t_meas = np.arange(0.5, 30.5, 0.01)
    yaw_meas = np.interp(t_meas, grid, yaw_fine) + rng.normal(0.0, 0.05, t_meas.size)
    changes = np.flatnonzero(np.diff(cmd) != 0) + 1
    truth = act[changes] - t_cmd[changes]
    est = estimate_command_delay(t_cmd, cmd, t_meas, yaw_meas)
    assert abs(est.mean_s - truth.mean()) < 5e-3, (est, truth.mean())
    assert abs(est.sd_s - 0.03 / math.sqrt(12)) < 5e-3, est
    assert abs(est.tau_s - 0.1) <= 0.02 and abs(est.gain - 1.2) < 0.05, est
    assert est.n_steps > 0.8 * changes.size
