"""Builds a backend, agents and a bus from a mission and drives the clock (DESIGN §1–2).

`run_mode` flies one mode of a simulated mission in lock-step: every tick all agents run phase 1, then
all run phase 2, then the backend's clock advances by dt. It records the agents' internal signals and,
on a simulated backend, the ground truth needed for the paper's error e ∈ R^{8n}.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flightstack.agent import Agent, AgentConfig, Predictor
from flightstack.backends import build_backend
from flightstack.comms.bus import InProcBus
from flightstack.control import Gains
from flightstack.geometry import Pose, compose, compose_arrays, inverse, inverse_arrays, vec_arrays
from flightstack.mission import Mission
from flightstack.projection import CameraModel


def pose_from_spec(spec) -> Pose:
    return Pose.make(spec.p, spec.theta)


@dataclass
class Recording:
    """Time series of one run; arrays indexed [tick, drone, component]. Poses are [x, y, z, θ]."""

    mode: str
    drone_ids: list[int]
    t: np.ndarray
    g_w0: np.ndarray  # (N, 4) true target pose
    g_wi: np.ndarray  # (N, n, 4) true drone poses
    g_bar_w: np.ndarray  # (N, n, 4) estimates ḡ_w,i
    e_c: np.ndarray  # (N, n, 4) vec(g_d⁻¹ ḡ_i0)
    e_e: np.ndarray  # (N, n, 4) true vec(ḡ_i0⁻¹ g_i0)
    e_e_meas: np.ndarray  # (N, n, 4) J⁺(f − f̄)
    u_e: np.ndarray  # (N, n, 4)
    mu_used: np.ndarray  # (N, n, 4)
    var_own: np.ndarray  # (N, n, 4)
    V_cmd: np.ndarray  # (N, n, 4)
    visible: np.ndarray  # (N, n) bool
    ticks_done: int = 0
    bus_dropped: dict[str, int] = field(default_factory=dict)
    wall_seconds: float = 0.0
    interrupted: bool = False
    events: list[dict[str, object]] = field(default_factory=list)

    @staticmethod
    def empty(mode: str, ids: list[int], n_ticks: int) -> Recording:
        n = len(ids)
        z = lambda: np.zeros((n_ticks, n, 4))  # noqa: E731
        return Recording(
            mode,
            ids,
            np.zeros(n_ticks),
            np.zeros((n_ticks, 4)),
            z(),
            z(),
            z(),
            z(),
            z(),
            z(),
            z(),
            z(),
            z(),
            np.zeros((n_ticks, n), dtype=bool),
        )

    def truncated(self) -> Recording:
        """Only the ticks actually flown (after an interrupt)."""
        k = self.ticks_done
        out = Recording(self.mode, self.drone_ids, *(getattr(self, f)[:k] for f in ARRAY_FIELDS))
        out.ticks_done, out.bus_dropped = k, self.bus_dropped
        out.wall_seconds, out.interrupted, out.events = self.wall_seconds, self.interrupted, self.events
        return out

    def save(self, path: str) -> None:
        np.savez_compressed(
            path,
            mode=self.mode,
            drone_ids=np.array(self.drone_ids),
            **{f: getattr(self, f)[: self.ticks_done] for f in ARRAY_FIELDS},
        )


ARRAY_FIELDS = (
    "t",
    "g_w0",
    "g_wi",
    "g_bar_w",
    "e_c",
    "e_e",
    "e_e_meas",
    "u_e",
    "mu_used",
    "var_own",
    "V_cmd",
    "visible",
)


def make_agents(
    mission: Mission,
    mode: str,
    backend,
    bus,
    predictors: dict[int, Predictor] | None,
) -> list[Agent]:
    """One Agent per drone of the mission, with initial estimates from the mission's initial errors."""
    P0 = np.array(mission.target.feature_points, dtype=float)
    cam = CameraModel(focal_length=mission.camera.focal_length)
    gains = Gains.make(mission.gains.k_c, mission.gains.k_e, mission.gains.k_s)
    ids = [d.id for d in mission.drones]
    agents = []
    g_w0 = pose_from_spec(mission.target.initial_pose)
    for k, d in enumerate(mission.drones):
        cfg = AgentConfig(
            mission=mission.name,
            drone_id=d.id,
            body_name=f"drone{d.id}",
            g_d=pose_from_spec(d.desired_pose),
            P0=P0,
            camera=cam,
            gains=gains,
            mode=mode,
            fusion_rule=mission.gp.fusion,
            neighbour_ids=tuple(ids[j] for j in mission.neighbours(k)),
            stale_after=mission.bus.stale_after_s,
        )
        # ḡ_w,i(0) = g_w0(0) g_e(0)⁻¹, i.e. g_e(0) = ḡ_w,i⁻¹ g_w0 is the mission's initial estimation error.
        g_bar = compose(g_w0, inverse(pose_from_spec(d.initial_estimate_error)))
        pred = None if predictors is None else predictors.get(d.id)
        agents.append(
            Agent(cfg, backend.drone(d.id), backend.camera(d.id), backend.pose_source(), bus, pred, g_bar)
        )
    return agents


