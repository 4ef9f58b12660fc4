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

from flightstack.paper.geometry import Pose, integrate_body_velocity
from flightstack.paper.projection import CameraModel, features_and_jacobian


def estimation_error(f: np.ndarray, g_bar_i0: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """e_e = J⁺ (f − f̄): the first-order estimate of vec(ḡ_i0⁻¹ g_i0) from the image, shape (4,).

    f (2m,) is the measured feature vector, f̄ = f(ḡ_i0) the predicted one; J (2m × 4) has full column
    rank for m ≥ 4 non-degenerate points, so J⁺ r is the least-squares solution of J ξ = r.
    """
    f_bar, J = features_and_jacobian(g_bar_i0, P0, cam)
    # J⁺ r = (JᵀJ)⁻¹ Jᵀ r for full column rank (4 × 4 solve; 10× cheaper than an SVD per tick)
    return np.linalg.solve(J.T @ J, J.T @ (f - f_bar))


def observer_step(g_bar_w: Pose, u_e: np.ndarray, dt: float) -> Pose:
    """ḡ_w,i(t + dt) = ḡ_w,i(t) exp(−û_e dt) for u_e (4,) held over dt seconds."""
    return integrate_body_velocity(g_bar_w, -np.asarray(u_e, dtype=float), dt)
