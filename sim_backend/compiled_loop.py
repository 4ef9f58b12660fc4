"""The compiled lock-step loop: `run_mode`'s ticks on the ideal rig, in chunks of kernels.lockstep_chunk.

On the paper's ideal rig (backend sim_ideal, the in-process bus, safety off, a Duffing-like target, every
drone in this process) a tick is nothing but the paper's math, and Python's per-call overhead was almost
all of its cost. `CompiledLoop` flies such ticks in one compiled call per chunk of CHUNK_TICKS, calling
the same kernels as the Agent (flightstack.paper.kernels), in the same order, on the same state: it reads
the world and the agents before a chunk and writes them back after it, so a Python tick can run between
two chunks and the run ends, lands and records exactly as before. tests/test_compiled_loop.py holds its
recordings bit-identical to the Agent path in every mode.

A tick the compiled loop does not model (features that are not finite, a message the bus would drop, a
command that is not finite) ends the chunk before that tick changed anything; the runner flies it in
Python (with its rejection counts, drops and errors) and resumes the compiled loop after it. Between
chunks Ctrl-C, the progress bar and the run directory's writer work as they do per tick; the run
directory's `wall_t` of a compiled tick is the end of its chunk.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from flightstack.comms.bus import InProcBus
from flightstack.comms.messages import PredictionMessage
from flightstack.config.types import Mode
from flightstack.paper import kernels as kern
from flightstack.paper.gp import GPExpert
from flightstack.paper.target_motion import DuffingField
from flightstack.recording.timeseries import Recording
from flightstack.runtime.agent import MODE_CODES, Agent, TickRecord, TruthPredictor, pose_of
from flightstack.runtime.fleet import Fleet
from flightstack.runtime.tick_record import TickBook
from flightstack.sim_backend.ideal import IdealDrone

#: ticks per compiled call: ≤ the bus's max_seq_jump (the chunk's last message must be accepted), small
#: enough that Ctrl-C and the progress bar answer within ~10 ms of wall time
CHUNK_TICKS = 500

_LOCKSTEP_CHUNK: Callable[..., int] = kern.lockstep_chunk  # (numba's Dispatcher stub fixes the arity)

#: rec_f's planes, in order, and the Recording array each fills
_PLANES = ("g_wi", "g_bar_w", "e_e_meas", "u_e", "mu_used", "var_own", "V_cmd")


def why_not_compiled(f: Fleet) -> str | None:
    """Why this fleet's ticks cannot be compiled (None: they can)."""
    from flightstack.sim_backend.ideal import IdealSimBackend

    backend = f.backend
    if not isinstance(backend, IdealSimBackend):
        return "not the ideal rig"
    if not isinstance(f.bus, InProcBus) or f.bus.operator is not None:
        return "not the in-process bus"
    if f.supervisor is not None or f.safe or f.target is not None:
        return "safety layer or target driver present"
    if not isinstance(backend.world.target_field, DuffingField):
        return "target is not the Duffing-like field"
    if {a.cfg.drone_id for a in f.agents} != set(f.everyone):
        return "not every drone flies in this process"
    ids = [a.cfg.drone_id for a in f.agents]
    if ids != list(backend.world.drones):
        return "agent order differs from the world's drone order"
    if any(a.cfg.compensation is not None for a in f.agents):
        return "delay compensation is on"
    mode = Mode(f.mode)
    preds = [a.predictor for a in f.agents]
    if mode.uses_gp and not all(isinstance(p, GPExpert) for p in preds):
        return "a predictor is not a GP expert"
    if mode.uses_gp and len({p.kernel_arrays()[0].shape for p in preds if isinstance(p, GPExpert)}) != 1:
        return "experts of different shapes"
    if mode == Mode.ORACLE:
        prm = backend.world.target_field.prm
        if not all(isinstance(p, TruthPredictor) and p.prm == prm for p in preds):
            return "oracle predictors are not the world's field"
    for a in f.agents:
        cam = backend.camera(a.cfg.drone_id)
        if cam.cam.packed.tobytes() != a.cfg.camera.packed.tobytes() or not np.array_equal(cam.P0, a.cfg.P0):
            return "an agent's camera model differs from its ideal camera"
        if a.cfg.stale_after < 0 or a.cfg.max_frame_age_s < 0:
            return "negative freshness limits"
    return None


