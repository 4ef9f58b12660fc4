"""`flightstack world MISSION`: the simulated world served over Zenoh to agent processes.

One process owns the simulated backend (sim_ideal or sim_lab) and is the clock master; each agent
process (`flightstack agent MISSION --id N`) sees its own drone, camera and motion-capture pose through
`flightstack.sim_backend.served.client.RemoteBackend`. Tick k (sim_backend/served/messages.py):
  1. the world sends every present agent its tick (state, poses, frame, truth) at mission time t_k;
  2. it waits (at most `bus.zenoh.lockstep_timeout_s`) until every present agent has sent its cmd of
     tick k — agents that left the bus (liveliness) are not waited for;
  3. it applies the received hal.Drone calls in order, drives the target (square law on sim_lab, as
     `phases.TargetDriver`), and advances the world to t_k + dt.
Cmds are decoded into validated `WorldCmd`s (world_messages.py: known calls with their exact arguments, a
body velocity within what a Tello can fly); a malformed cmd, one from an unknown sender or one of a tick
not yet published is dropped and counted by reason in `WorldSummary.dropped` (printed by `flightstack
world`), and `apply_cmd` cannot fail on an accepted one.
An agent that leaves (killed, or finished) has its drone landed by the world: the stand-in for a
ground-station safety net. (On hardware a Tello whose agent was killed holds its last rc command until
its own 15 s auto-land: docs/bus.md.) The world ends when every agent has
left, or after the mission's duration plus takeoff and landing allowances, and lands every drone.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from flightstack.comms.factory import make_bus
from flightstack.comms.identity import SECOND_SESSION, UNLABELLED, SessionBook, sample_label
from flightstack.comms.wire import WORLD_TICK_ENCODING
from flightstack.config.mission import Mission
from flightstack.events import Event
from flightstack.hal import TARGET_BODY, DroneIdentity, FlightPhase
from flightstack.runtime.phases import (
    LAND_TIMEOUT_S,
    TAKEOFF_TIMEOUT_S,
    TargetDriver,
    settle_virtual_landing,
)
from flightstack.runtime.rig import build_backend
from flightstack.sim_backend.served import messages as wm


@dataclass
class WorldSummary:
    ticks: int = 0
    sim_seconds: float = 0.0
    wall_seconds: float = 0.0
    events: list[Event] = field(default_factory=list)  # source world, mission clock (s)
    dropped: dict[str, int] = field(default_factory=dict)
    landed: dict[int, bool] = field(default_factory=dict)


def _pose_row(sp: Any) -> wm.PoseRow | None:
    if sp is None:
        return None
    return (float(sp.stamp), *(float(v) for v in sp.pose.as_vector()))  # type: ignore[return-value]


def _frame(frame: Any) -> tuple[wm.FrameHead | None, Any]:
    if frame is None:
        return None, None
    image = frame.image
    head = wm.FrameHead(
        float(frame.stamp),
        None if frame.features is None else tuple(float(x) for x in frame.features),
        None
        if image is None
        else (int(image.shape[0]), int(image.shape[1]))
        if image.ndim == 3
        else (int(image.shape[0]), int(image.shape[1]), 1),
    )
    return head, image


def apply_cmd(drone: Any, cmd: wm.WorldCmd) -> None:
    """Apply a decoded cmd's calls to the world's hal.Drone in order (`close` is the agent's own: the
    world keeps its drone). Every call of an accepted cmd is valid for a hal.Drone: a known name, and for
    send_body_velocity 4 finite numbers in range."""
    for call in cmd.calls:
        if call.name == wm.VELOCITY_CALL:
            assert call.velocity is not None
            drone.send_body_velocity(np.array(call.velocity, dtype=float))
        elif call.name != "close":
            getattr(drone, call.name)()


class WorldServer:
    def __init__(self, mission: Mission, log: Callable[[str], None] = print) -> None:
        if not mission.simulated:
            raise ValueError(f"backend {mission.backend!r} is real hardware: there is no world to serve")
        if mission.bus.kind != "zenoh" or mission.bus.zenoh is None:
            raise ValueError("bus.kind: serving the world needs the zenoh bus (bus.zenoh.endpoints)")
        self.mission = mission
        self.log = log
        self.z = mission.bus.zenoh
        self.ids = [d.id for d in mission.drones]
        self.backend = build_backend(mission)
        self.bus = make_bus(mission, "world", set())
        session = self.bus.session  # type: ignore[attr-defined]
        prefix, name = self.z.key_prefix, mission.name
        # agents wait for every tick: never drop one under congestion (a lost tick stalls the agent)
        self._pubs = {
            i: session.declare_publisher(
                wm.tick_key(prefix, name, i),
                encoding=zenoh.Encoding(WORLD_TICK_ENCODING),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH,
            )
            for i in self.ids
        }
        self._cond = threading.Condition()
        self._queued: dict[int, list[wm.WorldCmd]] = defaultdict(list)
        self._tick_k = -1  # the newest tick published: a cmd of a later tick is refused
        self._done_k: dict[int, int] = {i: -2 for i in self.ids}  # -1: hello (subscribed); k: cmd of tick k
        self.summary = WorldSummary()
        self._dropped = self.summary.dropped
        self._sessions = SessionBook("sends commands as")  # which session commands each drone
        self._n_reported = 0  # second sessions (self._sessions.events) reported by the main loop
        # the owner of a contested drone silent this long (wall s) has left: its drone lands
        self.owner_silent_s = 2.0 * self.z.lockstep_timeout_s + 1.0
        self._sub = session.declare_subscriber(wm.cmd_key(prefix, name, "*"), self._on_cmd)
        self._gone: set[int] = set()

    def _on_cmd(self, sample: Any) -> None:
        try:
            key, data = str(sample.key_expr), bytes(sample.payload.to_bytes())
        except Exception:
            with self._cond:
                self._dropped["bad sample"] = self._dropped.get("bad sample", 0) + 1
            return
        self.receive_cmd(key, data, sample_label(sample))

    def receive_cmd(self, key: str, data: bytes, session: str = UNLABELLED) -> str | None:
        """Decode one cmd that came on `key` (…/world/cmd/<id>, the id exactly as the agent's key writes
        it) from `session` (its label, comms/identity.py); queue it, or count why not (returned). The
        session of a drone's first accepted cmd (its hello) commands it; a second session's cmds are
        dropped ("second session") and reported by name. Never raises."""
        cmd, reason = wm.decode_cmd(data)
        last = key.rsplit("/", 1)[-1]
        ok = len(last) <= 9 and last.isascii() and last.isdigit() and str(int(last)) == last
        sender = int(last) if ok else -1
        now = time.monotonic()
        with self._cond:
            if cmd is not None and sender not in self._done_k:
                reason = "unknown sender"
            elif cmd is not None and not self._sessions.admit(sender, session, now):
                reason = SECOND_SESSION
            elif cmd is not None and cmd.k > self._tick_k:
                reason = "cmd of a future tick"
            if cmd is None or reason is not None:
                r = reason or "bad cmd"
                self._dropped[r] = self._dropped.get(r, 0) + 1
                return r
            self._sessions.claim(sender, session, now)
            self._queued[sender].append(cmd)
            self._done_k[sender] = max(self._done_k[sender], cmd.k)
            self._cond.notify_all()
            return None

    def _publish_ticks(self, k: int, t: float) -> None:
        g_w0, g_wis = self.backend.truth()
        poses = self.backend.pose_source()
        with self._cond:
            self._tick_k = k
        for i in self.ids:
            if i in self._gone:
                continue
            d = self.backend.drone(i)
            st = d.state()
            frame, image = _frame(self.backend.camera(i).latest())
            state = wm.TickState(
                float(st.battery_pct),
                float(st.height_m),
                bool(st.link_alive),
                bool(st.flying),
                str(st.phase),
            )
            rows = {
                b: row
                for b in (DroneIdentity(i).name, TARGET_BODY)
                if (row := _pose_row(poses.latest(b))) is not None
            }
            truth = wm.Truth(
                tuple(g_w0.as_vector().tolist()),
                tuple(g_wis[i].as_vector().tolist()),
            )
            tick = wm.make_tick(k, float(t), state, rows, truth, frame)
            with self._cond:
                owner = self._sessions.owner(i)  # the session served: a second one refuses the tick
            att = None if owner is None else owner.encode("ascii")
            self._pubs[i].put(wm.encode_tick(tick, image), attachment=att)

    def _wait_cmds(self, k: int, timeout_s: float | None = None) -> None:
        timeout_s = self.z.lockstep_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                alive = self.bus.alive()  # type: ignore[attr-defined]
                waiting = [i for i in self.ids if i in alive and i not in self._gone and self._done_k[i] < k]
                if not waiting:
                    return
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    detail = f"tick {k}: no cmd from agents {waiting} (went on)"
                    self.summary.events.append(
                        Event(k * self.mission.dt_s, None, "lockstep_timeout", detail, "world")
                    )
                    self.log(f"tick {k}: no cmd from agents {waiting} within {timeout_s:g} s")
                    return
                self._cond.wait(min(remaining, 0.01))  # also re-checks liveliness

    def _apply(self) -> None:
        with self._cond:
            queued = {i: q for i, q in self._queued.items() if q}
            self._queued = defaultdict(list)
        for i in self.ids:
            d = self.backend.drone(i)
            for cmd in queued.get(i, []):
                apply_cmd(d, cmd)

    def _report_sessions(self, t: float) -> None:
        """Log and record (mission time t, s) every second session heard since the last call."""
        with self._cond:
            news = self._sessions.events[self._n_reported :]
            self._n_reported += len(news)
        for e in news:
            self.summary.events.append(Event(t, e.sender, SECOND_SESSION, e.text, source="world"))
            self.log(e.text)

    def _handle_departures(self, t: float) -> None:
        """Land the drone of every agent that left: its token is gone, or its commanding session has
        been silent for `owner_silent_s` while a second session speaks for it (and holds the token)."""
        self._report_sessions(t)
        alive = self.bus.alive()  # type: ignore[attr-defined]
        now = time.monotonic()
        for i in self.ids:
            if i in self._gone:
                continue
            with self._cond:
                quiet = self._sessions.silent_for(i, now) > self.owner_silent_s
                silent = quiet and self._sessions.contested(i)
            if i not in alive or silent:
                self._gone.add(i)
                d = self.backend.drone(i)
                why = "its drone lands"
                if silent and i in alive:
                    why = f"its session is silent, a second session holds its token; {why}"
                self.summary.events.append(Event(t, i, "agent_left", why, source="world"))
                self.log(f"agent {i} left at t = {t:.3f} s: landing drone {i}")
                d.send_body_velocity(np.zeros(4))
                st = d.state()
                if st.flying or st.phase != FlightPhase.GROUND:
                    d.land()

    def run(self) -> WorldSummary:
        m = self.mission
        wall0 = time.perf_counter()
        clock = self.backend.clock
        missing = self.bus.wait_alive(set(self.ids), self.z.start_timeout_s)
        if missing:
            raise RuntimeError(f"agents {sorted(missing)} did not join within {self.z.start_timeout_s:g} s")
        self._wait_cmds(-1, self.z.start_timeout_s)  # every agent subscribed to its ticks
        self.log(f"serving {m.name}: agents {self.ids} present")
        target = TargetDriver(m.target_law(), self.backend) if m.target.motion == "square" else None
        t_target0: float | None = None
        dt = m.dt_s
        max_ticks = round((m.duration_s + TAKEOFF_TIMEOUT_S + 2 * LAND_TIMEOUT_S) / dt)
        k = 0
        try:
            while k < max_ticks:
                t = clock.now()
                self._publish_ticks(k, t)
                self._wait_cmds(k)
                self._apply()
                self._handle_departures(t)
                if len(self._gone) == len(self.ids):
                    break
                if target is not None:
                    if t_target0 is None and all(self.backend.drone(i).state().flying for i in self.ids):
                        t_target0 = t
                    if t_target0 is not None:
                        target.tick(t - t_target0)
                clock.sleep_until(t + dt)
                k += 1
                if k % max(1, round(1.0 / dt)) == 0:  # once per simulated second
                    self.log(f"tick {k} t = {clock.now():.2f} s")
        finally:
            self._land_all(dt)
            self.summary.ticks = k
            self.summary.sim_seconds = clock.now()
            self.summary.wall_seconds = time.perf_counter() - wall0
            self._close()
        return self.summary

    def _land_all(self, dt: float) -> None:
        self.backend.close()  # lands every drone, stops the robot
        self.summary.landed.update(settle_virtual_landing(self.backend, self.ids, dt))

    def _close(self) -> None:
        for obj in (self._sub, *self._pubs.values()):
            with contextlib.suppress(Exception):
                obj.undeclare()
        self.bus.close()
