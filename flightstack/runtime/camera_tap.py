"""The frames an agent's camera published to it: `FrameKeeper` remembers each agent's last one for the
observers of a flight (runtime.taps), and `CameraTap` records them into the run directory
(flightstack.recording.camera_frames) at most IMAGE_HZ per drone and second of mission time.

Why a keeper: an observer must see the frame the agent itself measured. Asking the camera again
(`backend.camera(i).latest()`) would, on the simulated lab, render a new image with the simulation's random
generator and change the flight it shows (sim_backend/lab.py, RenderedCamera.latest). Keepers nest (the
live Rerun view keeps its own); each observer removes exactly its own (`release_frames`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightstack.recording.camera_frames import IMAGE_HZ, FrameWriter, images_name

if TYPE_CHECKING:
    from flightstack.config.mission import Mission
    from flightstack.hal import Camera, Frame
    from flightstack.recording.timeseries import Recording
    from flightstack.runtime.fleet import Fleet

_log = logging.getLogger(__name__)


class FrameKeeper:
    """An agent's camera as the agent sees it, remembering the last frame it returned (hal.Camera)."""

    def __init__(self, inner: Camera) -> None:
        self.inner = inner
        self.last: Frame | None = None

    def latest(self) -> Frame | None:
        frame = self.inner.latest()
        self.last = frame
        return frame

    def __getattr__(self, name: str) -> Any:  # anything else the camera offers (stop, counters)
        return getattr(self.inner, name)


def has_image_cameras(mission: Mission) -> bool:
    """Whether the mission's cameras give images (a drone with a calibration file): not the ideal rig's."""
    return any(d.camera is not None and d.camera.calibration for d in mission.drones)


def keep_frames(agents: Iterable[Any]) -> dict[int, FrameKeeper]:
    """Wrap each agent's camera in a FrameKeeper; drone id → its keeper."""
    keepers = {}
    for a in agents:
        keeper = FrameKeeper(a.camera)
        a.camera = keeper
        keepers[a.cfg.drone_id] = keeper
    return keepers


def release_frames(agents: Iterable[Any], keepers: dict[int, FrameKeeper]) -> None:
    """Take exactly these keepers out of the agents' camera chains (others' keepers stay)."""
    mine = {id(k) for k in keepers.values()}
    for a in agents:
        outer: Any = None
        cam = a.camera
        while isinstance(cam, FrameKeeper):
            if id(cam) in mine:
                if outer is None:
                    a.camera = cam.inner
                else:
                    outer.inner = cam.inner
                break
            outer, cam = cam, cam.inner


class CameraTap:
    """A runtime.taps.TickTap writing each mode's camera frames to `out`/images_<mode>.jpgs (module
    docstring). On the control thread it only compares stamps and, when a frame is due, hands it to the
    writer's queue (flightstack.recording.camera_frames.FrameWriter: by reference, never waiting).
    `written`, `dropped`: frames per mode."""

    def __init__(self, out: Path, hz: float = IMAGE_HZ) -> None:
        self.out = Path(out)
        self.period = 1.0 / hz
        self.written: dict[str, int] = {}
        self.dropped: dict[str, int] = {}
        self._agents: list[Any] = []
        self._keepers: dict[int, FrameKeeper] = {}
        self._next: dict[int, float] = {}
        self._writer: FrameWriter | None = None
        self._mode = ""

    def start(self, f: Fleet, rec: Recording) -> None:
        self._mode = rec.mode
        self._agents = list(f.agents)
        self._keepers = keep_frames(self._agents)
        self._next = dict.fromkeys(self._keepers, -math.inf)
        self._writer = FrameWriter(self.out / images_name(rec.mode))

    def on_tick(self, f: Fleet, rec: Recording, k_end: int) -> None:
        w = self._writer
        if w is None:
            return
        for i, keeper in self._keepers.items():
            fr = keeper.last
            if fr is None or fr.image is None or fr.stamp < self._next[i]:
                continue
            self._next[i] = fr.stamp + self.period
            w.offer(i, float(fr.stamp), fr.image, bool(fr.damaged), fr.since_loss)

    def close(self, rec: Recording) -> None:
        release_frames(self._agents, self._keepers)
        self._agents, self._keepers = [], {}
        w, self._writer = self._writer, None
        if w is None:
            return
        w.close()
        self.written[self._mode] = w.counts["written"]
        self.dropped[self._mode] = w.counts["dropped"] + w.counts["over_size"] + w.counts["failed"]
        if self.dropped[self._mode]:
            _log.warning("camera frames of mode %s: %s", self._mode, dict(w.counts))


__all__ = ["CameraTap", "FrameKeeper", "has_image_cameras", "keep_frames", "release_frames"]
