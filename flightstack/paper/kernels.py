"""The tick's math, compiled: the only copy of every equation a control tick evaluates (DESIGN §4).

Every function here is a numba kernel (`@kernel` = `@njit(cache=True, error_model="numpy")`) on float64
scalars and C-contiguous float64 arrays. The public functions of flightstack.paper (geometry, projection,
observer, gp, fusion, control, target_motion) are thin wrappers that validate their arguments and call
these; the Agent calls `agent_sense` and `agent_act`; the compiled lock-step loop (`lockstep_chunk`, run
by flightstack.sim_backend.compiled_loop) calls the very same kernels, so the simulator and the flight code
cannot drift apart. Symbols are the paper's (Saito et al., IFAC 2023); docs/equations.md maps them.

Numba's rules, kept here on purpose:
* all kernels live in this one module: numba's on-disk cache is keyed on the file that defines a
  function, so a kernel calling a kernel from another file would keep a stale compiled copy;
* nothing compiles during a flight: `warm_up()` compiles (or loads from the cache) every kernel for the
  argument types the callers use; it runs when a mission is built and in preflight, and
  tests/test_kernels.py asserts that no kernel gains a signature during a run after warm-up;
* arithmetic is written out in scalar loops in a fixed order (no fastmath, no reassociation), so a kernel
  gives the same bits whether it is called from Python or inlined into the compiled loop.

Poses are vectors [x, y, z, θ] (m, rad) of planar SE(3) (flightstack.paper.geometry); body velocities
[v_x, v_y, v_z, ω] (m/s, rad/s).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi
PI = math.pi

#: the decorator of every kernel: cached on disk; IEEE division (x/0 is ±inf or NaN, as in numpy, not an
#: exception: a non-finite result is caught where it leaves the math, e.g. a command the drone refuses)
kernel = njit(cache=True, error_model="numpy")

#: fusion rule codes (flightstack.paper.fusion.FUSION_RULES order)
RULE_POE, RULE_GPOE, RULE_BCM, RULE_RBCM = 0, 1, 2, 3
#: agent modes (flightstack.config.types.Mode)
MODE_NONE, MODE_LOCAL, MODE_DGP, MODE_ORACLE = 0, 1, 2, 3
#: estimation_error's outcome
OK, NOT_VISIBLE, SINGULAR = 0, 1, 2
#: oracle predictor's variance and prior (flightstack.runtime.agent.TruthPredictor)
ORACLE_VAR = 1e-9


# ---- geometry (paper Sec. 2) -----------------------------------------------------------------------------
@kernel
def wrap_angle(theta: float) -> float:
    """θ wrapped to (−π, π]; exactly math.remainder(θ, 2π) with −π mapped to π (fmod is exact)."""
    r = np.fmod(theta, TWO_PI)
    if r > PI:
        r -= TWO_PI
    elif r <= -PI:
        r += TWO_PI
    return r


@kernel
def compose4(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out = a·b = (p_a + R_a p_b, θ_a + θ_b) for pose vectors (out may alias neither input)."""
    c, s = math.cos(a[3]), math.sin(a[3])
    out[0] = a[0] + c * b[0] - s * b[1]
    out[1] = a[1] + s * b[0] + c * b[1]
    out[2] = a[2] + b[2]
    out[3] = wrap_angle(a[3] + b[3])


@kernel
def inverse4(g: np.ndarray, out: np.ndarray) -> None:
    """out = g⁻¹ = (−Rᵀ p, −θ)."""
    c, s = math.cos(g[3]), math.sin(g[3])
    out[0] = -(c * g[0] + s * g[1])
    out[1] = -(-s * g[0] + c * g[1])
    out[2] = -g[2]
    out[3] = wrap_angle(-g[3])


