"""Rig-side schema sections of the simulated lab (issue 17): the ground robot, the rc gains a driver
believes (per drone) and the simulated physics (`sim:`). Used by flightstack.config.mission."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from flightstack.config.types import NonNegative, Positive
from flightstack.config.types import Strict as _Strict


class RobotSpec(_Strict):
    """Simulated ground robot (sim_lab only)."""

    time_constant_s: Positive = 0.2
    max_speed_mps: Positive = 0.5
    max_yaw_rate: Positive = 1.0
    command_timeout_s: Positive = 3.0


class RcGainsSpec(_Strict):
    """Velocity per Tello rc unit (m/s, rad/s)."""

    xy: Positive = 0.01
    z: Positive = 0.01
    yaw: Positive = 0.0175


class TelloSimSpec(_Strict):
    """Physics of the simulated Tellos (sim_lab).

    The rc gains here are the truth; drones.N.rc_gains are what the driver believes (its calibration)."""

    true_rc_gains: RcGainsSpec = RcGainsSpec()
    time_constant_s: Positive = 0.25
    latency_s: NonNegative = 0.05
    max_speed_xy: Positive = 1.0
    max_speed_z: Positive = 0.5
    max_yaw_rate: Positive = 1.75
    takeoff_height_m: Positive = 1.0
    battery_pct: Annotated[float, Field(ge=0, le=100)] = 90.0
    battery_drain_pct_per_s: NonNegative = 0.12
    auto_land_s: Positive = 15.0


class MocapSimSpec(_Strict):
    rate_hz: Positive = 120.0
    noise_pos_m: NonNegative = 0.0005
    noise_yaw_rad: NonNegative = 0.002
    dropout_prob: Annotated[float, Field(ge=0, lt=1)] = 0.0


class RenderSpec(_Strict):
    marker_radius_m: Positive = 0.03
    noise_std: NonNegative = 2.0
    blur_px: NonNegative = 0.0


class SimSpec(_Strict):
    """Settings of the simulated lab (backend sim_lab)."""

    world_dt_s: Annotated[float, Field(gt=0, le=0.1)] = 0.005
    tello: TelloSimSpec = TelloSimSpec()
    mocap: MocapSimSpec = MocapSimSpec()
    render: RenderSpec = RenderSpec()
