"""Compile (or load from numba's cache) every kernel before anything flies (flightstack.paper.kernels).

A kernel compiles on its first call for a new combination of argument types; a compile takes seconds and
holds the GIL, long enough to trip the Tello driver's loop watchdog (0.5 s) mid-flight. `warm_up` calls
every kernel once with the argument types its callers use (C-contiguous writable float64 arrays, Python
or numpy floats, int64 and booleans), so a mission's first tick finds them compiled. It runs when a fleet is
assembled (flightstack.runtime.fleet) and in preflight; tests/test_kernels.py asserts that a run after it
adds no signature to any kernel. What it costs (2-core CI machine): the first run on a machine (no cache
yet) compiles for ~11 s, ~9 s more for the compiled simulator's loop; later runs load the cache in
~0.3–0.7 s (docs/performance.md).
"""

from __future__ import annotations

import time

import numpy as np
from numba.core.registry import CPUDispatcher

from flightstack.paper import kernels as kern

_warm: set[bool] = set()
#: warm-up arguments of the types the callers pass: four coplanar feature points (m), an ideal camera
#: (kernels' packed CameraModel), the Duffing parameters
_P0 = np.array([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0], [0.1, -0.1, 0.0]])
_CAM = np.array([1.0, 1e-3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
_PRM = np.array([-1.0, 1.0, 0.39, 0.1, 0.4])


def dispatchers() -> dict[str, CPUDispatcher]:
    """Every kernel of flightstack.paper.kernels by name."""
    return {name: obj for name, obj in vars(kern).items() if isinstance(obj, CPUDispatcher)}


def signature_counts() -> dict[str, int]:
    """How many compiled signatures each kernel has now."""
    return {name: len(d.signatures) for name, d in dispatchers().items()}


def warm_up(loop: bool = False) -> float:
    """Compile or load every kernel the Agent and the paper's functions call (and the compiled
    lock-step loop if `loop`); returns the seconds it took (0 if done already in this process)."""
    if loop in _warm:
        return 0.0
    t0 = time.perf_counter()
    g, h, V = np.array([0.1, -0.2, 1.5, 0.3]), np.array([0.0, 0.1, 0.2, -0.1]), np.zeros(4)
    out = np.zeros(4)
    kern.wrap_angle(0.5)
    kern.compose4(g, h, out)
    kern.inverse4(g, out)
    kern.relative4(g, h, out)
    kern.exp_twist4(V, 0.01, out)
    kern.integrate4(g, V, 0.01, out)
    kern.lag_integrate4(g, V.copy(), h, 0.1, 0.01, out)
    g_i0 = np.array([0.0, 0.0, 1.5, 0.1])
    pc, f, J = np.zeros((4, 3)), np.zeros(8), np.zeros((8, 4))
    kern.points_in_camera(g_i0, _P0, _CAM, pc)
    kern.points_in_view(g_i0, _P0, _CAM, pc)
    kern.measure(g_i0, _P0, _CAM, f)
    kern.features_and_jacobian(g_i0, _P0, _CAM, f, J)
    kern.estimation_error(f, g_i0, _P0, _CAM, out)
    kern.solve4(np.eye(4), np.ones(4), out)
    M = 3
    inv_l, Z, sf2 = np.ones((4, 4)), np.zeros((4, M, 4)), np.ones(4)
    alpha, L_inv, floor = np.zeros((4, M)), np.zeros((4, M, M)), np.full(4, 1e-12)
    mu, var = np.zeros(4), np.ones(4)
    kern.gp_predict_one(g, inv_l, Z, sf2, alpha, L_inv, floor, M, mu, var)
    stack = np.ones((2, 4))
    kern.fuse(stack, stack, kern.RULE_POE, stack, 2, mu, var)
    kern.control_error(g, h, out)
    kern.consensus_term(g, stack, 2, out)
    kern.pursuit_law(out, 0.1, out, 0.1, out, mu, np.ones(4), np.ones(4), 1.0, True, mu, var)
    kern.drone_velocity_command(out, g, V)
    kern.duffing_body_velocity(g, _PRM, V)
    T = np.ones((10, 4))
    T[kern.G_BAR_W] = g_i0
    kern.agent_sense(T, V, 0.01, np.zeros(4), f, True, _P0, _CAM)
    kern.agent_act(
        T,
        True,
        stack,
        stack,
        stack,
        stack,
        2,
        kern.MODE_DGP,
        kern.RULE_POE,
        g,
        np.ones(4),
        np.ones(4),
        1.0,
        False,
    )
    kern.message_check(np.concatenate((g, mu, var, var)), np.array([1e-12, 1e12, 10.0, 10.0, 1e3, 1e3]))
    if loop:
        _warm_loop()
    _warm.add(loop)
    return time.perf_counter() - t0


def _warm_loop() -> None:
    """One tick of kern.lockstep_chunk with the types flightstack.sim_backend.compiled_loop passes."""
    n, M = 2, 3
    drones = np.array([[0.0, 0.0, -1.5, 0.0], [0.2, 0.0, -1.5, 0.0]])
    T = np.zeros((n, 10, 4))
    kern.world_advance(
        np.zeros(1), 0.002, 0.002, np.zeros(4), np.zeros(4), drones.copy(), np.zeros((n, 4)), 1, _PRM
    )
    gp = (
        np.ones((n, 4, 4)), np.zeros((n, 4, M, 4)), np.ones((n, 4)), np.zeros((n, 4, M)),
        np.zeros((n, 4, M, M)), np.full((n, 4), 1e-12), np.full(n, M, dtype=np.int64),
    )  # fmt: skip
    kern.lockstep_chunk(
        0, 1, 0.002, np.zeros(1), np.zeros(4), np.zeros(4), drones, np.zeros((n, 4)), 1,
        _PRM, _P0, np.array([_CAM, _CAM]), np.ones(n, dtype=np.bool_),
        np.array([[0.0, 0.0, 1.5, 0.0]] * n), np.ones(9), kern.MODE_DGP, kern.RULE_POE, False, *gp,
        np.array([[1], [0]], dtype=np.int64), np.ones(n, dtype=np.int64), T, np.zeros((n, 4)), np.zeros(n),
        np.zeros(n, dtype=np.bool_), np.array([1e-12, 1e12, 10.0, 10.0, 1e3, 1e3]),
        np.zeros((1, n, 7, 4)), np.zeros(1), np.zeros((1, 4)), np.zeros((1, n), dtype=np.bool_),
        np.zeros((1, n), dtype=np.int64),
    )  # fmt: skip