@kernel
def relative4(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out = a⁻¹·b (e.g. ḡ_i0 = g_wi⁻¹ ḡ_w,i)."""
    inv = np.empty(4)
    inverse4(a, inv)
    compose4(inv, b, out)


@kernel
def exp_twist4(V: np.ndarray, dt: float, out: np.ndarray) -> None:
    """out = exp(V̂ dt): closed form for rotation about z, Taylor series for |ω dt| < 1e-6."""
    vx, vy, vz, w = V[0], V[1], V[2], V[3]
    th = w * dt
    if abs(th) < 1e-6:
        a = dt * (1.0 - th * th / 6.0)
        b = dt * (th / 2.0 - th**3 / 24.0)
    else:
        a = math.sin(th) / w
        b = (1.0 - math.cos(th)) / w
    out[0] = a * vx - b * vy
    out[1] = b * vx + a * vy
    out[2] = vz * dt
    out[3] = wrap_angle(th)


@kernel
def integrate4(g: np.ndarray, V: np.ndarray, dt: float, out: np.ndarray) -> None:
    """out = g exp(V̂ dt): a body velocity V held for dt seconds (zero-order hold; exact)."""
    e = np.empty(4)
    exp_twist4(V, dt, e)
    compose4(g, e, out)


@kernel
def lag_integrate4(
    g: np.ndarray, V: np.ndarray, V_target: np.ndarray, a: float, dt: float, out: np.ndarray
) -> None:
    """One step of dt seconds of a body whose velocity follows V_target with a first-order lag:
    V += a (V_target − V) in place (a = 1 − exp(−dt/τ)), then out = g exp(V̂ dt) (the simulated lab's
    drones and robot; out may alias neither g nor V)."""
    for i in range(4):
        V[i] += a * (V_target[i] - V[i])
    integrate4(g, V, dt, out)


# ---- projection (paper eq. f, DESIGN §4) ---------------------------------------------------------------
# cam = [λ, min_depth, R_ic (9, row-major), t_ic (3)]: the camera of flightstack.paper.projection.CameraModel
@kernel
def points_in_camera(g_i0: np.ndarray, P0: np.ndarray, cam: np.ndarray, out: np.ndarray) -> None:
    """out (m, 3): p_c^j = R_icᵀ (R(θ_i0) p_0^j + p_i0 − t_ic) for the feature points P0 (m, 3) in Σ0."""
    c, s = math.cos(g_i0[3]), math.sin(g_i0[3])
    for j in range(P0.shape[0]):
        px = c * P0[j, 0] - s * P0[j, 1] + g_i0[0] - cam[11]
        py = s * P0[j, 0] + c * P0[j, 1] + g_i0[1] - cam[12]
        pz = P0[j, 2] + g_i0[2] - cam[13]
        for k in range(3):
            out[j, k] = px * cam[2 + k] + py * cam[5 + k] + pz * cam[8 + k]


@kernel
def points_in_view(g_i0: np.ndarray, P0: np.ndarray, cam: np.ndarray, pc: np.ndarray) -> bool:
    """pc (m, 3) = the points in Σc (points_in_camera); False if a depth is ≤ min_depth (behind it)."""
    points_in_camera(g_i0, P0, cam, pc)
    for j in range(P0.shape[0]):  # noqa: SIM110  (numba compiles no generator in all())
        if not pc[j, 2] > cam[1]:
            return False
    return True


@kernel
def measure(g_i0: np.ndarray, P0: np.ndarray, cam: np.ndarray, f: np.ndarray) -> bool:
    """f (2m,) = [λ x^j / z^j, λ y^j / z^j]_j; False (f untouched) if a depth is ≤ min_depth."""
    m = P0.shape[0]
    pc = np.empty((m, 3))
    if not points_in_view(g_i0, P0, cam, pc):
        return False
    for j in range(m):
        f[2 * j] = cam[0] * pc[j, 0] / pc[j, 2]
        f[2 * j + 1] = cam[0] * pc[j, 1] / pc[j, 2]
    return True


@kernel
def features_and_jacobian(
    g_bar: np.ndarray, P0: np.ndarray, cam: np.ndarray, f_bar: np.ndarray, J: np.ndarray
) -> bool:
    """f̄ = f(ḡ) (2m,) and J (2m, 4) with f(ḡ exp(ξ̂)) ≈ f̄ + J ξ; False if a depth is ≤ min_depth.

    Per point p_0^j = (a, b, c): J^j = (λ/z̄)[[1, 0, −x̄/z̄], [0, 1, −ȳ/z̄]] R_icᵀ R̄ [I₃ | (−b, a, 0)ᵀ].
    """
    m = P0.shape[0]
    pc = np.empty((m, 3))
    if not points_in_view(g_bar, P0, cam, pc):
        return False
    c, s = math.cos(g_bar[3]), math.sin(g_bar[3])
    # M = R_icᵀ R(θ): M[k, q] = Σ_r R_ic[r, k] R[r, q]
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    M = np.empty((3, 3))
    for k in range(3):
        for q in range(3):
            M[k, q] = cam[2 + k] * R[0, q] + cam[5 + k] * R[1, q] + cam[8 + k] * R[2, q]
    lam = cam[0]
    D = np.empty((3, 4))
    for j in range(m):
        a, b = P0[j, 0], P0[j, 1]
        for k in range(3):
            D[k, 0] = M[k, 0]
            D[k, 1] = M[k, 1]
            D[k, 2] = M[k, 2]
            D[k, 3] = -b * M[k, 0] + a * M[k, 1]
        x, y, z = pc[j, 0], pc[j, 1], pc[j, 2]
        iz = lam / z
        xz, yz = x / z, y / z
        for q in range(4):
            J[2 * j, q] = iz * (D[0, q] - xz * D[2, q])
            J[2 * j + 1, q] = iz * (D[1, q] - yz * D[2, q])
        f_bar[2 * j] = x * iz
        f_bar[2 * j + 1] = y * iz
    return True


@kernel
def solve4(A: np.ndarray, b: np.ndarray, x: np.ndarray) -> bool:
    """x = A⁻¹ b for a 4×4 A by Gaussian elimination with partial pivoting; False if A is singular."""
    n = 4
    a = A.copy()
    r = b.copy()
    for col in range(n):
        p = col
        big = abs(a[col, col])
        for i in range(col + 1, n):
            if abs(a[i, col]) > big:
                big = abs(a[i, col])
                p = i
        if not big > 0.0 or not math.isfinite(big):
            return False
        if p != col:
            for q in range(n):
                a[col, q], a[p, q] = a[p, q], a[col, q]
            r[col], r[p] = r[p], r[col]
        for i in range(col + 1, n):
            fct = a[i, col] / a[col, col]
            for q in range(col, n):
                a[i, q] -= fct * a[col, q]
            r[i] -= fct * r[col]
    for i in range(n - 1, -1, -1):
        acc = r[i]
        for q in range(i + 1, n):
            acc -= a[i, q] * x[q]
        x[i] = acc / a[i, i]
    return True


@kernel
def estimation_error(
    f: np.ndarray, g_bar_i0: np.ndarray, P0: np.ndarray, cam: np.ndarray, xi: np.ndarray
) -> int:
    """xi = J⁺(f − f̄) ≈ [p_e, θ_e] by the 4×4 normal equations (JᵀJ ξ = Jᵀ r). Returns OK, or
    NOT_VISIBLE (a point of the estimate at depth ≤ min_depth) or SINGULAR (JᵀJ singular); xi then unset."""
    m2 = 2 * P0.shape[0]
    f_bar = np.empty(m2)
    J = np.empty((m2, 4))
    if not features_and_jacobian(g_bar_i0, P0, cam, f_bar, J):
        return NOT_VISIBLE
    JtJ = np.zeros((4, 4))
    Jtr = np.zeros(4)
    for q in range(4):
        for w in range(4):
            acc = 0.0
            for i in range(m2):
                acc += J[i, q] * J[i, w]
            JtJ[q, w] = acc
        acc = 0.0
        for i in range(m2):
            acc += J[i, q] * (f[i] - f_bar[i])
        Jtr[q] = acc
    return OK if solve4(JtJ, Jtr, xi) else SINGULAR


# ---- GP expert (paper "Distributed GP") ------------------------------------------------------------------
@kernel
def gp_predict_one(
    x: np.ndarray,
    inv_l: np.ndarray,
    Z: np.ndarray,
    sf2: np.ndarray,
    alpha: np.ndarray,
    L_inv: np.ndarray,
    var_floor: np.ndarray,
    n: int,
    mu: np.ndarray,
    var: np.ndarray,
) -> None:
    """μ_d = k_*ᵀ α_d and var_d = max(σ_f,d² − ‖L_d⁻¹ k_*‖², floor_d) at one input x (Din,).

    inv_l (Dk, Din) = 1/l, Z (Dk, M, Din) = X/l, L_inv (Dk, M, M) lower triangular, alpha (D, M); only
    the first n ≤ M training points are used (padded stacks). Dk = D (one SE-ARD kernel per output,
    the paper's model) or Dk = 1 (one kernel shared by the D outputs: one k_*, one L⁻¹ k_*).
    """
    D = alpha.shape[0]
    Dk = Z.shape[0]
    Din = Z.shape[2]
    k = np.empty(n)
    acc = 0.0
    for d in range(D):
        dk = d if Dk == D else 0
        if d == 0 or Dk == D:
            for i in range(n):
                s = 0.0
                for q in range(Din):
                    diff = x[q] * inv_l[dk, q] - Z[dk, i, q]
                    s += diff * diff
                k[i] = sf2[dk] * math.exp(-0.5 * s)
            acc = 0.0
            for r in range(n):  # v_r = Σ_{i≤r} (L⁻¹)_ri k_i in four interleaved partial sums (a fixed
                a0 = a1 = a2 = a3 = 0.0  # order, so the bits do not depend on the caller; 4× the throughput
                i = 0  # of one dependent chain at large M)
                while i + 3 <= r:
                    a0 += L_inv[dk, r, i] * k[i]
                    a1 += L_inv[dk, r, i + 1] * k[i + 1]
                    a2 += L_inv[dk, r, i + 2] * k[i + 2]
                    a3 += L_inv[dk, r, i + 3] * k[i + 3]
                    i += 4
                while i <= r:
                    a0 += L_inv[dk, r, i] * k[i]
                    i += 1
                v = (a0 + a1) + (a2 + a3)
                acc += v * v
        m = 0.0
        for i in range(n):
            m += alpha[d, i] * k[i]
        mu[d] = m
        vd = sf2[dk] - acc
        var[d] = vd if vd > var_floor[dk] else var_floor[dk]


# ---- fusion (Deisenroth & Ng 2015; paper eqs. poe_mu, poe_var) -------------------------------------------
@kernel
def fuse(
    mu: np.ndarray,
    var: np.ndarray,
    rule: int,
    prior: np.ndarray,
    n: int,
    mu_out: np.ndarray,
    var_out: np.ndarray,
) -> None:
    """Fuse the first n experts (rows) of mu, var (K, D) per output: (var)⁻¹ = Σ β_k var_k⁻¹ + c σ_**⁻²,
    μ = var Σ β_k var_k⁻¹ μ_k (flightstack.paper.fusion for the rules, σ_**² = mean of the priors)."""
    D = var.shape[1]
    for d in range(D):
        if rule == RULE_POE:
            sp = 0.0
            for k in range(n):
                sp += 1.0 / var[k, d]
            fv = 1.0 / sp
            m = 0.0
            for k in range(n):
                m += fv * (1.0 / var[k, d]) * mu[k, d]
            mu_out[d] = m
            var_out[d] = fv
            continue
        ps = 0.0
        for k in range(n):
            ps += prior[k, d]
        prior_star = ps / n
        fp = 0.0
        bsum = 0.0
        if rule == RULE_GPOE:
            for k in range(n):
                fp += (1.0 / n) * (1.0 / var[k, d])
        elif rule == RULE_BCM:
            pmin = math.inf
            for k in range(n):
                p = 1.0 / var[k, d]
                fp += p
                pmin = min(pmin, p)
            fp = max(fp + (1.0 - n) / prior_star, pmin)
        else:
            for k in range(n):
                beta = 0.5 * (math.log(prior_star) - math.log(var[k, d]))
                fp += beta * (1.0 / var[k, d])
                bsum += beta
            fp = fp + (1.0 - bsum) / prior_star
        fv = 1.0 / fp
        m = 0.0
        for k in range(n):
            if rule == RULE_GPOE:
                beta = 1.0 / n
            elif rule == RULE_BCM:
                beta = 1.0
            else:
                beta = 0.5 * (math.log(prior_star) - math.log(var[k, d]))
            m += fv * beta * (1.0 / var[k, d]) * mu[k, d]
        mu_out[d] = m
        var_out[d] = fv


# ---- pursuit law (paper eq. ui with the DESIGN §4 corrections) --------------------------------------------
@kernel
def control_error(g_d: np.ndarray, g_bar_i0: np.ndarray, e_c: np.ndarray) -> float:
    """e_c = vec(g_d⁻¹ ḡ_i0) = [p_c, sin θ_c] into e_c; returns θ_c (rad)."""
    inv = np.empty(4)
    g_c = np.empty(4)
    inverse4(g_d, inv)
    compose4(inv, g_bar_i0, g_c)
    e_c[0], e_c[1], e_c[2], e_c[3] = g_c[0], g_c[1], g_c[2], math.sin(g_c[3])
    return g_c[3]


@kernel
def consensus_term(g_bar_w_i: np.ndarray, G: np.ndarray, n: int, c_i: np.ndarray) -> None:
    """c_i = Σ_{j<n} vec(ḡ_w,i⁻¹ ḡ_w,j) over the first n rows of G (K, 4), each θ_j wrapped first."""
    inv = np.empty(4)
    inverse4(g_bar_w_i, inv)
    ca, sa = math.cos(inv[3]), math.sin(inv[3])
    c0 = c1 = c2 = c3 = 0.0
    for j in range(n):
        c0 += inv[0] + ca * G[j, 0] - sa * G[j, 1]
        c1 += inv[1] + sa * G[j, 0] + ca * G[j, 1]
        c2 += inv[2] + G[j, 2]
        c3 += math.sin(wrap_angle(inv[3] + wrap_angle(G[j, 3])))
    c_i[0], c_i[1], c_i[2], c_i[3] = c0, c1, c2, c3


@kernel
def pursuit_law(
    e_c: np.ndarray,
    theta_c: float,
    e_e: np.ndarray,
    theta_e: float,
    c_i: np.ndarray,
    mu: np.ndarray,
    k_c: np.ndarray,
    k_e: np.ndarray,
    k_s: float,
    visible: bool,
    u_c: np.ndarray,
    u_e: np.ndarray,
) -> None:
    """u_e = −v_i k_e (e_e − Ad_{Rᵀ(θc)} e_c) − k_s c_i − Ad_{R(θe)} μ and
    u_c = −k_c e_c − k_s Ad_{R(θc)} c_i − Ad_{R(θc)} Ad_{R(θe)} μ (v_i = 1 if the target is seen)."""
    v_i = 1.0 if visible else 0.0
    c, s = math.cos(theta_e), math.sin(theta_e)
    me0, me1, me2, me3 = c * mu[0] - s * mu[1], s * mu[0] + c * mu[1], mu[2], mu[3]
    c, s = math.cos(-theta_c), math.sin(-theta_c)
    er0, er1, er2, er3 = c * e_c[0] - s * e_c[1], s * e_c[0] + c * e_c[1], e_c[2], e_c[3]
    u_e[0] = -v_i * k_e[0] * (e_e[0] - er0) - k_s * c_i[0] - me0
    u_e[1] = -v_i * k_e[1] * (e_e[1] - er1) - k_s * c_i[1] - me1
    u_e[2] = -v_i * k_e[2] * (e_e[2] - er2) - k_s * c_i[2] - me2
    u_e[3] = -v_i * k_e[3] * (e_e[3] - er3) - k_s * c_i[3] - me3
    c, s = math.cos(theta_c), math.sin(theta_c)
    cr0, cr1, cr2, cr3 = c * c_i[0] - s * c_i[1], s * c_i[0] + c * c_i[1], c_i[2], c_i[3]
    mr0, mr1, mr2, mr3 = c * me0 - s * me1, s * me0 + c * me1, me2, me3
    u_c[0] = -k_c[0] * e_c[0] - k_s * cr0 - mr0
    u_c[1] = -k_c[1] * e_c[1] - k_s * cr1 - mr1
    u_c[2] = -k_c[2] * e_c[2] - k_s * cr2 - mr2
    u_c[3] = -k_c[3] * e_c[3] - k_s * cr3 - mr3


@kernel
def drone_velocity_command(u_c: np.ndarray, g_d: np.ndarray, V: np.ndarray) -> None:
    """V_wi = −Ad_{g_d} u_c, Ad_g = [[R, (p_y, −p_x, 0)ᵀ], [0, 1]]."""
    c, s = math.cos(g_d[3]), math.sin(g_d[3])
    V[0] = -(c * u_c[0] - s * u_c[1] + g_d[1] * u_c[3])
    V[1] = -(s * u_c[0] + c * u_c[1] - g_d[0] * u_c[3])
    V[2] = -u_c[2]
    V[3] = -u_c[3]


# ---- the target's velocity field (paper Sec. 5) -----------------------------------------------------------
@kernel
def duffing_body_velocity(g_w0: np.ndarray, prm: np.ndarray, V: np.ndarray) -> None:
    """V_w0 = 0.5 Ad_{Rᵀ(θ)} [y, z, v_z, 2ω], v_z = 0.2(−δz − αy − 3βx²y − γω sin θ).

    prm = [α, β, γ, δ, ω] (flightstack.paper.target_motion.DuffingParams.packed)."""
    x, y, z, th = g_w0[0], g_w0[1], g_w0[2], g_w0[3]
    al, be, ga, de, om = prm[0], prm[1], prm[2], prm[3], prm[4]
    v_z = 0.2 * (-de * z - al * y - 3.0 * be * x * x * y - ga * om * math.sin(th))
    wx, wy, wz = 0.5 * y, 0.5 * z, 0.5 * v_z
    c, s = math.cos(th), math.sin(th)
    V[0] = c * wx + s * wy
    V[1] = -s * wx + c * wy
    V[2] = wz
    V[3] = om


# ---- one agent's tick (flightstack.runtime.agent) ------------------------------------------------------
#: rows of an agent's tick buffer T (10, 4)
G_BAR_W, G_BAR_I0, E_E, MU_OWN, VAR_OWN, PRIOR, MU_USED, U_C, U_E, V_CMD = range(10)


@kernel
def agent_sense(
    T: np.ndarray,
    u_e_prev: np.ndarray,
    dt_obs: float,
    g_wi: np.ndarray,
    f: np.ndarray,
    has_f: bool,
    P0: np.ndarray,
    cam: np.ndarray,
) -> bool:
    """Phase 1's math: ḡ_w,i ← ḡ_w,i exp(−û_e dt_obs) (if dt_obs > 0), ḡ_i0 = g_wi⁻¹ ḡ_w,i and, with
    features f, e_e = [p_e, sin θ_e] from ξ = J⁺(f − f̄). Writes T[G_BAR_W], T[G_BAR_I0], T[E_E] (zeros
    when not seen); returns v_i (the target was measured)."""
    if dt_obs > 0.0:
        neg = np.empty(4)
        for q in range(4):
            neg[q] = -u_e_prev[q]
        g = np.empty(4)
        integrate4(T[G_BAR_W], neg, dt_obs, g)
        T[G_BAR_W, :] = g
    relative4(g_wi, T[G_BAR_W], T[G_BAR_I0])
    T[E_E, :] = 0.0
    if not has_f:
        return False
    xi = np.empty(4)
    if estimation_error(f, T[G_BAR_I0], P0, cam, xi) != OK:
        return False
    T[E_E, 0], T[E_E, 1], T[E_E, 2], T[E_E, 3] = xi[0], xi[1], xi[2], math.sin(xi[3])
    return True


@kernel
def agent_act(
    T: np.ndarray,
    visible: bool,
    NG: np.ndarray,
    NMU: np.ndarray,
    NVAR: np.ndarray,
    NPRIOR: np.ndarray,
    n: int,
    mode: int,
    rule: int,
    g_d: np.ndarray,
    k_c: np.ndarray,
    k_e: np.ndarray,
    k_s: float,
    hover: bool,
) -> int:
    """Phase 2's math with the first n neighbour messages (ḡ_w,j, μ_j, var_j, σ_f,j² rows of NG, NMU,
    NVAR, NPRIOR): c_i, the fused μ (mode dgp), (u_c, u_e) and V = −Ad_{g_d} u_c (0 when hovering).
    Writes T[MU_USED], T[U_C], T[U_E], T[V_CMD]; returns how many experts entered μ."""
    c_i = np.empty(4)
    consensus_term(T[G_BAR_W], NG, n, c_i)
    n_fused = 0
    if mode == MODE_DGP:
        mus = np.empty((n + 1, 4))
        vs = np.empty((n + 1, 4))
        ps = np.empty((n + 1, 4))
        mus[0, :] = T[MU_OWN]
        vs[0, :] = T[VAR_OWN]
        ps[0, :] = T[PRIOR]
        for j in range(n):
            mus[j + 1, :] = NMU[j]
            vs[j + 1, :] = NVAR[j]
            ps[j + 1, :] = NPRIOR[j]
        var_f = np.empty(4)
        fuse(mus, vs, rule, ps, n + 1, T[MU_USED], var_f)
        n_fused = n + 1
    elif mode in (MODE_LOCAL, MODE_ORACLE):
        T[MU_USED, :] = T[MU_OWN]
        n_fused = 1
    else:
        T[MU_USED, :] = 0.0
    e_c = np.empty(4)
    th_c = control_error(g_d, T[G_BAR_I0], e_c)
    th_e = math.asin(max(-1.0, min(1.0, T[E_E, 3])))
    pursuit_law(e_c, th_c, T[E_E], th_e, c_i, T[MU_USED], k_c, k_e, k_s, visible, T[U_C], T[U_E])
    if hover:
        T[V_CMD, :] = 0.0
    else:
        drone_velocity_command(T[U_C], g_d, T[V_CMD])
    return n_fused


# ---- the compiled lock-step loop (ideal rig, in-process bus, safety off) ---------------------------------
@kernel
def world_advance(
    clock: np.ndarray,
    t_end: float,
    dt: float,
    target: np.ndarray,
    target_V: np.ndarray,
    drones: np.ndarray,
    drones_V: np.ndarray,
    substeps: int,
    prm: np.ndarray,
) -> None:
    """VirtualClock.sleep_until(t_end) of sim_backend.ideal: World.step(min(dt, t_end − t)) until t_end
    (the target re-evaluates its Duffing field `substeps` times per step; drones hold their command)."""
    tmp = np.empty(4)
    while clock[0] < t_end - 1e-12:
        h = min(dt, t_end - clock[0])
        hs = h / substeps
        for _ in range(substeps):
            duffing_body_velocity(target, prm, target_V)
            integrate4(target, target_V, hs, tmp)
            target[:] = tmp
        for i in range(drones.shape[0]):
            integrate4(drones[i], drones_V[i], h, tmp)
            drones[i, :] = tmp
        clock[0] += h


@kernel
def lockstep_chunk(
    k0: int,
    k1: int,
    dt: float,
    clock: np.ndarray,
    target: np.ndarray,
    target_V: np.ndarray,
    drones: np.ndarray,
    drones_V: np.ndarray,
    substeps: int,
    prm: np.ndarray,
    P0: np.ndarray,
    cams: np.ndarray,
    sees: np.ndarray,
    g_d: np.ndarray,
    gains: np.ndarray,
    mode: int,
    rule: int,
    oracle: bool,
    gp_inv_l: np.ndarray,
    gp_Z: np.ndarray,
    gp_sf2: np.ndarray,
    gp_alpha: np.ndarray,
    gp_L_inv: np.ndarray,
    gp_floor: np.ndarray,
    gp_n: np.ndarray,
    nb: np.ndarray,
    nb_n: np.ndarray,
    T: np.ndarray,
    u_e_prev: np.ndarray,
    t_prev: np.ndarray,
    has_prev: np.ndarray,
    bounds: np.ndarray,
    rec_f: np.ndarray,
    rec_t: np.ndarray,
    rec_g_w0: np.ndarray,
    rec_vis: np.ndarray,
    rec_nf: np.ndarray,
) -> int:
    """Ticks k0..k1−1 of flightstack.runtime.runner.run_mode on the ideal rig, the same kernels in the
    same order: cameras, every agent's phase 1 (observer, e_e, own prediction, the message checks), every
    agent's phase 2 (consensus, fusion, law, command), the row, the world to t + dt.

    State (updated in place): clock [t], target/target_V (4,), drones/drones_V (n, 4), agent buffers T
    (n, 10, 4), u_e_prev (n, 4), t_prev (n,), has_prev (n,). gains = [k_c (4), k_e (4), k_s].
    Rows (row k − k0 for tick k): rec_f (k1 − k0, n, 7, 4) = g_wi, ḡ_w,i, e_e, u_e, μ used, own var, V
    per drone; rec_t, rec_g_w0 (g_w0), rec_vis (v_i), rec_nf (experts fused). Returns the first
    tick not done: k1, or earlier at a tick the compiled path does not model (bad features, a message the
    bus would drop, a non-finite command), before anything of that tick changed; Python then flies it."""
    n = drones.shape[0]
    m2 = 2 * P0.shape[0]
    F = np.zeros((n, m2))
    has_f = np.zeros(n, dtype=np.bool_)
    vis = np.zeros(n, dtype=np.bool_)
    T_save = np.empty_like(T)
    g_i0 = np.empty(4)
    x = np.empty(4)
    body = np.empty(16)  # a message's 16 floats, as the bus checks them
    K = max(1, nb.shape[1])
    NG, NMU, NVAR, NPRIOR = np.empty((K, 4)), np.empty((K, 4)), np.empty((K, 4)), np.empty((K, 4))
    k_c, k_e, k_s = gains[0:4], gains[4:8], gains[8]
    for k in range(k0, k1):
        r = k - k0  # row of this tick in the rec_* arrays
        t = clock[0]
        for i in range(n):  # the ideal cameras (the world does not move during phase 1)
            has_f[i] = False
            if sees[i]:
                relative4(drones[i], target, g_i0)
                if measure(g_i0, P0, cams[i], F[i]):
                    for q in range(m2):
                        if not math.isfinite(F[i, q]):
                            return k
                    has_f[i] = True
        T_save[:] = T  # a tick handed to Python must find every agent's buffer as the last tick left it
        for i in range(n):
            dt_obs = t - t_prev[i] if has_prev[i] and t > t_prev[i] else 0.0
            vis[i] = agent_sense(T[i], u_e_prev[i], dt_obs, drones[i], F[i], has_f[i], P0, cams[i])
            if mode == MODE_NONE:
                T[i, MU_OWN, :], T[i, VAR_OWN, :], T[i, PRIOR, :] = 0.0, 1.0, 1.0
            elif oracle:
                x[:] = T[i, G_BAR_W]
                x[3] = wrap_angle(x[3])
                duffing_body_velocity(x, prm, T[i, MU_OWN])
                T[i, VAR_OWN, :], T[i, PRIOR, :] = ORACLE_VAR, 1.0
            else:
                gp_predict_one(
                    T[i, G_BAR_W], gp_inv_l[i], gp_Z[i], gp_sf2[i], gp_alpha[i], gp_L_inv[i], gp_floor[i],
                    gp_n[i], T[i, MU_OWN], T[i, VAR_OWN],
                )  # fmt: skip
                for d in range(4):
                    T[i, PRIOR, d] = gp_sf2[i, d if gp_sf2.shape[1] == 4 else 0]
            body[0:4], body[4:8], body[8:12], body[12:16] = (
                T[i, G_BAR_W],
                T[i, MU_OWN],
                T[i, VAR_OWN],
                T[i, PRIOR],
            )
            if message_check(body, bounds) != MSG_OK:  # the bus would drop it (or encode refuse it)
                T[:] = T_save
                return k
        for i in range(n):
            for jj in range(nb_n[i]):
                j = nb[i, jj]
                NG[jj, :], NMU[jj, :] = T[j, G_BAR_W], T[j, MU_OWN]
                NVAR[jj, :], NPRIOR[jj, :] = T[j, VAR_OWN], T[j, PRIOR]
            rec_nf[r, i] = agent_act(
                T[i], vis[i], NG, NMU, NVAR, NPRIOR, nb_n[i], mode, rule, g_d[i], k_c, k_e, k_s, False
            )
        for i in range(n):
            for q in range(4):
                if not math.isfinite(T[i, V_CMD, q]):
                    T[:] = T_save
                    return k
        for i in range(n):
            drones_V[i, :] = T[i, V_CMD]
            u_e_prev[i, :] = T[i, U_E]
            t_prev[i] = t
            has_prev[i] = True
            rec_f[r, i, 0, :] = drones[i]
            rec_f[r, i, 1, :] = T[i, G_BAR_W]
            rec_f[r, i, 2, :] = T[i, E_E]
            rec_f[r, i, 3, :] = T[i, U_E]
            rec_f[r, i, 4, :] = T[i, MU_USED]
            rec_f[r, i, 5, :] = T[i, VAR_OWN]
            rec_f[r, i, 6, :] = T[i, V_CMD]
            rec_vis[r, i] = vis[i]
        rec_t[r] = t
        rec_g_w0[r, :] = target
        world_advance(
            clock, t + dt, dt, target, target_V, drones, drones_V, 1 if substeps < 1 else substeps, prm
        )
    return k1


# ---- the prediction message's checks (flightstack.comms.messages, acceptance) ------------------------------
#: message_check's verdicts, in the order they are decided; flightstack.comms.messages.REASONS names them
#: (the drop reasons counted by the buses). Codes below MSG_OUT_OF_BOUNDS are the wire checks (decode
#: rejects, encode refuses), the others AcceptanceBounds (the receiver drops).
MSG_OK, MSG_NONFINITE_G, MSG_NONFINITE_MU, MSG_NONFINITE_VAR, MSG_NONFINITE_PRIOR = range(5)
MSG_VAR_NOT_POSITIVE = 5
MSG_OUT_OF_BOUNDS = MSG_VAR_BOUNDS = 6
MSG_MU_BOUNDS, MSG_POSE_BOUNDS = 7, 8


@kernel
def message_check(body: np.ndarray, bounds: np.ndarray) -> int:
    """The first defect of a prediction message's 16 floats body = [ḡ_w (4), μ (4), var (4), σ_f² (4)],
    as a MSG_* code (MSG_OK: none): per field in that order a non-finite element, then a variance ≤ 0 (the
    wire checks), then AcceptanceBounds.violation's checks in its order with bounds = [var_floor,
    var_ceiling, max_speed_mps, max_yaw_rate_rps, max_position_m, max_angle_rad] (AcceptanceBounds.packed).
    The compiled lock-step loop calls it too: a message it would fail hands that tick to Python."""
    for k in range(4):
        for q in range(4 * k, 4 * k + 4):
            if not math.isfinite(body[q]):
                return MSG_NONFINITE_G + k
    for q in range(8, 16):
        if body[q] <= 0.0:
            return MSG_VAR_NOT_POSITIVE
    for q in range(8, 16):
        if not (bounds[0] <= body[q] <= bounds[1]):
            return MSG_VAR_BOUNDS
    if max(abs(body[4]), abs(body[5]), abs(body[6])) > bounds[2] or abs(body[7]) > bounds[3]:
        return MSG_MU_BOUNDS
    if max(abs(body[0]), abs(body[1]), abs(body[2])) > bounds[4] or abs(body[3]) > bounds[5]:
        return MSG_POSE_BOUNDS
    return MSG_OK
