"""One drone identity: each drone's names come from one value built from its id, so every layer
that names a drone (the pose source's body, the lab file's motion-capture map, the bus's participant,
the emulated lab's device label) agrees by construction."""

from __future__ import annotations

import pytest

from flightstack.config.mission import load_mission
from flightstack.config.rig import emulated_hardware
from flightstack.hal import TARGET_BODY, DroneIdentity


def test_each_drone_has_one_identity_in_drone_order() -> None:
    m = load_mission("paper_experiment", rig="lab-sim")
    assert [who.id for who in m.identities()] == m.drone_ids() == [d.id for d in m.drones]
    who = m.identity(m.drone_ids()[-1])
    assert (who.name, who.label, who.agent) == (f"drone{who.id}", f"tello{who.id}", str(who.id))
    with pytest.raises(KeyError, match="not one of the mission's drones"):
        m.identity(99)


def test_the_emulated_lab_file_maps_exactly_the_identities_bodies() -> None:
    hw = emulated_hardware([3, 7])
    assert set(hw["mocap"]["bodies"]) == {DroneIdentity(3).name, DroneIdentity(7).name, TARGET_BODY}
    m = load_mission("paper_experiment", rig="emulated-lab")
    assert m.hardware is not None
    assert {who.name for who in m.identities()} | {TARGET_BODY} == set(m.hardware.mocap.bodies)
