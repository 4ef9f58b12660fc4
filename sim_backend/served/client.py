"""An agent process's view of the served simulated world (`flightstack world`): a hal.Backend over Zenoh.

The world is the clock master. Each tick k it sends this agent a `tick` (flightstack/comms/
world_messages.py) and waits for the agent's `cmd` of tick k. On this side:
- `RemoteClock.now()` is the time of the newest tick; `sleep_until(T)` sends the calls made since the
  last tick as this tick's `cmd`, then waits for the next tick, until its time reaches T.
- `RemoteDrone` queues hal.Drone calls for the world and reads the state of the newest tick.
- `RemoteCamera` and `RemotePoseSource` return what the newest tick carried.
A tick that does not come within `timeout_s` raises `WorldLostError` (the world died): the runner then
lands (queues `land`) and ends with the error recorded.

Ticks are decoded into validated `WorldTick`s (world_messages.py: a malformed tick is dropped and counted
in `_Link.dropped` by reason, as are ticks older than the newest, ticks whose time goes back or is not
k·dt, and ticks further ahead than the world can be: tick_gate.py), so the accessors below cannot fail
on any accepted tick; gaps (ticks the world went on without this agent) are counted in `_Link.gaps`.
Every cmd carries this process's session label (comms/identity.py): the world obeys the session that
said hello first for a drone, drops and reports a second one, and puts the label of the session it
serves on each tick (the attachment); a process that receives ticks served to another session refuses
them ("tick for another session"), never starts flying, and ends naming that session. Velocities are
saturated to what the world accepts (`world_messages.saturate_velocity`: beyond what a Tello can fly;
never reached by the agents' control).
A forged tick that is well formed and newer cannot be told from the world's here: who may publish on
the world keys is the transport's to authenticate (Zenoh mutual TLS and ACL).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh

from flightstack.comms.identity import UNLABELLED, sample_label, session_label
from flightstack.comms.wire import WORLD_CMD_ENCODING
from flightstack.hal import DroneState, Frame, StampedPose
from flightstack.paper.geometry import Pose
from flightstack.sim_backend.served import messages as wm
from flightstack.sim_backend.served.tick_gate import TickBounds, tick_refusal

if TYPE_CHECKING:
    from flightstack.config.mission import Mission
    from flightstack.runtime.rig import AgentSeat


TICK_FOR_ANOTHER = "tick for another session"


class WorldLostError(RuntimeError):
    """No tick from the served world within the timeout."""


def drone_state(tick: wm.WorldTick) -> DroneState:
    s = tick.state
    return DroneState(s.battery_pct, s.height_m, s.link_alive, s.flying, s.phase)


def camera_frame(tick: wm.WorldTick, image: np.ndarray | None) -> Frame | None:
    """The tick's camera sample; `image` is the one decoded with it (shape tick.frame.image_shape)."""
    f = tick.frame
    if f is None:
        return None
    return Frame(
        f.stamp,
        image if f.image_shape is not None else None,
        None if f.features is None else np.array(f.features, dtype=float),
    )


def body_pose(tick: wm.WorldTick, body: str) -> StampedPose | None:
    p = tick.poses.get(body)
    if p is None:
        return None
    return StampedPose(p[0], Pose.make(p[1:4], p[4]))


def truth_poses(tick: wm.WorldTick, drone_id: int) -> tuple[Pose, dict[int, Pose]]:
    tr = tick.truth
    return Pose.from_vector(np.array(tr.target)), {drone_id: Pose.from_vector(np.array(tr.drone))}


