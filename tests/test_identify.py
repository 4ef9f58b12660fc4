"""drivers/tello/identify.py: the step fit on synthetic data, the state-stream velocity source, and a full
identification against the loopback Tello emulator through TelloDriver.

The emulator owns 127.0.0.5 (the driver tests use 127.0.0.3/.4, the emulator's own tests 127.0.0.2).
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

import flightstack.drivers.tello.identify as ident
from flightstack.config.mission import RcGainsSpec
from flightstack.drivers.tello.identify import (
    StepFit,
    first_order_step,
    fit_first_order_step,
    fits_to_rc_gains,
    identify,
    save_identification,
    state_velocity_source,
)
from flightstack.drivers.tello.rc import RcGains


# ------------------------------------------------------------------------------------- synthetic fits
@pytest.mark.parametrize(
    ("gain", "tau", "delay", "u", "rate_hz", "noise"),
    [
        # noise σ ≈ 2 % of the step: over 200 seeds the τ error stays below 10 % (its σ is 2–3.3 %)
        (0.0123, 0.25, 0.12, 40, 20.0, 0.01),  # m/s per unit, noise in m/s
        (0.0095, 0.40, 0.05, -30, 20.0, 0.005),
        (0.0180, 0.15, 0.20, 50, 30.0, 0.02),  # yaw-like: rad/s per unit
        (0.0100, 0.10, 0.02, 40, 10.0, 0.002),  # the emulator's truth at the state stream's 10 Hz
    ],
)
def test_fit_recovers_gain_tau_and_delay(
    gain: float, tau: float, delay: float, u: int, rate_hz: float, noise: float
) -> None:
    rng = np.random.default_rng(7)
    t_step = 100.0  # arbitrary monotonic-clock origin
    t = t_step + np.arange(-0.5, 2.5, 1.0 / rate_hz) + rng.uniform(0, 1.0 / rate_hz)
    v = first_order_step(t, t_step, u, gain, tau, delay) + rng.normal(0.0, noise, t.size)
    fit = fit_first_order_step(t, v, t_step, u, "x")
    assert fit.axis == "x" and fit.samples == t.size
    assert fit.gain == pytest.approx(gain, rel=0.02)
    assert fit.tau_s == pytest.approx(tau, rel=0.10)
    assert fit.delay_s == pytest.approx(delay, abs=0.03)
    assert fit.rms_residual == pytest.approx(noise, rel=0.3)


def test_fit_rejects_too_few_samples_and_no_response() -> None:
    t = np.arange(0.0, 2.0, 0.1)
    v = first_order_step(t, 1.7, 40, 0.01, 0.1, 0.0)
    with pytest.raises(ValueError, match=r"only 2 velocity samples after the step"):
        fit_first_order_step(t, v, 1.75, 40, "z")  # samples at 1.8 and 1.9 only
    rng = np.random.default_rng(1)
    flat = rng.normal(0.0, 0.002, t.size)  # sensor noise, no motion
    with pytest.raises(ValueError, match=r"yaw: no response"):
        fit_first_order_step(t, flat, 0.5, 40, "yaw")
    with pytest.raises(ValueError, match="non-zero"):
        fit_first_order_step(t, v, 0.5, 0, "x")
    with pytest.raises(ValueError, match="differ in length"):
        fit_first_order_step(t, v[:-1], 0.5, 40, "x")


def test_differenced_weighting_tightens_tau_on_rounded_positions() -> None:
    """Velocities differenced from 1 cm-rounded positions at 10 Hz (what the default source produces):
    the position-domain weighting (differenced=True) keeps τ much tighter than plain least squares."""
    gain, tau, delay, u = 0.01, 0.1, 0.02, 40

    def position_cm(t: np.ndarray) -> np.ndarray:
        s = np.maximum(t - delay, 0.0)
        return 100.0 * gain * u * (s - tau * -np.expm1(-s / tau))

    taus: dict[bool, list[float]] = {False: [], True: []}
    for seed in range(40):
        rng = np.random.default_rng(seed)
        tp = np.arange(-0.5, 2.0, 0.1) + rng.uniform(0, 0.1) + rng.uniform(0, 0.01, 25)  # packet jitter
        p = np.round(position_cm(tp) + rng.uniform(0, 100))
        t, v = 0.5 * (tp[1:] + tp[:-1]), np.diff(p) / np.diff(tp) / 100.0
        for differenced in (False, True):
            fit = fit_first_order_step(t, v, 0.0, u, "x", differenced=differenced)
            assert fit.gain == pytest.approx(gain, rel=0.05)
            taus[differenced].append(fit.tau_s)
    spread = {k: float(np.sqrt(np.mean((np.array(x) - tau) ** 2))) for k, x in taus.items()}
    assert spread[True] < 0.7 * spread[False], spread
    assert max(abs(x / tau - 1.0) for x in taus[True]) < 0.5, taus[True]


# ---------------------------------------------------------------------------- state velocity source
class _FakeTello:
    def __init__(self) -> None:
        self.state: dict[str, Any] = {}

    def get_current_state(self) -> dict[str, Any]:
        return self.state


def _packet(tello: _FakeTello, clock: list[float], t: float, **fields: float) -> None:
    clock[0] = t
    base = {"x": 0, "y": 0, "z": 80, "yaw": 0, "vgx": 0, "vgy": 0, "vgz": 0}
    tello.state = base | fields  # a new dict per packet, like djitellopy


def test_state_source_differences_rotates_and_unwraps(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [0.0]
    monkeypatch.setattr(ident, "time", SimpleNamespace(monotonic=lambda: clock[0], sleep=time.sleep))
    tello = _FakeTello()
    driver = SimpleNamespace(current_state=tello.get_current_state)
    # heading 90° clockwise (facing the state's +y = right): +y motion is body forward (x)
    sx, sy = state_velocity_source(driver, "x"), state_velocity_source(driver, "y")
    _packet(tello, clock, 10.0, yaw=90)
    assert math.isnan(sx()[0]) and math.isnan(sy()[0])  # one packet: no difference yet
    _packet(tello, clock, 10.1, yaw=90, y=3, x=-1)
    stamp, vx = sx()
    assert stamp == pytest.approx(10.05) and vx == pytest.approx(0.30)  # m/s
    assert sy()[1] == pytest.approx(-0.10)  # state −x (backwards at takeoff) is body right at 90° cw
    assert sx() == (stamp, vx)  # no new packet: same sample
    # yaw through ±180: 178 → −179 is +3° clockwise in 0.1 s → −30°/s counter-clockwise
    syaw = state_velocity_source(driver, "yaw")
    _packet(tello, clock, 20.0, yaw=178)
    syaw()
    _packet(tello, clock, 20.1, yaw=-179)
    assert syaw()[1] == pytest.approx(-math.radians(30.0))
    # vg fields: dm/s, stamped at arrival; vgz positive down (a real Tello climbing reads vgz −4)
    svz = state_velocity_source(driver, "z", field="vg")
    _packet(tello, clock, 30.0, vgz=-4)
    assert svz() == (30.0, pytest.approx(0.4))
    with pytest.raises(ValueError, match="no yaw-rate field"):
        state_velocity_source(driver, "yaw", field="vg")
    with pytest.raises(ValueError, match="unknown axis"):
        state_velocity_source(driver, "roll")


# ----------------------------------------------------------------------------------- gains and YAML
def test_rc_gains_and_saved_yaml(tmp_path: Any) -> None:
    fits = {
        "x": StepFit("x", 0.0098, 0.11, 0.02, 0.03, 50),
        "y": StepFit("y", 0.0102, 0.09, 0.01, 0.03, 50),
        "z": StepFit("z", 0.0110, 0.12, 0.00, 0.04, 50),
        "yaw": StepFit("yaw", 0.0170, 0.10, 0.03, 0.06, 50),
    }
    g = fits_to_rc_gains(fits)
    assert (g.xy, g.z, g.yaw) == pytest.approx((0.0100, 0.0110, 0.0170))
    partial = fits_to_rc_gains({"yaw": fits["yaw"]}, base=RcGains(0.02, 0.03, 0.04))
    assert (partial.xy, partial.z, partial.yaw) == pytest.approx((0.02, 0.03, 0.0170))
    with pytest.raises(ValueError, match="xy"):
        fits_to_rc_gains({"z": fits["z"], "yaw": fits["yaw"]})
    with pytest.raises(ValueError, match=r"\['z'\] moved against the command"):
        fits_to_rc_gains(fits | {"z": StepFit("z", -0.01, 0.1, 0.0, 0.03, 50)})
    path = tmp_path / "tello_127.0.0.5.yaml"
    save_identification(path, fits, "127.0.0.5")
    doc = yaml.safe_load(path.read_text())
    RcGainsSpec(**doc["rc_gains"])  # loadable as a mission's drones.N.rc_gains
    assert doc["rc_gains"] == pytest.approx({"xy": 0.0100, "z": 0.0110, "yaw": 0.0170})
    assert doc["drone_host"] == "127.0.0.5" and doc["date"].endswith("Z")
    assert doc["tau_s"]["z"] == 0.12 and doc["delay_s"]["yaw"] == 0.03 and doc["rms_residual"]["x"] == 0.03


# --------------------------------------------------------------------------------- emulator, end to end
TRUTH = {"x": 0.01, "y": 0.01, "z": 0.01, "yaw": math.radians(1.0)}  # per rc unit: 1 cm/s, 1 deg/s
TRUE_TAU_S = 0.1


@pytest.mark.system  # long (emulator or fuzzing): the system tier
def test_identify_against_the_emulator() -> None:
    pytest.importorskip("av")
    from flightstack.drivers.tello.driver import TelloDriver
    from tests.test_tello_driver import config, make_emulator

    with make_emulator("127.0.0.5", tau_s=TRUE_TAU_S) as emu:
        d = TelloDriver(config(emu))
        try:
            d.connect()
            with pytest.raises(RuntimeError, match="takeoff"):
                identify(d)  # on the ground: refused before any rc is sent
            d.takeoff()
            start_cm, n_rc = emu.position_cm, len(emu.rc_history)
            t0 = time.monotonic()
            # rc 60 rather than the default 40: the state rounds positions to 1 cm and yaw to 1°, and a
            # larger step has more counts per 0.1 s packet; in a Monte Carlo of this pipeline the τ error
            # passes 50 % in ~0.7 % of axes at rc 40 and in none of 300 at rc 60 (drivers/tello/identify.py).
            fits = identify(d, ("x", "y", "z", "yaw"), rc_amplitude=60, duration_s=1.5)
            print(f"identify: {time.monotonic() - t0:.1f} s (8 steps of 0.5 + 1.5 + 0.5 s, plus the fits)")
            # every step went out on the right rc slot with the right sign, forward then back
            sent = {rc for _, rc in list(emu.rc_history)[n_rc:]}
            for rc in [(0, 60, 0, 0), (0, -60, 0, 0), (-60, 0, 0, 0), (60, 0, 0, 0)]:
                assert rc in sent
            for rc in [(0, 0, 60, 0), (0, 0, -60, 0), (0, 0, 0, -60), (0, 0, 0, 60)]:
                assert rc in sent
            assert emu.rc_history[-1][1] == (0, 0, 0, 0) and emu.flying and not emu.landed_by_timeout
            # forward then back: back near the start (cm) and heading (deg)
            assert np.allclose(emu.position_cm, start_cm, atol=5.0) and abs(emu.yaw_deg) < 5.0
            report = {a: (round(f.gain, 5), round(f.tau_s, 3), round(f.delay_s, 3)) for a, f in fits.items()}
            for axis, fit in fits.items():
                assert fit.gain == pytest.approx(TRUTH[axis], rel=0.10), report
                # τ only within 50 %: the state stream comes at 10 Hz, one sample per τ, so the rise
                # (≈ 3τ) is seen in ~3 samples, each a 0.1 s mean of 1 cm (1°) rounded positions (±10 cm/s
                # on a 60 cm/s step), τ and the dead time trade off against each other on so few points,
                # and the step's phase against the packet clock is random.
                assert fit.tau_s == pytest.approx(TRUE_TAU_S, rel=0.50), report
                assert 0.0 <= fit.delay_s < 0.1, report
                assert fit.samples >= 30
            print("identified (gain per unit, tau s, delay s):", report)
            d.land()
            assert not emu.flying
        finally:
            d.close()


def test_cli_refuses_to_fly_without_confirmation(tmp_path) -> None:
    """`flightstack calibrate drone` takes off: without --yes and without a terminal it must refuse,
    before any network traffic, and write nothing."""
    import subprocess
    import sys

    out = tmp_path / "gains.yaml"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "flightstack.cli.app",
            "calibrate",
            "drone",
            "--ip",
            "127.0.0.9",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert r.returncode == 2 and "--yes" in r.stderr
    assert not out.exists()
