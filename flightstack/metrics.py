"""Scalar metrics of a recorded run (pure functions of a Recording)."""

from __future__ import annotations

import numpy as np

from flightstack.runner import Recording


def error_vector_sq_norm(rec: Recording) -> np.ndarray:
    """‖e(t)‖² per tick with e = [e_c; e_e] ∈ R^{8n} (paper Sec. 2.4), shape (N,)."""
    k = rec.ticks_done
    return (rec.e_c[:k] ** 2).sum(axis=(1, 2)) + (rec.e_e[:k] ** 2).sum(axis=(1, 2))


def mode_metrics(rec: Recording) -> dict[str, object]:
    """The paper's 'squared mean of e' as the time mean of ‖e(t)‖², and its parts."""
    k = rec.ticks_done
    if k == 0:
        return {"ticks": 0}
    sq = error_vector_sq_norm(rec)
    ec = (rec.e_c[:k] ** 2).sum(axis=(1, 2))
    ee = (rec.e_e[:k] ** 2).sum(axis=(1, 2))
    pos_err = np.linalg.norm(rec.e_c[:k, :, :3], axis=2)
    return {
        "mean_sq_error": float(sq.mean()),
        "mean_sq_error_c": float(ec.mean()),
        "mean_sq_error_e": float(ee.mean()),
        "max_error_norm": float(np.sqrt(sq.max())),
        "final_error_norm": float(np.sqrt(sq[-1])),
        "rms_control_position_error_m": float(np.sqrt((pos_err**2).mean())),
        "visible_fraction": {str(i): float(rec.visible[:k, j].mean()) for j, i in enumerate(rec.drone_ids)},
        "ticks": int(k),
        "sim_seconds": float(rec.t[k - 1] - rec.t[0]) if k > 1 else 0.0,
        "wall_seconds": float(rec.wall_seconds),
        "bus_dropped": dict(rec.bus_dropped),
        "interrupted": bool(rec.interrupted),
    }
