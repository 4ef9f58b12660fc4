"""Rows of one mode → Rerun columns: the time series, the 3-D poses with their trails, the events.

The same `ModeLogger` serves a replay (one call with every selected row of a mode) and the live view
(many calls with the rows new since the last one): it keeps what spans calls (the trails). Rows come as
column arrays of a `Recording` (flightstack.recording.timeseries: poses [x, y, z, θ] in Σw, m and rad;
t the mission clock, s), already reduced to the ticks to log (flightstack.viewer.layout's rates); every
call sends columns (`send_columns`), never one `log` per row.
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from flightstack.events import mission_time, severity
from flightstack.paper.geometry import yaw_quaternions
from flightstack.viewer import layout

if TYPE_CHECKING:
    from rerun import RecordingStream


class MeanPredictor(Protocol):
    """A GP expert as far as the viewer needs it (flightstack.paper.gp.GPExpert)."""

    def predict(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


_QUIET_KEYS = ("t", "event", "drone", "mode")


def event_text(ev: Mapping[str, Any]) -> str:
    """One line for an event dict of a Recording: `event (drone i): key=value, ...`."""
    head = str(ev.get("event", "event"))
    if ev.get("drone") is not None:
        head += f" (drone {ev['drone']})"
    rest = [f"{k}={json.dumps(v, default=str)}" for k, v in ev.items() if k not in _QUIET_KEYS]
    return f"{head}: {', '.join(rest)}" if rest else head


def event_level(ev: Mapping[str, Any]) -> str:
    """TextLog level of an event: its flightstack.events.severity in Rerun's names."""
    return {"WARNING": "WARN"}.get(severity(ev), severity(ev))


def event_time(ev: Mapping[str, Any], default: float) -> float:
    """The event's mission time t (s), or `default` for an event without one (bus presence events and
    device events carry a monotonic stamp instead)."""
    t = mission_time(ev)
    return default if t is None else t


class Trail:
    """The path of one body over the last layout.TRAIL_S seconds, one point per 1/layout.TRAIL_HZ s."""

    def __init__(self) -> None:
        self._points: deque[tuple[float, np.ndarray]] = deque()
        self._last = -math.inf

    def strip(self, t: float, xyz: np.ndarray) -> np.ndarray:
        """The trail at mission time t (s) ending at the body's position xyz (m, Σw): (k, 3) float32."""
        if t - self._last >= 1.0 / layout.TRAIL_HZ - 1e-9:
            self._points.append((t, np.asarray(xyz, dtype=np.float32)))
            self._last = t
        while self._points and self._points[0][0] < t - layout.TRAIL_S:
            self._points.popleft()
        return np.array([p for _, p in self._points] + [xyz], dtype=np.float32)