def run_mode(
    mission: Mission,
    mode: str,
    predictors: dict[int, Predictor] | None = None,
    progress: Callable[[int], None] | None = None,
) -> Recording:
    """Fly `mode` of a simulated mission for mission.duration_s; Ctrl-C stops early and keeps the data."""
    backend = build_backend(mission)
    ids = [d.id for d in mission.drones]
    bus = InProcBus(mission.name, set(ids))
    agents = make_agents(mission, mode, backend, bus, predictors)
    g_d = [a.cfg.g_d for a in agents]
    dt = mission.dt_s
    n_ticks = round(mission.duration_s / dt)
    rec = Recording.empty(mode, ids, n_ticks)
    clock = backend.clock
    wall0 = time.perf_counter()
    try:
        for k in range(n_ticks):
            t = clock.now()
            for a in agents:
                a.sense_and_publish(t)
            for a in agents:
                a.fuse_control_act(t)
            g_w0, g_wis = backend.truth()
            rec.t[k] = t
            rec.g_w0[k] = g_w0.as_vector()
            for i, a in enumerate(agents):
                last = a.last
                rec.g_wi[k, i] = g_wis[a.cfg.drone_id].as_vector()
                rec.g_bar_w[k, i] = last.g_bar_w.as_vector()
                rec.e_e_meas[k, i] = last.e_e_meas
                rec.u_e[k, i] = last.u_e
                rec.mu_used[k, i] = last.mu_used
                rec.var_own[k, i] = last.var_own
                rec.V_cmd[k, i] = last.V_cmd
                rec.visible[k, i] = last.visible
            rec.ticks_done = k + 1
            if progress is not None:
                progress(1)
            clock.sleep_until(t + dt)
    except KeyboardInterrupt:
        rec.interrupted = True
        rec.events.append({"t": clock.now(), "event": "interrupted", "mode": mode})
    finally:
        backend.close()  # lands every drone
        for i in ids:
            st = backend.drone(i).state()
            rec.events.append(
                {
                    "t": clock.now(),
                    "event": "landed" if not st.flying else "NOT LANDED",
                    "drone": i,
                    "mode": mode,
                }
            )
        rec.wall_seconds = time.perf_counter() - wall0
        rec.bus_dropped = dict(bus.dropped)
        fill_true_errors(rec, np.array([g.as_vector() for g in g_d]))
    return rec if not rec.interrupted else rec.truncated()


def fill_true_errors(rec: Recording, g_d: np.ndarray) -> None:
    """e_c = vec(g_d⁻¹ ḡ_i0) and the true e_e = vec(ḡ_i0⁻¹ g_i0) from the recorded poses (vectorised)."""
    k = rec.ticks_done
    inv_wi = inverse_arrays(rec.g_wi[:k])
    g_bar_i0 = compose_arrays(inv_wi, rec.g_bar_w[:k])
    g_i0 = compose_arrays(inv_wi, rec.g_w0[:k, None, :])
    rec.e_c[:k] = vec_arrays(compose_arrays(inverse_arrays(g_d)[None], g_bar_i0))
    rec.e_e[:k] = vec_arrays(compose_arrays(inverse_arrays(g_bar_i0), g_i0))
