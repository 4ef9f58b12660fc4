"""`--viewer foxglove[:PORT]` (`--viewer-host ADDR`): the flight served live over Foxglove's WebSocket
protocol (flightstack.viewer.foxglove_server, whose caps bound what clients cost the flight), on loopback
unless `--viewer-host` names another address, with the topics and typed messages of the run's MCAP
(flightstack.recording.mcap_writer), so one Foxglove layout opens both (docs/logs.md).

The control tick only copies its newest row, at most LIVE_RATE_HZ times per second of wall time, into a
bounded queue (QUEUE_TICKS; a full queue drops the row and counts it in `dropped`), with, on rigs with
image cameras, the agents' newest frames at most camera_frames.IMAGE_HZ per drone and second of mission
time (as the recording takes them: flightstack.runtime.camera_tap); a thread encodes (JPEG) and publishes
them, an image only while some client subscribes to its camera's topic (advertised with its first frame).
e_c and e_e are derived there from the poses and the fleet's desired poses, as the recording derives them
at the end. A client that connects late sees the flight from then on (the scene is sent again every
mcap_writer.SCENE_PERIOD_S).
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import queue
import socket
import threading
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from flightstack.recording.camera_frames import IMAGE_HZ, CameraFrame, encode_jpeg
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording
from flightstack.runtime.camera_tap import FrameKeeper, has_image_cameras, keep_frames, release_frames
from flightstack.viewer.foxglove_server import Topic

if TYPE_CHECKING:
    from flightstack.config.mission import Mission
    from flightstack.runtime.fleet import Fleet

_log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's default WebSocket port."""
LOOPBACK = "127.0.0.1"
"""Where the view listens unless `--viewer-host` says otherwise."""
LIVE_RATE_HZ = 30.0
"""Ticks published per second of wall time (the newest one each time)."""
QUEUE_TICKS = 64
"""Rows waiting for the publishing thread beyond which new ones are dropped (counted)."""
FINISH_TIMEOUT_S = 5.0
"""How long `finish` waits for the publishing thread (s)."""

_Image = tuple[int, float, bool, "int | None", np.ndarray]  # drone, stamp (s), damaged, since_loss, image
_Item = tuple[str, list[int], np.ndarray, dict[str, np.ndarray], list[Mapping[str, Any]], list[_Image]]