class ModeLogger:
    """Logs one mode's rows under `/<mode>/` (layout) to `stream`.

    ids: the recording's drone ids (its drone axis). experts: drone id → its GP expert, to show each
    expert's own mean μ_i(ḡ_w,i) at the drone's estimate (the recording keeps only the fused μ the
    control law used and the own variance); used only when `uses_gp` (the mode predicts)."""

    def __init__(
        self,
        rr: ModuleType,
        stream: RecordingStream,
        mode: str,
        ids: Sequence[int],
        *,
        experts: Mapping[int, MeanPredictor] | None = None,
        uses_gp: bool = False,
    ) -> None:
        self.rr, self.stream, self.mode, self.ids = rr, stream, mode, list(ids)
        self.experts = dict(experts or {}) if uses_gp else {}
        bodies = ["target", *(f"drone{i}" for i in self.ids), *(f"estimate{i}" for i in self.ids)]
        self.trails = {b: Trail() for b in bodies}
        self._named: set[str] = set()
        self.rows: dict[str, int] = {}
        """Rows sent per entity path (non-static), for the summary and the tests."""

    # ---- helpers ------------------------------------------------------------------------------------
    def _send(self, path: str, t: np.ndarray, columns: Any) -> None:
        self.stream.send_columns(
            path, indexes=[self.rr.TimeColumn(layout.TIMELINE, duration=t)], columns=columns
        )
        self.rows[path] = self.rows.get(path, 0) + int(t.shape[0])

    def _scalars(
        self, path: str, t: np.ndarray, values: np.ndarray, names: Sequence[str] | None = None
    ) -> None:
        """values (K,) or (K, c): one series, or c series in one entity (one row per tick), named `names`
        (a static SeriesLines, sent with the path's first rows)."""
        v = np.asarray(values, dtype=float)
        if names is not None and path not in self._named:
            self.stream.log(path, self.rr.SeriesLines(names=list(names)), static=True)
            self._named.add(path)
        cols = self.rr.Scalars.columns(scalars=v.reshape(-1))
        if v.ndim == 2:
            cols = cols.partition([v.shape[1]] * v.shape[0])
        self._send(path, t, cols)

    # ---- time series --------------------------------------------------------------------------------
    def scalars(self, cols: Mapping[str, np.ndarray]) -> None:
        """Every row of `cols` (t (K,) and the Recording's per-drone arrays (K, n, ...)): per drone e_c and
        e_e (vec of the pose errors: m and sin θ) and their norms, the fused μ the control law used
        (`mu_fused`, body velocity of the target: m/s, rad/s), the own expert's μ (`mu_own`, GP modes with
        experts) and variance (`var_own`), `visible`, `n_fused`; the loop-health arrays when present (s)."""
        t = np.asarray(cols["t"], dtype=float)
        if t.shape[0] == 0:
            return
        m = self.mode
        for j, i in enumerate(self.ids):
            for name in ("e_c", "e_e"):
                if name in cols:
                    e = cols[name][:, j]
                    self._scalars(layout.series(m, name, i), t, e, layout.POSE_ERROR_NAMES)
                    self._scalars(layout.series(m, f"{name}_norm", i), t, np.linalg.norm(e, axis=-1))
            if "mu_used" in cols:
                self._scalars(
                    layout.series(m, "mu_fused", i), t, cols["mu_used"][:, j], layout.VELOCITY_NAMES
                )
            if "var_own" in cols:
                self._scalars(layout.series(m, "var_own", i), t, cols["var_own"][:, j], layout.VARIANCE_NAMES)
            expert = self.experts.get(i)
            if expert is not None and "g_bar_w" in cols:
                mean, _ = expert.predict(np.asarray(cols["g_bar_w"][:, j], dtype=float))
                self._scalars(layout.series(m, "mu_own", i), t, mean, layout.VELOCITY_NAMES)
            for name in ("visible", "n_fused"):
                if name in cols:
                    self._scalars(layout.series(m, name, i), t, cols[name][:, j])
        for name in layout.HEALTH_FIELDS:
            a = cols.get(name)
            if a is None:
                continue
            per_drone: list[tuple[int | None, np.ndarray]] = (
                [(None, a)] if a.ndim == 1 else [(i, a[:, j]) for j, i in enumerate(self.ids)]
            )
            for who, v in per_drone:
                ok = np.isfinite(v)  # NaN: not measured (compiled ticks, files written before loop health)
                if ok.any():
                    signal = f"loop/{name.removeprefix('loop_')}" if who is None else name
                    self._scalars(layout.series(m, signal, who), t[ok], v[ok])

    # ---- 3-D ---------------------------------------------------------------------------------------
    def poses(self, cols: Mapping[str, np.ndarray]) -> None:
        """Every row of `cols` (t, g_w0 (K, 4), g_wi and g_bar_w (K, n, 4)) as the bodies' transforms
        (translation in m, rotation about z by θ) and their trails."""
        t = np.asarray(cols["t"], dtype=float)
        if t.shape[0] == 0:
            return
        bodies: list[tuple[str, str, np.ndarray]] = [("target", layout.target(self.mode), cols["g_w0"])]
        for j, i in enumerate(self.ids):
            bodies.append((f"drone{i}", layout.drone(self.mode, i), cols["g_wi"][:, j]))
            bodies.append((f"estimate{i}", layout.estimate(self.mode, i), cols["g_bar_w"][:, j]))
        for name, path, g in bodies:
            g = np.asarray(g, dtype=float)
            self._send(
                path,
                t,
                self.rr.Transform3D.columns(translation=g[:, :3], quaternion=yaw_quaternions(g[:, 3])),
            )
            trail = self.trails[name]
            strips = [trail.strip(float(tk), g[k, :3]) for k, tk in enumerate(t)]
            self._send(layout.trail(self.mode, name), t, self.rr.LineStrips3D.columns(strips=strips))

    # ---- text ---------------------------------------------------------------------------------------
    def events(self, evs: Sequence[Mapping[str, Any]], t_default: float) -> None:
        """Each event as one TextLog row at its mission time (`t_default`, s, for one without)."""
        if not evs:
            return
        t = np.array([event_time(e, t_default) for e in evs])
        cols = self.rr.TextLog.columns(text=[event_text(e) for e in evs], level=[event_level(e) for e in evs])
        self._send(layout.events(self.mode), t, cols)

    def note(self, signal: str, text: str, t: float, level: str = "INFO") -> None:
        """One TextLog line under `/<mode>/<signal>` (bus drops, the live view's own drops)."""
        cols = self.rr.TextLog.columns(text=[text], level=[level])
        self._send(layout.series(self.mode, signal), np.array([t]), cols)
