"""Scalar metrics of a recorded run (pure functions of its Recordings) and metrics.json's contents.

The paper (Sec. 4) reports "the squared mean of e" without defining it; two readings are reported:

- `mean_sq_error`: the time mean of the squared norm, (1/T)∫‖e(t)‖² dt (how large e is on average);
- `sq_mean_error`: the squared norm of the time mean, ‖(1/T)∫e(t) dt‖², the literal reading (a bias: an
  error that oscillates around zero has a small squared mean but a large mean square).

Both use e = [e_c; e_e] ∈ R^{8n} over all drones and components, the true e_e, and the arithmetic mean over
the recorded ticks (the rectangle rule of the integral; ticks are evenly spaced). By Jensen's inequality
sq_mean_error ≤ mean_sq_error.

Oscillation (the lab): after a transient of min(TRANSIENT_S, TRANSIENT_FRACTION · run length), per drone,
the standard deviation over time of the true position error norm ‖p_err(t)‖ and its total variation per
second Σ_k |‖p_err(t_{k+1})‖ − ‖p_err(t_k)‖| / (t_last − t_first).

Envelope (how the error grows or settles): the largest true position error norm over the drones in each
consecutive window of ENVELOPE_WINDOW_S from the mode's first tick (flightstack.analysis.stability
classifies a run from it).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from flightstack.analysis.loop_health import loop_health
from flightstack.config.mission import Mission
from flightstack.paper.control import Gains
from flightstack.paper.gain_analysis import gain_condition, region_samples
from flightstack.paper.gp import GPExpert
from flightstack.recording.timeseries import Recording

PAPER_SQ_MEAN_ERROR = {"none": 3.0e-7, "local": 3.6e-8, "dgp": 5.6e-9}
"""The paper's "squared mean of e" of its simulation (Sec. 5) per mode, compared with `sq_mean_error`, the
literal reading. The absolute values cannot match under the stated gains (docs: the paper comparison):
with no GP the target's yaw rate ω₀ leaves sin θ_c = ω₀/k_c and sin θ_e = ω₀(1/k_c + 1/k_e) per drone."""

PAPER_RATIOS = {f"{m}/dgp": PAPER_SQ_MEAN_ERROR[m] / PAPER_SQ_MEAN_ERROR["dgp"] for m in ("none", "local")}
"""The paper's ratios none/dgp and local/dgp of its squared means (of `sq_mean_error`)."""


def error_vector_sq_norm(rec: Recording) -> np.ndarray:
    """‖e(t)‖² per tick with e = [e_c; e_e] ∈ R^{8n} (paper Sec. 2.4), shape (N,)."""
    k = rec.ticks_done
    return (rec.e_c[:k] ** 2).sum(axis=(1, 2)) + (rec.e_e[:k] ** 2).sum(axis=(1, 2))


def error_vector_time_mean(rec: Recording) -> np.ndarray:
    """(1/N) Σ_k e(t_k): the time mean of e = [e_c; e_e] over the recorded ticks, shape (n, 8)."""
    k = rec.ticks_done
    return np.concatenate([rec.e_c[:k].mean(axis=0), rec.e_e[:k].mean(axis=0)], axis=1)


TRANSIENT_S = 10.0
"""Longest transient (s) left out of the oscillation measures."""
TRANSIENT_FRACTION = 0.25
"""...unless the run is short: then this fraction of its length is left out."""


def default_transient_s(run_seconds: float) -> float:
    """The transient left out of the oscillation measures: min(10 s, 25 % of the run)."""
    return min(TRANSIENT_S, TRANSIENT_FRACTION * max(run_seconds, 0.0))


