"""The robot's motion-capture pose for a Scamper driver on the rover emulator, where no motion capture runs.

ArduPilot Rover (and the emulator that follows it) enters GUIDED only with a position estimate, which the
driver gives it as VISION_POSITION_ESTIMATE from its `pose_source` (docs/drivers.md, "What ArduPilot
needs to move indoors"). These tests are about the link, not the estimate: the pose is where the robot
starts, stamped now.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from flightstack.hal import StampedPose
from flightstack.paper.geometry import Pose


def still_pose(x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> Callable[[], StampedPose]:
    """A pose source: lab (x, y, 0) m facing θ rad, stamped time.monotonic() at each call."""
    pose = Pose.make([x, y, 0.0], theta)
    return lambda: StampedPose(time.monotonic(), pose)
