"""The real lab's rig (backend `tello`): real Tellos, motion capture and the Scamper, described by the
mission's `hardware:` section, flown on the wall clock (drivers/lab/hardware.py assembles them)."""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

from flightstack.config.mission import Mission
from flightstack.config.rigs import LabFacts, need_cameras, need_square_law
from flightstack.recording.files import DeviceFiles
from flightstack.runtime.rig import AgentSeat, Preflight, Rig, RigDefaults

if TYPE_CHECKING:
    from flightstack.drivers.lab.hardware import HardwareBackend


class LabRig(LabFacts, RigDefaults):
    name = "tello"
    simulated = False
    starts_emulators = False
    has_devices = True
    flies_real_drones = True
    robot_is_device = True
    applies_network_profile = True

    def check(self, mission: Mission) -> None:
        """The devices (hardware:) for exactly the mission's drones, the square law, calibrated cameras, an
        authenticated bus, and the drones' measured response time when compensation is on."""
        if mission.hardware is None:
            raise ValueError("hardware: backend 'tello' needs a hardware section (drone IPs, mocap, robot)")
        hw_ids, ids = sorted(d.id for d in mission.hardware.drones), sorted(d.id for d in mission.drones)
        if hw_ids != ids:
            raise ValueError(f"hardware.drones: ids {hw_ids} must be exactly the drones' ids {ids}")
        need_square_law(mission, "real robots are driven on the 'square' law")
        need_cameras(mission, "on real hardware")
        z = mission.bus.zenoh
        if mission.bus.kind == "zenoh" and z is not None and z.security != "mtls":
            raise ValueError(
                "bus.zenoh.security: real drones fly only on an authenticated bus (mtls with the "
                "certificates of `flightstack certs`); plaintext is for simulations on one computer"
            )
        self.check_compensation(mission)

    def check_compensation(self, mission: Mission) -> None:
        """A real drone's response time is measured, never assumed."""
        if mission.compensation.enabled and mission.compensation.response_s is None:
            raise ValueError(
                "compensation.response_s: required on hardware (the drone's velocity response time "
                "constant, s; flightstack calibrate latency measures it)"
            )

    def drone_response_s(self, mission: Mission) -> float:
        """Unused on hardware (check_compensation requires compensation.response_s); the emulated Tello's."""
        from flightstack.config.compensation import EMULATED_TELLO_RESPONSE_S

        return EMULATED_TELLO_RESPONSE_S

    def build_backend(self, mission: Mission, devices: DeviceFiles | None) -> HardwareBackend:
        from flightstack.drivers.lab.hardware import build_tello

        return build_tello(mission, devices=devices)

    def agent_backend(
        self, mission: Mission, seat: AgentSeat
    ) -> contextlib.AbstractContextManager[HardwareBackend]:
        """This agent's Tello, the motion capture and, where the mission has one, the robot."""
        from flightstack.drivers.lab.hardware import agent_backend

        return agent_backend(mission, seat)

    def preflight(
        self,
        mission: Mission,
        drone_ids: list[int] | None = None,
        deadline_s: float = 9.0,
        camera: bool = True,
    ) -> Preflight:
        """Every check of drivers/lab/preflight.py, the devices in parallel."""
        from flightstack.drivers.lab.preflight import format_table, run_preflight

        rows = run_preflight(mission, deadline_s, camera, drone_ids)
        return Preflight(format_table(rows), not any(r.status == "FAIL" for r in rows))


RIG: Rig = LabRig()  # checked against the Rig protocol