def oscillation(
    t: np.ndarray, pos_err: np.ndarray, transient_s: float | None = None
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(std, total variation per second, transient) of a position error norm per drone after the transient.

    t: (N,) tick times (s); pos_err: (N, n) ‖p_err‖ per tick and drone (m); transient_s: the time left out
    from t[0] (default: `default_transient_s` of the run's length). std is the population standard deviation
    over the kept ticks (m); TV/s is Σ|Δ‖p_err‖| over consecutive kept ticks divided by their time span
    (m/s). None when fewer than 2 ticks remain or they span no time."""
    if t.shape[0] < 2:
        return None
    tr = default_transient_s(float(t[-1] - t[0])) if transient_s is None else float(transient_s)
    keep = (t - t[0]) >= tr
    tk, pk = t[keep], pos_err[keep]
    if tk.shape[0] < 2 or tk[-1] <= tk[0]:
        return None
    tv = np.abs(np.diff(pk, axis=0)).sum(axis=0) / float(tk[-1] - tk[0])
    return pk.std(axis=0), tv, tr


ENVELOPE_WINDOW_S = 5.0
"""Length (s) of the windows of the error envelope."""


def error_envelope(t: np.ndarray, pos_err: np.ndarray, window_s: float = ENVELOPE_WINDOW_S) -> list[float]:
    """Per consecutive window of `window_s` from t[0]: the largest ‖p_err‖ over its ticks and the drones (m).

    t: (N,) tick times (s); pos_err: (N, n) ‖p_err‖ per tick and drone (m). A non-finite value makes its
    window's entry non-finite (nan propagates through max); an empty window (a gap) is left out."""
    if t.shape[0] == 0:
        return []
    idx = np.floor((t - t[0]) / window_s).astype(np.int64)
    per_tick = pos_err.max(axis=1) if pos_err.ndim == 2 else pos_err
    return [float(per_tick[idx == w].max()) for w in np.unique(idx)]


ON_THE_FLOOR_M = 0.15
"""A drone whose true height is below this (m) stands on the floor: landed, not outside the fence."""


def fence_excursion(rec: Recording, lo: np.ndarray, hi: np.ndarray) -> float:
    """Largest distance (m) any drone's true position was outside the box [lo, hi] while off the floor
    (0 if never): a drone that landed during the mode sits below the box's floor, and that is no
    excursion."""
    p = rec.g_wi[: rec.ticks_done, :, :3]
    out = np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)
    dist = np.where(p[..., 2] >= ON_THE_FLOOR_M, np.linalg.norm(out, axis=2), 0.0)
    return float(dist.max()) if p.size else 0.0


def mode_metrics(
    rec: Recording, mission: Mission | None = None, transient_s: float | None = None
) -> dict[str, Any]:
    """Both readings of the paper's 'squared mean of e' (module docstring), the parts of the mean square,
    and flight facts; given the mission, the true position error and its oscillation after `transient_s`
    (default: min(10 s, 25 % of the run))."""
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
        "sq_mean_error": float((error_vector_time_mean(rec) ** 2).sum()),
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
        **({"video_counts": rec.video_counts} if rec.video_counts else {}),
        **({"vision_gate": rec.vision_gate} if rec.vision_gate else {}),
        # did this computer keep dt (hardware, emulated lab); on a simulated clock only how fast it ran
        "loop_health": loop_health(
            rec,
            mission.dt_s if mission is not None else dt,
            real_time=mission is not None and not mission.simulated,
        ),
    }
    if mission is not None:
        g_d = np.array([[*d.desired_pose.p, d.desired_pose.theta] for d in mission.drones])
        rel = rec.true_relative_error(g_d)
        out["mean_position_error_m"] = float(np.linalg.norm(rel[:, :, :3], axis=2).mean())
        out["mean_position_error_per_drone_m"] = {
            str(i): float(np.linalg.norm(rel[:, j, :3], axis=1).mean()) for j, i in enumerate(rec.drone_ids)
        }
        rel_norm = np.linalg.norm(rel[:, :, :3], axis=2)
        out["error_envelope"] = {"window_s": ENVELOPE_WINDOW_S, "max_m": error_envelope(rec.t[:k], rel_norm)}
        osc = oscillation(rec.t[:k], rel_norm, transient_s)
        if osc is not None:
            std, tv, tr = osc
            out["oscillation_transient_s"] = tr
            out["position_error_std_m"] = float(std.mean())
            out["position_error_std_per_drone_m"] = {
                str(i): float(std[j]) for j, i in enumerate(rec.drone_ids)
            }
            out["position_error_tv_mps"] = float(tv.mean())
            out["position_error_tv_per_drone_mps"] = {
                str(i): float(tv[j]) for j, i in enumerate(rec.drone_ids)
            }
        if mission.safety.enabled:
            out["max_fence_excursion_m"] = fence_excursion(
                rec, np.array(mission.safety.fence_lo), np.array(mission.safety.fence_hi)
            )
        out["safety_event_counts"] = dict(
            Counter(str(e.get("kind")) for e in rec.events if e.get("event") == "safety")
        )
    return out


NO_EXPERTS = "no GP expert was trained or loaded (kappa needs the experts' Lipschitz constant)"
"""metrics.json → gain_condition.reason of a run without experts (then "evaluated": false)."""


