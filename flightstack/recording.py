"""The time series of one run (every tick, every drone) and its on-disk form (npz)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flightstack.geometry import compose_arrays, inverse_arrays, vec_arrays

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
    "n_fused",
    "wall_t",
)


@dataclass
class Recording:
    """Arrays indexed [tick, drone, component]; poses are [x, y, z, θ] in Σw (m, rad); t in s."""

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
    V_cmd: np.ndarray  # (N, n, 4) body-velocity command sent (m/s, rad/s)
    visible: np.ndarray  # (N, n) bool
    n_fused: np.ndarray  # (N, n) int: predictions fused (own + fresh neighbours) by each agent
    wall_t: np.ndarray  # (N,) wall-clock time.time() of each tick (s since the epoch; across processes)
    ticks_done: int = 0
    bus_dropped: dict[str, int] = field(default_factory=dict)
    wall_seconds: float = 0.0
    interrupted: bool = False
    error: str | None = None
    events: list[dict[str, object]] = field(default_factory=list)
    vision_rejections: dict[str, dict[str, int]] = field(default_factory=dict)

    @staticmethod
    def empty(mode: str, ids: list[int], n_ticks: int) -> Recording:
        n = len(ids)

        def z() -> np.ndarray:
            return np.zeros((n_ticks, n, 4))

        return Recording(
            mode,
            list(ids),
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
            np.zeros((n_ticks, n), dtype=int),
            np.zeros(n_ticks),
        )

    def truncated(self) -> Recording:
        """Only the ticks actually flown (after an interrupt or an error)."""
        k = self.ticks_done
        out = Recording(self.mode, self.drone_ids, *(getattr(self, f)[:k] for f in ARRAY_FIELDS))
        for name in (
            "ticks_done",
            "bus_dropped",
            "wall_seconds",
            "interrupted",
            "error",
            "events",
            "vision_rejections",
        ):
            setattr(out, name, getattr(self, name))
        return out

    def save(self, path: str) -> None:
        np.savez_compressed(
            path,
            mode=self.mode,
            drone_ids=np.array(self.drone_ids),
            **{f: getattr(self, f)[: self.ticks_done] for f in ARRAY_FIELDS},
        )

    @staticmethod
    def load(path: str) -> Recording:
        """Read a recording written by `save` (arrays only; events and counters live in the run dir)."""
        with np.load(path) as z:
            N = z["t"].shape[0]
            n = len(z["drone_ids"])
            defaults = {"n_fused": np.zeros((N, n), dtype=int), "wall_t": np.zeros(N)}  # older files
            arrays = {f: z[f] if f in z else defaults[f] for f in ARRAY_FIELDS}
            rec = Recording(str(z["mode"]), [int(i) for i in z["drone_ids"]], **arrays)
        rec.ticks_done = rec.t.shape[0]
        return rec

    def fill_true_errors(self, g_d: np.ndarray) -> None:
        """e_c = vec(g_d⁻¹ ḡ_i0) and the true e_e = vec(ḡ_i0⁻¹ g_i0) from the recorded poses (vectorised).

        g_d: (n, 4) desired poses [x, y, z, θ] of the drones in recording order.
        """
        k = self.ticks_done
        inv_wi = inverse_arrays(self.g_wi[:k])
        g_bar_i0 = compose_arrays(inv_wi, self.g_bar_w[:k])
        g_i0 = compose_arrays(inv_wi, self.g_w0[:k, None, :])
        self.e_c[:k] = vec_arrays(compose_arrays(inverse_arrays(g_d)[None], g_bar_i0))
        self.e_e[:k] = vec_arrays(compose_arrays(inverse_arrays(g_bar_i0), g_i0))

    def true_relative_error(self, g_d: np.ndarray) -> np.ndarray:
        """vec(g_d⁻¹ g_i0) per tick and drone from the true poses: how far each drone is from its
        desired pose relative to the target, (N, n, 4)."""
        k = self.ticks_done
        g_i0 = compose_arrays(inverse_arrays(self.g_wi[:k]), self.g_w0[:k, None, :])
        return vec_arrays(compose_arrays(inverse_arrays(g_d)[None], g_i0))
