"""Device and physics settings are derived from the schema by field name (flightstack.config.derive)."""

from __future__ import annotations

import dataclasses

import pytest

from flightstack.config.derive import derive
from flightstack.config.mission import load_mission
from flightstack.config.sim_specs import MocapSimSpec, TelloSimSpec
from flightstack.config.types import Strict
from flightstack.drivers.lab.hardware import mocap_config, scamper_config, tello_config
from flightstack.sim_backend.lab import MocapParams, TelloParams


@dataclasses.dataclass
class _Two:
    a: float = 0.0
    b: float = 1.0


class _Section(Strict):
    a: float = 2.0
    c: float = 3.0


def test_a_section_field_without_counterpart_is_an_error() -> None:
    with pytest.raises(TypeError, match=r"_Section.c has no field 'c' in _Two"):
        derive(_Two, _Section())
    assert derive(_Two, _Section(), skip={"c"}) == _Two(a=2.0, b=1.0)
    assert derive(_Two, _Section(), rename={"c": "b"}) == _Two(a=2.0, b=3.0)
    with pytest.raises(TypeError, match="no field"):
        derive(_Two, _Section(), skip={"c"}, z=1.0)


def test_sim_params_carry_every_schema_value() -> None:
    spec = TelloSimSpec(time_constant_s=0.4, auto_land_s=9.0, battery_pct=55.0)
    p = derive(TelloParams, spec, skip={"true_rc_gains"})
    assert (p.time_constant_s, p.auto_land_s, p.battery_pct) == (0.4, 9.0, 55.0)
    m = derive(MocapParams, MocapSimSpec(rate_hz=60.0, dropout_prob=0.2))
    assert (m.rate_hz, m.dropout_prob) == (60.0, 0.2)


def test_driver_configs_from_the_lab_file() -> None:
    mission = load_mission("paper_experiment", rig="lab", check_files=False)
    hw = mission.hardware
    assert hw is not None
    for d in hw.drones:
        cfg = tello_config(mission, d.id)
        assert cfg.host == d.ip and cfg.control_port == d.control_port
        assert (cfg.loop_hover_s, cfg.loop_land_s, cfg.keepalive_s) == (
            d.loop_hover_s,
            d.loop_land_s,
            d.keepalive_s,
        )
        assert cfg.state_port == hw.state_port
        assert cfg.min_battery_pct == mission.safety.min_battery_takeoff
    mc = mocap_config(mission)
    assert (mc.system, mc.stale_after_s, mc.max_tilt_rad) == (
        hw.mocap.system,
        hw.mocap.stale_after_s,
        hw.mocap.max_tilt_rad,
    )
    sc = scamper_config(mission)
    assert hw.target is not None and sc is not None
    assert (sc.url, sc.stream_hz) == (hw.target.url, hw.target.stream_hz)