@dataclass
class CompiledLoop:
    """The fixed arrays of one fleet's compiled loop (built once per run by `plan`)."""

    f: Fleet
    P0: np.ndarray
    cams: np.ndarray
    sees: np.ndarray
    g_d: np.ndarray
    gains: np.ndarray
    mode: int
    rule: int
    oracle: bool
    gp: tuple[np.ndarray, ...]
    nb: np.ndarray
    nb_n: np.ndarray
    bounds: np.ndarray
    prm: np.ndarray
    chunk: int
    compiled_ticks: int = 0
    chunks: int = 0

    @classmethod
    def plan(cls, f: Fleet) -> CompiledLoop | None:
        """The loop for this fleet, or None when its ticks cannot be compiled (`why_not_compiled`)."""
        if why_not_compiled(f) is not None:
            return None
        backend = f.backend
        agents = f.agents
        idx = {a.cfg.drone_id: i for i, a in enumerate(agents)}
        n = len(agents)
        deg = max(1, max(len(a.cfg.neighbour_ids) for a in agents))
        nb = np.full((n, deg), -1, dtype=np.int64)
        for i, a in enumerate(agents):
            nb[i, : len(a.cfg.neighbour_ids)] = [idx[j] for j in a.cfg.neighbour_ids]
        g0 = agents[0].cfg.gains
        b = f.bus.freshness.bounds  # type: ignore[attr-defined]  # InProcBus (why_not_compiled)
        return cls(
            f=f,
            P0=np.ascontiguousarray(agents[0].cfg.P0, dtype=float),
            cams=np.array([a.cfg.camera.packed for a in agents]),
            sees=np.array([backend.camera(a.cfg.drone_id).sees_target for a in agents], dtype=np.bool_),  # type: ignore[attr-defined]
            g_d=np.array([a.cfg.g_d.as_vector() for a in agents]),
            gains=np.concatenate([g0.k_c, g0.k_e, [g0.k_s]]),
            mode=MODE_CODES[Mode(f.mode)],
            rule=agents[0].rule_code,
            oracle=Mode(f.mode) == Mode.ORACLE,
            gp=_stack_experts(agents),
            nb=nb,
            nb_n=np.array([len(a.cfg.neighbour_ids) for a in agents], dtype=np.int64),
            bounds=b.packed,
            prm=backend.world.target_field.prm.packed(),  # type: ignore[attr-defined]
            chunk=min(CHUNK_TICKS, b.max_seq_jump),
        )

    def ready(self, book: TickBook) -> bool:
        """Compiled ticks use every neighbour and hold nobody: true once the book says so already (a
        compiled tick adds no neighbour event)."""
        return all(
            not a.hold and book.neighbours_used[a.cfg.drone_id] == set(a.cfg.neighbour_ids)
            for a in self.f.agents
        )

    def run(self, rec: Recording, k0: int, k1: int) -> int:
        """Fly ticks k0..k1−1 (fewer if one needs Python); returns the first tick not flown."""
        f, agents = self.f, self.f.agents
        world = f.backend.world  # type: ignore[attr-defined]
        ids = list(world.drones)
        clock = np.array([world.t])
        target = world.target.pose.as_vector()
        target_V = np.array(world.target.velocity, dtype=float)
        drones = np.array([world.drones[i].pose.as_vector() for i in ids])
        drones_V = np.array([world.drones[i].velocity for i in ids], dtype=float)
        T = np.array([a._T for a in agents])
        has_prev = np.array(
            [a._u_e_prev is not None and a._t_prev is not None for a in agents], dtype=np.bool_
        )
        u_e_prev = np.array([a._u_e_prev if a._u_e_prev is not None else np.zeros(4) for a in agents])
        t_prev = np.array([a._t_prev if a._t_prev is not None else 0.0 for a in agents])
        n, rows = len(agents), k1 - k0
        rec_f, rec_t, rec_g_w0 = np.empty((rows, n, 7, 4)), np.empty(rows), np.empty((rows, 4))
        rec_vis, rec_nf = np.zeros((rows, n), dtype=np.bool_), np.zeros((rows, n), dtype=np.int64)
        k = _LOCKSTEP_CHUNK(
            k0, k1, f.loop.dt_s, clock, target, target_V, drones, drones_V, world.substeps, self.prm,
            self.P0, self.cams, self.sees, self.g_d, self.gains, self.mode, self.rule, self.oracle, *self.gp,
            self.nb, self.nb_n, T, u_e_prev, t_prev, has_prev, self.bounds,
            rec_f, rec_t, rec_g_w0, rec_vis, rec_nf,
        )  # fmt: skip
        done = k - k0
        if done == 0:
            return k
        # the world, the drones' commands and the agents, as the Python ticks would have left them
        world.t = float(clock[0])
        world.target.pose, world.target.velocity = pose_of(target), target_V
        for i, drone_id in enumerate(ids):
            world.drones[drone_id].pose, world.drones[drone_id].velocity = (
                pose_of(drones[i]),
                drones_V[i].copy(),
            )
            cast(IdealDrone, f.backend.drone(drone_id)).commands += done
        t_last = float(rec_t[done - 1])
        for i, a in enumerate(agents):
            a._T[:] = T[i]
            a._u_e_prev, a._t_prev = T[i, kern.U_E].copy(), float(t_prev[i])
            a._g_wi = rec_f[done - 1, i, 0].copy()
            a.seq += done
            a.last = _tick_record(a, bool(rec_vis[done - 1, i]), int(rec_nf[done - 1, i]))
            # the chunk's last message, as the bus would hold it (its seq jump ≤ CHUNK_TICKS is accepted)
            f.bus.publish(
                PredictionMessage(
                    a.cfg.mission, a.cfg.drone_id, a.seq, t_last, a.last.visible, a._T[kern.G_BAR_W].copy(),
                    a._T[kern.MU_OWN].copy(), a._T[kern.VAR_OWN].copy(), a._T[kern.PRIOR].copy(),
                )
            )  # fmt: skip
        rec.t[k0:k] = rec_t[:done]
        rec.g_w0[k0:k] = rec_g_w0[:done]
        for p, name in enumerate(_PLANES):
            getattr(rec, name)[k0:k] = rec_f[:done, :, p]
        rec.visible[k0:k] = rec_vis[:done]
        rec.n_fused[k0:k] = rec_nf[:done]
        # the ideal rig's camera and pose source stamp their samples with the world's time of the tick
        rec.frame_age[k0:k] = 0.0
        rec.pose_age[k0:k] = 0.0
        rec.wall_t[k0:k] = time.time()
        rec.ticks_done = k
        self.compiled_ticks += done
        self.chunks += 1
        return int(k)


