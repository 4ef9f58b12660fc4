"""The first pursuit tick on a loaded computer: the own motion-capture pose may be one frame late (stale)
just as pursuit begins. The runner seeds each agent with the pose it read at pursuit start
(`Agent.seed_own_pose`), so that tick is a dropout like any other (keep the pose, hover) instead of "no
pose for drone2" ending the mission with the drones in the air (seen in CI on the emulated lab)."""

from __future__ import annotations

from typing import Any

import pytest

from flightstack.hal import StampedPose
from tests.test_delay_compensation import _agent, _Scripted

pytestmark = pytest.mark.unit


class _Late(_Scripted):
    """The scripted world whose pose source has nothing fresh (None) while `stale`."""

    stale = False

    def latest(self, body: str | None = None) -> Any:
        if body is not None and self.stale:
            return None
        return super().latest(body)


def test_a_stale_pose_at_the_first_tick_is_a_dropout_once_seeded() -> None:
    world = _Late(delay_s=0.0)
    seed = world.latest("drone1")
    assert isinstance(seed, StampedPose)
    world.stale, world.t = True, 0.05
    agent = _agent(world, None)
    agent.seed_own_pose(seed)
    agent.sense_and_publish(world.t)  # no RuntimeError: the seeded pose is kept
    agent.fuse_control_act(world.t)
    assert agent.last is not None
    world.stale = False
    world.t = 0.1
    agent.sense_and_publish(world.t)
    agent.fuse_control_act(world.t)


def test_without_a_seed_the_same_tick_has_no_pose() -> None:
    """What the runner's seed prevents: an agent that never saw its own pose cannot fly a tick."""
    world = _Late(delay_s=0.0)
    world.stale, world.t = True, 0.05
    agent = _agent(world, None)
    with pytest.raises(RuntimeError, match="no pose for drone1"):
        agent.sense_and_publish(world.t)
