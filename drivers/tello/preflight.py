"""Preflight checks of one connected Tello (`TelloDriver.preflight()`, `flightstack preflight`).

The functions take what they read of the driver (`PreflightTarget`): its latest telemetry, and `wifi?`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from flightstack.drivers.tello.config import PreflightCheck, TelloConfig, parse_int_reply, sdk3_fix
from flightstack.drivers.tello.state import PLAUSIBLE
from flightstack.drivers.tello.video_settings import SettingOutcome, outcomes_of
from flightstack.hal import FlightPhase


class PreflightTarget(Protocol):
    """What the checks read of a connected Tello driver (drivers/tello/driver.py's `TelloDriver`)."""

    @property
    def cfg(self) -> TelloConfig: ...

    @property
    def sdk_version(self) -> str | None: ...

    @property
    def serial(self) -> str | None: ...

    @property
    def phase(self) -> FlightPhase: ...

    @property
    def video_outcomes(self) -> tuple[SettingOutcome, ...]: ...

    def current_state(self) -> dict[str, float]: ...

    def link_alive(self) -> bool: ...

    def query(self, command: str, parse: Callable[[str], str | None], attempts: int = 2) -> str | None: ...


def tello_preflight(driver: PreflightTarget) -> list[PreflightCheck]:
    """Battery (a reading above 100 % FAILs: implausible), temperature, state stream, on the ground, SDK
    version and serial, the lab file's SDK 3.0 video settings, Wi-Fi signal."""
    st, cfg = driver.current_state(), driver.cfg
    bat, temp = st.get("bat"), st.get("temph")
    checks = [
        battery_check(bat, cfg.min_battery_pct),
        PreflightCheck(
            "temperature",
            temp is not None and temp <= cfg.max_temperature_c,
            f"{temp:.0f} °C (max {cfg.max_temperature_c:.0f} °C)" if temp is not None else "not reported",
        ),
    ]
    alive = driver.link_alive()
    checks.append(PreflightCheck("state stream", alive, "alive" if alive else "silent"))
    ph = driver.phase
    checks.append(
        PreflightCheck("on the ground", ph is FlightPhase.GROUND, f"phase {ph.value}, h {st.get('h')} cm")
    )
    checks.append(sdk_check(driver))
    checks += video_checks(driver)
    snr = driver.query("wifi?", parse_int_reply)
    checks.append(
        PreflightCheck(
            "wifi signal",
            snr is not None and float(snr) >= cfg.min_wifi_snr,
            f"SNR {snr} (min {cfg.min_wifi_snr:.0f})" if snr is not None else "`wifi?` not answered",
            warn=True,
        )
    )
    return checks


def battery_check(bat: float | None, min_pct: float) -> PreflightCheck:
    """FAIL below `min_pct` (%), when not reported, and above the plausible 100 %: such a reading proves
    no charge (drivers/tello/state.py flags it and the driver uses it as sent)."""
    if bat is None:
        return PreflightCheck("battery", False, "not reported")
    highest = PLAUSIBLE["bat"][1]
    detail = f"{bat:.0f} % (min {min_pct:.0f} %)"
    if bat > highest:
        detail += f": above {highest:.0f} %, implausible"
    return PreflightCheck("battery", min_pct <= bat <= highest, detail)


def sdk_check(driver: PreflightTarget) -> PreflightCheck:
    """FAIL when the mission needs SDK 3.0 features that the firmware lacks, in one line naming the
    version, the features and the fix (a downward camera: a Tello EDU on SDK 3.0, DOWNWARD_FIX)."""
    sdk, sn, need = driver.sdk_version, driver.serial or "serial unknown", driver.cfg.sdk3_features
    if sdk is None:
        ok = not need
        detail = f"`sdk?` not answered (SDK 1.3/2.0 firmware?), {sn}"
    else:
        ok = not need or float(sdk) >= 3.0
        detail = f"SDK {sdk}, serial {sn}"
    if not ok:
        fix = sdk3_fix(driver.cfg.downward_camera)
        detail += f"; this mission needs SDK 3.0 for {', '.join(need)}: {fix}"
    return PreflightCheck("firmware", ok, detail)


def video_checks(driver: PreflightTarget) -> list[PreflightCheck]:
    """One check per SDK 3.0 video setting of the lab file: FAIL unless the drone answered `ok` at connect
    (the line names the key, the drone, its reply and the fix); none when the lab file sets none."""
    host = driver.cfg.host
    return [
        PreflightCheck(
            f"video {o.setting.key.rsplit('.', 1)[-1]}",
            o.ok,
            f"`{o.setting.command}` confirmed (ok)" if o.ok else o.refusal(host),
        )
        for o in outcomes_of(driver.cfg, driver.video_outcomes)
    ]