def build_metrics(
    mission: Mission,
    recordings: Mapping[str, Recording],
    experts: Mapping[int, GPExpert],
    gp_info: dict[str, object],
    wall: float,
    *,
    interrupted: bool = False,
    error: str | None = None,
) -> dict[str, Any]:
    """metrics.json of a run: per mode (those of compare_modes; every recorded one if none of them was
    recorded, e.g. an agent's run or a failed data run), the gain condition, GP facts, safety events, and
    for the paper's Duffing target with a dgp run the ratios none/dgp and local/dgp of each error metric
    (`ratios.<metric>`), and `paper`: our sq_mean_error (‖time mean of e‖², the reading of the paper's
    "squared mean of e") per mode and its ratios, each beside the paper's value of the same quantity
    (flightstack.analysis.metrics explains both readings).

    recordings: mode -> its recording; experts: drone id -> its GP expert (none: κ is not evaluated);
    gp_info: the training's facts; wall: wall time of the whole run (s); interrupted, error: how the
    run ended. A recording of only some of the mission's drones (an agent's)
    gets the metrics that need no mission. `gain_condition` has "evaluated": true and Theorem 1's numbers
    when experts holds experts; without any (no GP mode, a data run cut short, an agent flying
    `none`) it is {"evaluated": false, "reason", "region_lo", "region_hi"}: no κ or L_μ is made up."""
    ids = [d.id for d in mission.drones]
    shown = [m for m in recordings if m in mission.compare_modes] or list(recordings)
    modes: dict[str, dict[str, Any]] = {
        m: mode_metrics(recordings[m], mission if recordings[m].drone_ids == ids else None) for m in shown
    }
    gains = Gains.make(mission.gains.k_c, mission.gains.k_e, mission.gains.k_s)
    ref = recordings.get("none") or next(iter(recordings.values()), None)
    if ref is not None and ref.ticks_done > 0:
        xyz = ref.g_w0[: ref.ticks_done, :3]
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    else:
        lo, hi = np.full(3, -1.0), np.full(3, 1.0)
    region = {"region_lo": lo.tolist(), "region_hi": hi.tolist()}
    gc: dict[str, object] = {"evaluated": False, "reason": NO_EXPERTS, **region}
    if experts:  # L_μ and Δ̄ are the experts': without one, κ would be a made-up number
        ga = mission.gain_analysis
        cond = gain_condition(
            gains,
            len(mission.drones),
            mission.edge_index_pairs(),
            [d.sees_target for d in mission.drones],
            list(experts.values()),
            region_samples(lo, hi, ga.samples, mission.seed),
            ga.gamma_sq,
            ga.beta,
            ga.eta,
        )
        gc = {"evaluated": True, **cond.to_dict(), **region}
    out: dict[str, object] = {
        "mission": mission.name,
        "modes": modes,
        "gain_condition": gc,
        "gp": gp_info,
        "sim_seconds": float(sum(m.get("sim_seconds", 0.0) for m in modes.values())),
        "wall_seconds": wall,
        "seed": mission.seed,
        "interrupted": interrupted,
        "error": error,
        "safety_events": [
            {k: v for k, v in e.items() if k != "event"}
            for r in recordings.values()
            for e in r.events
            if e.get("event") == "safety"
        ],
    }
    if "dgp" in modes and modes["dgp"].get("mean_sq_error") and mission.target.motion == "duffing":
        ratios = {k: _ratios(modes, k) for k in ("mean_sq_error", "sq_mean_error") if modes["dgp"].get(k)}
        out["ratios"] = ratios
        if "sq_mean_error" in ratios:
            out["paper"] = {
                "metric": "sq_mean_error",
                "modes": {
                    m: {"ours": float(modes[m]["sq_mean_error"]), "paper": PAPER_SQ_MEAN_ERROR[m]}
                    for m in PAPER_SQ_MEAN_ERROR
                    if "sq_mean_error" in modes.get(m, {})
                },
                "ratios": {
                    k: {"ours": v, "paper": PAPER_RATIOS[k]} for k, v in ratios["sq_mean_error"].items()
                },
            }
    return out


def _ratios(modes: Mapping[str, Mapping[str, Any]], key: str) -> dict[str, float]:
    """{"none/dgp": ..., "local/dgp": ...} of metric `key` (the modes flown; dgp's value is not 0)."""
    d = float(modes["dgp"][key])
    return {f"{m}/dgp": float(modes[m][key]) / d for m in ("none", "local") if m in modes and key in modes[m]}
