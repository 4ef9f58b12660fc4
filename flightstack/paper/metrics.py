"""Scalar metrics of a recorded run (pure functions of a Recording)."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from flightstack.config.mission import Mission
from flightstack.recording.timeseries import Recording


def error_vector_sq_norm(rec: Recording) -> np.ndarray:
    """‖e(t)‖² per tick with e = [e_c; e_e] ∈ R^{8n} (paper Sec. 2.4), shape (N,)."""
    k = rec.ticks_done
    return (rec.e_c[:k] ** 2).sum(axis=(1, 2)) + (rec.e_e[:k] ** 2).sum(axis=(1, 2))


def fence_excursion(rec: Recording, lo: np.ndarray, hi: np.ndarray) -> float:
    """Largest distance (m) any drone's true position was outside the box [lo, hi] (0 if never)."""
    p = rec.g_wi[: rec.ticks_done, :, :3]
    out = np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)
    return float(np.linalg.norm(out, axis=2).max()) if p.size else 0.0


def mode_metrics(rec: Recording, mission: Mission | None = None) -> dict[str, Any]:
    """The paper's 'squared mean of e' as the time mean of ‖e(t)‖², its parts, and flight facts."""
    k = rec.ticks_done
    if k == 0:
        return {"ticks": 0, "interrupted": bool(rec.interrupted), "error": rec.error}
    sq = error_vector_sq_norm(rec)
    ec = (rec.e_c[:k] ** 2).sum(axis=(1, 2))
    ee = (rec.e_e[:k] ** 2).sum(axis=(1, 2))
    pos_err = np.linalg.norm(rec.e_c[:k, :, :3], axis=2)
    dt = float(np.median(np.diff(rec.t[:k]))) if k > 1 else 0.0
    out: dict[str, object] = {
        "mean_sq_error": float(sq.mean()),
        "mean_sq_error_c": float(ec.mean()),
        "mean_sq_error_e": float(ee.mean()),
        "max_error_norm": float(np.sqrt(sq.max())),
        "final_error_norm": float(np.sqrt(sq[-1])),
        "rms_control_position_error_m": float(np.sqrt((pos_err**2).mean())),
        "visible_fraction": {str(i): float(rec.visible[:k, j].mean()) for j, i in enumerate(rec.drone_ids)},
        "seen_seconds": {str(i): float(rec.visible[:k, j].sum() * dt) for j, i in enumerate(rec.drone_ids)},
        "ticks": int(k),
        "sim_seconds": float(rec.t[k - 1] - rec.t[0]) if k > 1 else 0.0,
        "wall_seconds": float(rec.wall_seconds),
        "bus_dropped": dict(rec.bus_dropped),
        "interrupted": bool(rec.interrupted),
        "error": rec.error,
        "vision_rejections": rec.vision_rejections,
    }
    if mission is not None:
        g_d = np.array([[*d.desired_pose.p, d.desired_pose.theta] for d in mission.drones])
        rel = rec.true_relative_error(g_d)
        out["mean_position_error_m"] = float(np.linalg.norm(rel[:, :, :3], axis=2).mean())
        out["mean_position_error_per_drone_m"] = {
            str(i): float(np.linalg.norm(rel[:, j, :3], axis=1).mean()) for j, i in enumerate(rec.drone_ids)
        }
        if mission.safety.enabled:
            out["max_fence_excursion_m"] = fence_excursion(
                rec, np.array(mission.safety.fence_lo), np.array(mission.safety.fence_hi)
            )
        out["safety_event_counts"] = dict(
            Counter(str(e.get("kind")) for e in rec.events if e.get("event") == "safety")
        )
    return out