def _tick_record(a: Agent, visible: bool, n_fused: int) -> TickRecord:
    T = a._T
    return TickRecord(
        g_bar_w=pose_of(T[kern.G_BAR_W]),
        visible=visible,
        e_e_meas=T[kern.E_E].copy(),
        mu_own=T[kern.MU_OWN].copy(),
        var_own=T[kern.VAR_OWN].copy(),
        mu_used=T[kern.MU_USED].copy(),
        u_c=T[kern.U_C].copy(),
        u_e=T[kern.U_E].copy(),
        V_cmd=T[kern.V_CMD].copy(),
        n_fused=n_fused,
        neighbours_used=tuple(a.cfg.neighbour_ids),
    )


def _stack_experts(agents: list[Agent]) -> tuple[np.ndarray, ...]:
    """Every agent's expert as padded stacks (inv_l, Z, σ_f², α, L⁻¹, floor, M): the first M_i rows of
    agent i's stacks are its expert, the rest zeros the kernel never reads (it stops at M_i)."""
    arrays = [a.predictor.kernel_arrays() for a in agents if isinstance(a.predictor, GPExpert)]
    n = len(agents)
    if len(arrays) != n:  # modes none and oracle: empty stacks of the right rank
        return (
            np.zeros((n, 1, 4)), np.zeros((n, 1, 1, 4)), np.ones((n, 1)), np.zeros((n, 4, 1)),
            np.zeros((n, 1, 1, 1)), np.zeros((n, 1)), np.zeros(n, dtype=np.int64),
        )  # fmt: skip
    m_max = max(ar[6] for ar in arrays)
    Dk, Din = arrays[0][1].shape[0], arrays[0][1].shape[2]
    D = arrays[0][3].shape[0]
    inv_l, sf2, floor = (np.array([ar[j] for ar in arrays]) for j in (0, 2, 5))
    Z, alpha, L_inv = np.zeros((n, Dk, m_max, Din)), np.zeros((n, D, m_max)), np.zeros((n, Dk, m_max, m_max))
    for i, (_, z, _, al, li, _, m) in enumerate(arrays):
        Z[i, :, :m], alpha[i, :, :m], L_inv[i, :, :m, :m] = z, al, li
    return inv_l, Z, sf2, alpha, L_inv, floor, np.array([ar[6] for ar in arrays], dtype=np.int64)