class _Link:
    """Receives this agent's ticks, sends its cmds; all state behind one condition."""

    def __init__(
        self,
        session: Any,
        prefix: str,
        mission: str,
        drone_id: int,
        timeout_s: float,
        bounds: TickBounds | None = None,
        label: str = UNLABELLED,
    ) -> None:
        """bounds: which ticks are possible (tick_gate.py; None: order only); label: this process's
        session label, put on every cmd (comms/identity.py)."""
        self.drone_id = drone_id
        self.timeout_s = timeout_s
        self.bounds = bounds
        self.label = label
        self._attachment = label.encode("ascii")
        self.served_to: str | None = None  # the session the world serves this drone to, when not us
        self._cond = threading.Condition()
        self._tick: wm.WorldTick | None = None
        self._ref_wall: float | None = None  # when the newest tick arrived (wall s)
        self._image: np.ndarray | None = None
        self._calls: list[wm.DroneCall] = []
        self._sent_k = -1
        self.dropped: Counter[str] = Counter()
        self.gaps: Counter[str] = Counter()  # "gaps": accepted ticks after a skip; "ticks skipped"
        # the world waits for every cmd: never drop one under congestion (a lost cmd stalls a whole tick)
        self._pub = session.declare_publisher(
            wm.cmd_key(prefix, mission, drone_id),
            encoding=zenoh.Encoding(WORLD_CMD_ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        self._sub = session.declare_subscriber(wm.tick_key(prefix, mission, drone_id), self._on_tick)

    def _on_tick(self, sample: Any) -> None:
        try:
            data = bytes(sample.payload.to_bytes())
        except Exception:
            with self._cond:
                self.dropped["bad sample"] += 1
            return
        self.receive(data, owner=None if sample.attachment is None else sample_label(sample))

    def receive(self, data: bytes, now: float | None = None, owner: str | None = None) -> str | None:
        """Decode one tick message received at wall time `now` (s, default time.monotonic()); keep it as
        the newest, or count why not (returned). owner: the session the world serves this drone to (the
        tick's attachment; None: not said): a tick served to another session is refused ("tick for
        another session"): this process is a second one for the drone. Never raises."""
        now = time.monotonic() if now is None else now
        if owner is not None and owner != self.label:
            with self._cond:
                self.served_to = owner
                self.dropped[TICK_FOR_ANOTHER] += 1
            return TICK_FOR_ANOTHER
        tick, image, reason = wm.decode_tick(data)
        with self._cond:
            if tick is not None:
                reason = tick_refusal(self._tick, tick, self.bounds, self._ref_wall, now)
            if tick is None or reason is not None:
                self.dropped[reason or "bad tick"] += 1
                return reason or "bad tick"
            if self._tick is not None and tick.k > self._tick.k + 1:
                self.gaps["gaps"] += 1
                self.gaps["ticks skipped"] += tick.k - self._tick.k - 1
            self._tick, self._image, self._ref_wall = tick, image, now
            self._cond.notify_all()
            return None

    def wait_first(self) -> wm.WorldTick:
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:  # hello until the world answers with a tick
            self.hello()
            with self._cond:
                if self._cond.wait_for(lambda: self._tick is not None, 0.2):
                    return self._tick  # type: ignore[return-value]
        with self._cond:
            if not self._cond.wait_for(lambda: self._tick is not None, self.timeout_s):
                if self.served_to is not None:
                    raise WorldLostError(
                        f"the served world flies drone {self.drone_id} for another session "
                        f"({self.served_to}), not this one ({self.label}): is a second `flightstack agent "
                        f"--id {self.drone_id}` running? This process flies nothing"
                    )
                refused = ", ".join(f"{r}: {n}" for r, n in sorted(self.dropped.items()))
                raise WorldLostError(
                    f"no tick from the served world within {self.timeout_s:g} s"
                    + (f" (ticks refused: {refused})" if refused else "")
                )
            assert self._tick is not None
            return self._tick

    def tick(self) -> wm.WorldTick:
        with self._cond:
            if self._tick is None:
                raise WorldLostError("not connected to the served world yet")
            return self._tick

    def image(self) -> np.ndarray | None:
        with self._cond:
            return self._image

    def call(self, call: wm.DroneCall) -> None:
        with self._cond:
            self._calls.append(call)

    def hello(self) -> None:
        """Tell the world we are subscribed (cmd of tick -1): it starts ticking when every agent has."""
        self._pub.put(wm.encode_cmd(wm.WorldCmd(-1, ())), attachment=self._attachment)

    def _put(self, k: int, calls: list[wm.DroneCall]) -> None:
        """Send `calls` as cmd(s) of tick k: one cmd, or several of wm.MAX_CALLS calls in order (a backlog
        after the world was lost); the world applies every cmd it receives, in order."""
        for i in range(0, max(len(calls), 1), wm.MAX_CALLS):
            cmd = wm.WorldCmd(k, tuple(calls[i : i + wm.MAX_CALLS]))
            self._pub.put(wm.encode_cmd(cmd), attachment=self._attachment)

    def send(self) -> None:
        """Send the calls made during the current tick as its cmd (once per tick)."""
        with self._cond:
            assert self._tick is not None
            k = self._tick.k
            if self._sent_k >= k:
                return
            calls, self._calls = self._calls, []
            self._sent_k = k
        self._put(k, calls)

    def step(self) -> None:
        """Send this tick's calls (if not yet sent), then wait for a newer tick."""
        self.send()
        with self._cond:
            k = self._sent_k

            def newer() -> bool:
                return self._tick is not None and self._tick.k > k

            if not self._cond.wait_for(newer, self.timeout_s):
                raise WorldLostError(f"no tick after {k} from the served world within {self.timeout_s:g} s")

    def flush(self) -> None:
        """Send the pending calls now (at the end of a run: the final land) without waiting."""
        with self._cond:
            if self._tick is None or not self._calls:
                return
            k = self._tick.k
            calls, self._calls = self._calls, []
        self._put(k, calls)

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
        return self.link.tick().t if self.lost_at is None else self.lost_at

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
        self.link.call(wm.DroneCall("connect"))

    def takeoff(self) -> None:
        self.link.call(wm.DroneCall("takeoff"))

    def land(self) -> None:
        self.link.call(wm.DroneCall("land"))

    def emergency_stop(self) -> None:
        self.link.call(wm.DroneCall("emergency_stop"))

    def send_body_velocity(self, V: np.ndarray) -> None:
        """V = [v_x, v_y, v_z, ω] (m/s, rad/s); non-finite parts sent as 0, saturated to a Tello's range."""
        self.link.call(wm.DroneCall(wm.VELOCITY_CALL, wm.saturate_velocity(V)))

    def state(self) -> DroneState:
        return drone_state(self.link.tick())

    @property
    def phase(self) -> str:
        return self.link.tick().state.phase

    def close(self) -> None:
        self.link.call(wm.DroneCall("close"))


class RemoteCamera:
    def __init__(self, link: _Link) -> None:
        self.link = link

    def latest(self) -> Frame | None:
        with self.link._cond:  # the tick and its image together
            return camera_frame(self.link.tick(), self.link.image())


class RemotePoseSource:
    def __init__(self, link: _Link) -> None:
        self.link = link

    def latest(self, body: str) -> StampedPose | None:
        return body_pose(self.link.tick(), body)


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
        bounds: TickBounds | None = None,
    ) -> None:
        """timeout_s: wait for the world's first tick (s); tick_timeout_s: for every later tick (s);
        bounds: which ticks the world can have sent (tick_gate.py)."""
        self.drone_id = drone_id
        self.link = _Link(session, prefix, mission, drone_id, timeout_s, bounds, session_label(session))
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
        return truth_poses(self.link.tick(), self.drone_id)

    def heartbeat(self) -> None:
        """The world watches its agents by their commands; no watchdog here."""

    def close(self) -> None:
        """Land (queued for the world); the link stays open so the landing can be followed."""
        self._drone.land()

    def disconnect(self) -> None:
        self.link.flush()
        self.link.close()

    def _own(self, drone_id: int) -> None:
        if drone_id != self.drone_id:
            raise KeyError(f"this agent process flies drone {self.drone_id}, not {drone_id}")


@contextlib.contextmanager
def agent_backend(mission: Mission, seat: AgentSeat) -> Iterator[RemoteBackend]:
    """The simulated rigs' agent backend (sim_backend/rigs/simulated.py): drone `seat.drone_id` of the
    world served over `seat.session`; the link is flushed and closed after the run (the run lands through
    close())."""
    z = mission.bus.zenoh
    if z is None or seat.session is None:
        raise ValueError("bus.kind: an agent of a simulated mission reaches the world over the zenoh bus")
    backend = RemoteBackend(
        seat.session,
        z.key_prefix,
        mission.name,
        seat.drone_id,
        timeout_s=z.start_timeout_s,
        tick_timeout_s=max(5.0, 2.0 * z.lockstep_timeout_s),
        bounds=TickBounds(mission.dt_s, z.lockstep_timeout_s),
    )
    try:
        yield backend
    finally:
        backend.disconnect()