class FoxgloveTap:
    """A runtime.taps.TickTap serving the flight live (module docstring); `finish` stops the server.
    mission: the flight's (its frame tree, scene and cameras: mcap_scene.Scene); None: no scene, no images."""

    def __init__(
        self,
        port: int = DEFAULT_PORT,
        host: str = LOOPBACK,
        name: str = "flightstack",
        mission: Mission | None = None,
    ) -> None:
        from flightstack.recording.mcap_scene import Scene
        from flightstack.recording.mcap_writer import RunChannels
        from flightstack.viewer.foxglove_server import FoxgloveServer

        self.server = FoxgloveServer(host, port, name)
        self.port = self.server.port
        self.host = host
        self.channels = RunChannels(self.server.topic, None if mission is None else Scene.of(mission))
        self.images = mission is not None and has_image_cameras(mission)
        self.frames_sent = 0  # camera frames encoded and published
        self.frames_unwatched = 0  # camera frames due while no client subscribed to their topic
        self._agents: list[Any] = []
        self._keepers: dict[int, FrameKeeper] = {}
        self._next_image: dict[int, float] = {}
        self.dropped = 0
        self.published = 0
        self._queue: queue.Queue[_Item | None] = queue.Queue(maxsize=QUEUE_TICKS)
        self._mode = ""
        self._ids: list[int] = []
        self._g_d = np.zeros((0, 4))
        self._last = -np.inf
        self._events = 0
        self._thread = threading.Thread(target=self._work, name="flightstack-foxglove", daemon=True)
        self._thread.start()

    def describe(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port} (Foxglove or Lichtblick: Open connection, Foxglove WebSocket)"

    # ---- runtime.taps.TickTap ------------------------------------------------------------------------
    def start(self, f: Fleet, rec: Recording) -> None:
        self._mode, self._ids = rec.mode, list(rec.drone_ids)
        self._g_d = np.asarray(f.g_d, dtype=float).reshape(len(self._ids), 4)
        self._last, self._events = -np.inf, 0
        if self.images:
            self._agents = list(f.agents)
            self._keepers = keep_frames(self._agents)
            self._next_image = dict.fromkeys(self._keepers, -np.inf)

    def on_tick(self, f: Fleet, rec: Recording, k_end: int) -> None:
        now = time.monotonic()
        if k_end <= 0 or now - self._last < 1.0 / LIVE_RATE_HZ:
            return
        self._last = now
        row = {name: np.array(getattr(rec, name)[k_end - 1 : k_end]) for name in ARRAY_FIELDS}
        self._put(rec, row)

    def close(self, rec: Recording) -> None:
        release_frames(self._agents, self._keepers)
        self._agents, self._keepers = [], {}
        k = rec.ticks_done
        row = {name: np.array(getattr(rec, name)[k - 1 : k]) for name in ARRAY_FIELDS} if k else {}
        self._put(rec, row)

    def _frames(self) -> list[_Image]:
        """The agents' newest frames that are due (IMAGE_HZ per drone, mission time), their images by
        reference (as flightstack.recording.camera_frames takes them)."""
        out: list[_Image] = []
        for i, keeper in self._keepers.items():
            fr = keeper.last
            if fr is None or fr.image is None or fr.stamp < self._next_image[i]:
                continue
            self._next_image[i] = fr.stamp + 1.0 / IMAGE_HZ
            out.append((i, float(fr.stamp), bool(fr.damaged), fr.since_loss, fr.image))
        return out

    def _put(self, rec: Recording, row: dict[str, np.ndarray]) -> None:
        events: list[Mapping[str, Any]] = list(rec.events[self._events :])
        self._events += len(events)
        try:
            self._queue.put_nowait((self._mode, self._ids, self._g_d, row, events, self._frames()))
        except queue.Full:
            self.dropped += 1

    # ---- the publishing thread ------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                self._publish(*item)
            except Exception:  # a viewer's fault never reaches the flight
                _log.exception("foxglove live view: a row was not published")

    def _publish(
        self,
        mode: str,
        ids: list[int],
        g_d: np.ndarray,
        row: dict[str, np.ndarray],
        events: Sequence[Mapping[str, Any]],
        images: Sequence[_Image],
    ) -> None:
        if row:
            rec = Recording.from_columns(mode, ids, row)
            rec.fill_true_errors(g_d)
            self.channels.ticks(mode, ids, {name: getattr(rec, name) for name in ARRAY_FIELDS})
            self.published += 1
        if events:
            self.channels.events(mode, list(events))
        frames = []
        for i, t, damaged, since, img in images:
            channel = self.channels.image_channel(mode, i)  # advertised with its first frame
            if isinstance(channel, Topic) and not channel.subscribed():
                self.frames_unwatched += 1  # nobody watches it: not encoded
                continue
            frames.append(CameraFrame(i, t, damaged, since, encode_jpeg(img)))
        if frames:
            self.channels.frames(mode, frames)
            self.frames_sent += len(frames)

    def finish(self) -> None:
        """Publish what is queued (≤ FINISH_TIMEOUT_S), then stop the server (logging what clients did
        wrong that was not said yet)."""
        with contextlib.suppress(queue.Full):
            self._queue.put(None, timeout=FINISH_TIMEOUT_S)
        self._thread.join(timeout=FINISH_TIMEOUT_S)
        self.server.stop()


def foxglove_port(spec: str) -> int | None:
    """The port of a `--viewer foxglove[:PORT]` value; None for any other viewer."""
    if spec != "foxglove" and not spec.startswith("foxglove:"):
        return None
    text = spec.partition(":")[2].strip()
    return DEFAULT_PORT if not text else int(text)


def host_problem(text: str) -> str | None:
    """Why `--viewer-host` cannot serve the view: not an IP address, or not one of this machine's (it
    cannot be bound); None when it can."""
    try:
        addr = ipaddress.ip_address(text.strip("[]"))
    except ValueError:
        return f"{text!r} is not an IP address (e.g. 192.168.1.20 or ::; a host name is not accepted)"
    family = socket.AF_INET6 if addr.version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((str(addr), 0))
    except OSError as exc:
        return f"{addr} is not an address of this machine ({exc.strerror or exc})"
    return None


def is_loopback(host: str) -> bool:
    """Whether `host` (an IP address) reaches only this machine."""
    return ipaddress.ip_address(host.strip("[]")).is_loopback


__all__ = [
    "DEFAULT_PORT",
    "LIVE_RATE_HZ",
    "LOOPBACK",
    "QUEUE_TICKS",
    "FoxgloveTap",
    "foxglove_port",
    "host_problem",
    "is_loopback",
]
