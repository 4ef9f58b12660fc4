"""Rig-side schema sections of the simulated lab: the ground robot, the rc gains a driver
believes (per drone) and the simulated physics (`sim:`). Used by flightstack.config.mission."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import Field

from flightstack.config.types import Distance, Seconds, Speed, YawRate
from flightstack.config.types import Strict as _Strict


class RobotSpec(_Strict):
    """The ground robot (the rig's `robot:`). `kinematics` and `min_turn_radius_m` are the robot's on every
    rig (flightstack.paper.target_law.KINEMATICS: `omni`, `differential`, `ackermann`; unset: `omni` on the
    ideal rig, the paper's idealised target, else `differential`: `Mission.robot_kinematics`);
    `min_turn_radius_m` (m) is required for, and only for, `ackermann`. The rest is the simulated robot's
    (sim_lab only)."""

    kinematics: Literal["omni", "differential", "ackermann"] | None = None
    min_turn_radius_m: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] | None = None
    time_constant_s: Seconds = 0.2
    max_speed_mps: Speed = 0.5
    max_yaw_rate: YawRate = 1.0
    command_timeout_s: Seconds = 3.0


RcGain = Annotated[float, Field(gt=0, le=1.0, allow_inf_nan=False)]
"""Velocity per rc unit; rc commands go to ±100 units, so more than 1 per unit would be 100 m/s."""


class RcGainsSpec(_Strict):
    """Velocity per Tello rc unit (m/s, rad/s)."""

    xy: RcGain = 0.01
    z: RcGain = 0.01
    yaw: RcGain = 0.0175


class TelloSimSpec(_Strict):
    """Physics of the simulated Tellos (sim_lab).

    The rc gains here are the truth; drones.N.rc_gains are what the driver believes (its calibration)."""

    true_rc_gains: RcGainsSpec = RcGainsSpec()
    time_constant_s: Seconds = 0.25
    max_speed_xy: Speed = 1.0
    max_speed_z: Speed = 0.5
    max_yaw_rate: YawRate = 1.75
    takeoff_height_m: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 1.0  # m; Tello: 30 m
    battery_pct: Annotated[float, Field(ge=0, le=100)] = 90.0
    battery_drain_pct_per_s: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.12
    auto_land_s: Seconds = 15.0


class MocapSimSpec(_Strict):
    rate_hz: Annotated[float, Field(gt=0, le=10000, allow_inf_nan=False)] = 120.0  # cameras: ≤ 1 kHz
    noise_pos_m: Annotated[float, Field(ge=0, le=1.0, allow_inf_nan=False)] = 0.0005
    noise_yaw_rad: Annotated[float, Field(ge=0, le=math.pi, allow_inf_nan=False)] = 0.002
    dropout_prob: Annotated[float, Field(ge=0, lt=1)] = 0.0


class RenderSpec(_Strict):
    marker_radius_m: Distance = 0.03
    noise_std: Annotated[float, Field(ge=0, le=255, allow_inf_nan=False)] = 2.0  # 8-bit grey levels
    blur_px: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.0
    # where the noise is drawn: "markers" (around the painted markers, the same random numbers there,
    # the same extracted features as "full", faster) or "full" (every pixel: frames for a viewer)
    region: Literal["full", "markers"] = "markers"
    # "image": render each frame and extract the markers from it; "centres" (faster, changes results
    # within the measurement noise, docs/performance.md): no image, each marker's exact normalised centre
    # plus Gaussian noise of centre_noise_px pixels (the extractor's measured error on these frames)
    model: Literal["image", "centres"] = "image"
    centre_noise_px: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.02
    # what the cameras see around the target: "plain" (one grey) or "tiles" (a tiled, mottled floor fixed
    # in the world, sim_backend/scene/floor.py: video concealment is tested against structure); the
    # emulated lab's cameras read it too
    floor: Literal["plain", "tiles"] = "plain"


class SimSpec(_Strict):
    """Settings of the simulated lab (backend sim_lab)."""

    world_dt_s: Annotated[float, Field(gt=0, le=0.1)] = 0.005
    tello: TelloSimSpec = TelloSimSpec()
    mocap: MocapSimSpec = MocapSimSpec()
    render: RenderSpec = RenderSpec()
