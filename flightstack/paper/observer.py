"""Visual motion observer (Hatanaka & Fujita; paper Sec. 2.4 and DESIGN §4).

The observer keeps ḡ_w,i = g_wi ḡ_i0, the drone's estimate of the target pose in the world frame Σw.
With the paper's observer  dḡ_i0/dt = −V̂_wi ḡ_i0 − ḡ_i0 û_ei  and ġ_wi = g_wi V̂_wi one gets

    d ḡ_w,i / dt = −ḡ_w,i û_ei ,

so ḡ_w,i moves with body velocity −u_ei, independent of the drone's own motion. Keeping the state in Σw
and reading ḡ_i0 = g_wi⁻¹ ḡ_w,i from the measured own pose is the same observer in continuous time, and
in discrete time it does not depend on how well the drone tracked its velocity command. With u_e held
over a tick the update ḡ_w,i ← ḡ_w,i exp(−û_e dt) is exact.
"""

from __future__ import annotations

import numpy as np

from flightstack.paper import kernels as kern
from flightstack.paper.geometry import Pose, integrate_body_velocity
from flightstack.paper.projection import CameraModel, TargetNotVisibleError


def estimation_error(f: np.ndarray, g_bar_i0: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """e_e = J⁺ (f − f̄): the first-order estimate of vec(ḡ_i0⁻¹ g_i0) from the image, shape (4,).

    f (2m,) is the measured feature vector, f̄ = f(ḡ_i0) the predicted one; J (2m × 4) has full column
    rank for m ≥ 4 non-degenerate points, so J⁺ r is the least-squares solution of J ξ = r, computed from
    the 4×4 normal equations (kernels.estimation_error). Raises TargetNotVisibleError if a point of the
    estimate is behind the camera, numpy.linalg.LinAlgError if JᵀJ is singular.
    """
    P = np.ascontiguousarray(P0, dtype=float)
    fv = np.ascontiguousarray(f, dtype=float).reshape(-1)
    if P.ndim != 2 or P.shape[1] != 3 or fv.shape != (2 * P.shape[0],):
        raise ValueError(f"need P0 (m, 3) and f (2m,), got {P.shape} and {fv.shape}")
    xi = np.empty(4)
    g = np.array((g_bar_i0.p[0], g_bar_i0.p[1], g_bar_i0.p[2], g_bar_i0.theta), dtype=float)
    status = kern.estimation_error(fv, g, P, cam.packed, xi)
    if status == kern.NOT_VISIBLE:
        raise TargetNotVisibleError("estimated feature point behind the camera")
    if status == kern.SINGULAR:
        raise np.linalg.LinAlgError("JᵀJ is singular (degenerate feature points)")
    return xi


def observer_step(g_bar_w: Pose, u_e: np.ndarray, dt: float) -> Pose:
    """ḡ_w,i(t + dt) = ḡ_w,i(t) exp(−û_e dt) for u_e (4,) held over dt seconds."""
    return integrate_body_velocity(g_bar_w, -np.asarray(u_e, dtype=float), dt)
