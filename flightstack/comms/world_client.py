"""An agent process's view of the served simulated world (`flightstack world`): a hal.Backend over Zenoh.

The world is the clock master. Each tick k it sends this agent a `tick` (flightstack/comms/
world_messages.py) and waits for the agent's `cmd` of tick k. On this side:
- `RemoteClock.now()` is the time of the newest tick; `sleep_until(T)` sends the calls made since the
  last tick as this tick's `cmd`, then waits for the next tick, until its time reaches T.
- `RemoteDrone` queues hal.Drone calls for the world and reads the state of the newest tick.
- `RemoteCamera` and `RemotePoseSource` return what the newest tick carried.
A tick that does not come within `timeout_s` raises `WorldLostError` (the world died): the runner then
lands (queues `land`) and ends with the error recorded.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter
from typing import Any

import numpy as np
import zenoh

from flightstack.comms import world_messages as wm
from flightstack.geometry import Pose
from flightstack.hal import DroneState, FlightPhase, Frame, StampedPose


class WorldLostError(RuntimeError):
    """No tick from the served world within the timeout."""


class _Link:
    """Receives this agent's ticks, sends its cmds; all state behind one condition."""

    def __init__(self, session: Any, prefix: str, mission: str, drone_id: int, timeout_s: float) -> None:
        self.drone_id = drone_id
        self.timeout_s = timeout_s
        self._cond = threading.Condition()
        self._tick: dict[str, Any] | None = None
        self._image: np.ndarray | None = None
        self._calls: list[list[Any]] = []
        self._sent_k = -1
        self.dropped: Counter[str] = Counter()
        # the world waits for every cmd: never drop one under congestion (a lost cmd stalls a whole tick)
        self._pub = session.declare_publisher(
            wm.cmd_key(prefix, mission, drone_id),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        self._sub = session.declare_subscriber(wm.tick_key(prefix, mission, drone_id), self._on_tick)

    def _on_tick(self, sample: Any) -> None:
        header, image, reason = wm.decode_tick(bytes(sample.payload.to_bytes()))
        with self._cond:
            if header is None:
                self.dropped[reason or "bad tick"] += 1
                return
            if self._tick is not None and header["k"] <= self._tick["k"]:
                self.dropped["old tick"] += 1
                return
            self._tick, self._image = header, image
            self._cond.notify_all()

    def wait_first(self) -> dict[str, Any]:
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:  # hello until the world answers with a tick
            self.hello()
            with self._cond:
                if self._cond.wait_for(lambda: self._tick is not None, 0.2):
                    return self._tick  # type: ignore[return-value]
        with self._cond:
            if not self._cond.wait_for(lambda: self._tick is not None, self.timeout_s):
                raise WorldLostError(f"no tick from the served world within {self.timeout_s:g} s")
            assert self._tick is not None
            return self._tick

    def tick(self) -> dict[str, Any]:
        with self._cond:
            if self._tick is None:
                raise WorldLostError("not connected to the served world yet")
            return self._tick

    def image(self) -> np.ndarray | None:
        with self._cond:
            return self._image

    def call(self, name: str, *args: Any) -> None:
        with self._cond:
            self._calls.append([name, *args])

    def hello(self) -> None:
        """Tell the world we are subscribed (cmd of tick -1): it starts ticking when every agent has."""
        self._pub.put(wm.pack({"v": wm.VERSION, "k": -1, "calls": []}))

    def send(self) -> None:
        """Send the calls made during the current tick as its cmd (once per tick)."""
        with self._cond:
            assert self._tick is not None
            k = self._tick["k"]
            if self._sent_k >= k:
                return
            calls, self._calls = self._calls, []
            self._sent_k = k
        self._pub.put(wm.pack({"v": wm.VERSION, "k": k, "calls": calls}))

    def step(self) -> None:
        """Send this tick's calls (if not yet sent), then wait for a newer tick."""
        self.send()
        with self._cond:
            k = self._sent_k

            def newer() -> bool:
                return self._tick is not None and self._tick["k"] > k

            if not self._cond.wait_for(newer, self.timeout_s):
                raise WorldLostError(f"no tick after {k} from the served world within {self.timeout_s:g} s")

    def flush(self) -> None:
        """Send the pending calls now (at the end of a run: the final land) without waiting."""
        with self._cond:
            if self._tick is None or not self._calls:
                return
            k = self._tick["k"]
            calls, self._calls = self._calls, []
        self._pub.put(wm.pack({"v": wm.VERSION, "k": k, "calls": calls}))

    def close(self) -> None:
        for obj in (self._sub, self._pub):
            with contextlib.suppress(Exception):  # the session may already be closed
                obj.undeclare()


class RemoteClock:
    """Mission time of the newest tick. Once the world is lost (WorldLostError raised once), time runs on
    locally: `sleep_until(t)` returns at once with now() = t, so the runner's bounded landing loops end
    (the world, if it still runs, lands a drone whose agent left)."""

    def __init__(self, link: _Link) -> None:
        self.link = link
        self.lost_at: float | None = None

    def now(self) -> float:
        return float(self.link.tick()["t"]) if self.lost_at is None else self.lost_at

    def sleep_until(self, t: float) -> None:
        """Send this tick's cmd (always, even when the world is already past t), then follow the ticks
        until their time reaches t."""
        if self.lost_at is not None:
            self.lost_at = max(self.lost_at, t)
            return
        self.link.send()
        try:
            while self.now() < t - 1e-12:
                self.link.step()
        except WorldLostError:
            self.lost_at = self.now()
            raise


class RemoteDrone:
    """hal.Drone whose calls are applied by the world at the end of the current tick."""

    def __init__(self, link: _Link) -> None:
        self.link = link

    def connect(self) -> None:
        self.link.call("connect")

    def takeoff(self) -> None:
        self.link.call("takeoff")

    def land(self) -> None:
        self.link.call("land")

    def emergency_stop(self) -> None:
        self.link.call("emergency_stop")

    def send_body_velocity(self, V: np.ndarray) -> None:
        v = [float(x) if np.isfinite(x) else 0.0 for x in np.asarray(V, dtype=float).reshape(4)]
        self.link.call("send_body_velocity", v)

    def state(self) -> DroneState:
        s = self.link.tick()["state"]
        phase = s.get("phase")
        known = phase if isinstance(phase, str) and phase in FlightPhase._value2member_map_ else ""
        return DroneState(
            float(s["battery_pct"]), float(s["height_m"]), bool(s["link_alive"]), bool(s["flying"]), known
        )

    @property
    def phase(self) -> str:
        return str(self.link.tick()["state"].get("phase", "ground"))

    def close(self) -> None:
        self.link.call("close")


class RemoteCamera:
    def __init__(self, link: _Link) -> None:
        self.link = link

    def latest(self) -> Frame | None:
        f = self.link.tick().get("frame")
        if not isinstance(f, dict):
            return None
        feats = f.get("features")
        return Frame(
            float(f["stamp"]),
            self.link.image() if f.get("image") is not None else None,
            None if feats is None else np.array(feats, dtype=float),
        )


class RemotePoseSource:
    def __init__(self, link: _Link) -> None:
        self.link = link

    def latest(self, body: str) -> StampedPose | None:
        p = self.link.tick().get("poses", {}).get(body)
        if p is None:
            return None
        return StampedPose(float(p[0]), Pose.make(p[1:4], p[4]))


class RemoteBackend:
    """hal.Backend of one agent process against `flightstack world`; `truth()` comes from the world."""

    simulated = True

    def __init__(
        self,
        session: Any,
        prefix: str,
        mission: str,
        drone_id: int,
        timeout_s: float = 10.0,
        tick_timeout_s: float = 5.0,
    ) -> None:
        """timeout_s: wait for the world's first tick (s); tick_timeout_s: for every later tick (s)."""
        self.drone_id = drone_id
        self.link = _Link(session, prefix, mission, drone_id, timeout_s)
        self.link.wait_first()
        self.link.timeout_s = tick_timeout_s  # after the first tick: how long a missing tick may take
        self.clock = RemoteClock(self.link)
        self._drone = RemoteDrone(self.link)
        self._camera = RemoteCamera(self.link)
        self._poses = RemotePoseSource(self.link)

    def drone(self, drone_id: int) -> RemoteDrone:
        self._own(drone_id)
        return self._drone

    def camera(self, drone_id: int) -> RemoteCamera:
        self._own(drone_id)
        return self._camera

    def pose_source(self) -> RemotePoseSource:
        return self._poses

    def target(self) -> None:
        return None  # the world drives the target

    def truth(self) -> tuple[Pose, dict[int, Pose]]:
        tr = self.link.tick()["truth"]
        return Pose.from_vector(np.array(tr["target"])), {
            self.drone_id: Pose.from_vector(np.array(tr["drone"]))
        }

    def close(self) -> None:
        """Land (queued for the world); the link stays open so the landing can be followed."""
        self._drone.land()

    def disconnect(self) -> None:
        self.link.flush()
        self.link.close()

    def _own(self, drone_id: int) -> None:
        if drone_id != self.drone_id:
            raise KeyError(f"this agent process flies drone {self.drone_id}, not {drone_id}")
