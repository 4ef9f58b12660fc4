"""A latency calibration's recording (one .npz), what `flightstack calibrate latency --session` reads.

Video part (the camera's latency): `t_pose` (n,) the motion capture's sample times; `g_wi`, `g_w0`
(n, 4) the drone's and the target's poses in Σw ([x, y, z m, yaw rad]) at those times; `t_frames` (f,)
each decoded frame's stamp, its plain decode time on this computer (no latency subtracted); `pixels`
(f, m, 2) its markers' pixels (NaN where they were not all found); `calibration` the camera file's
path; `R_ic` (3, 3), `t_ic` (3,) the camera's mount in the body frame (FLU); `P0` (m, 3) the markers in
the target's frame (m). rc part (rc → motion): `t_cmd` (c,) when each rc was sent, `cmd` (c,) its yaw
rate (rc units), `t_yaw` (y,) and `yaw` (y,) the motion capture's yaw (rad, unwrapped). All times on
one clock (time.monotonic() of this computer, motion capture's samples stamped when taken).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from flightstack.calibration.latency import DelayEstimate, ResponseEstimate, estimate_command_delay
from flightstack.calibration.latency_video import predicted_pixels, video_delay
from flightstack.paper.geometry import Pose
from flightstack.recording.files import RunDirError, read_npz
from flightstack.vision.camera_file import load_calibration

MAX_SESSION_BYTES = 256_000_000
"""Bound on a session's arrays (bytes, uncompressed, read from the npz headers before anything is
allocated): a 60 s calibration flight holds a few MB."""
MAX_SESSION_SPAN_S = 3600.0
"""Bound on the time a session spans (s, all its times on one clock): a calibration flight is about 30 s."""
ROTATION_TOL = 1e-3
"""How far R_ic's columns may be from orthonormal (largest |RᵀR − I| entry): a mount written by hand with
four decimals (0.7071) passes."""


@dataclass
class VideoRecord:
    """The video part of a recording (module docstring)."""

    t_pose: np.ndarray
    g_wi: np.ndarray
    g_w0: np.ndarray
    t_frames: np.ndarray
    pixels: np.ndarray
    calibration: str
    R_ic: np.ndarray
    t_ic: np.ndarray
    P0: np.ndarray

    def estimate(self, max_lag_s: float = 1.0, window_s: float = 0.3) -> DelayEstimate:
        """The frames' delay behind the poses (calibration.latency_video.video_delay)."""
        cal = load_calibration(self.calibration)
        pred = np.array(
            [
                predicted_pixels(
                    cal, Pose.make(a[:3], a[3]), Pose.make(b[:3], b[3]), self.P0, self.R_ic, self.t_ic
                )
                for a, b in zip(self.g_wi, self.g_w0, strict=True)
            ]
        )
        found = [None if not np.isfinite(px).all() else px for px in self.pixels]
        return video_delay(self.t_pose, pred, self.t_frames, found, max_lag_s, window_s)


@dataclass
class RcRecord:
    """The rc part of a recording (module docstring)."""

    t_cmd: np.ndarray
    cmd: np.ndarray
    t_yaw: np.ndarray
    yaw: np.ndarray

    def estimate(self, max_delay_s: float = 0.5) -> ResponseEstimate:
        """How late each yaw-rate change acts (calibration.latency.estimate_command_delay)."""
        return estimate_command_delay(self.t_cmd, self.cmd, self.t_yaw, self.yaw, max_delay_s)


def save_session(path: str | Path, video: VideoRecord | None = None, rc: RcRecord | None = None) -> Path:
    """Write a recording (either part may be missing); returns its path."""
    arrays: dict[str, np.ndarray] = {}
    for part in (video, rc):
        if part is not None:
            arrays.update({f.name: np.asarray(getattr(part, f.name)) for f in fields(part)})
    p = Path(path)
    with p.open("wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
    return p


def load_session(path: str | Path) -> tuple[VideoRecord | None, RcRecord | None]:
    """Read a recording: (video part or None, rc part or None). ValueError (one line, without the path)
    when it is not a file, not an npz of numeric arrays within MAX_SESSION_BYTES, a part is incomplete,
    or an array has the wrong dtype, shape or a non-finite value (check_session)."""
    p = Path(path)
    if not p.exists():
        raise ValueError("no such file")
    if not p.is_file():
        raise ValueError("not a file (a session is one .npz file)")
    if p.stat().st_size == 0:
        raise ValueError("empty file, not a session (.npz)")
    try:
        data = read_npz(p, max_bytes=MAX_SESSION_BYTES)
    except RunDirError as exc:
        raise ValueError(exc.what) from None
    parts: list[VideoRecord | RcRecord | None] = []
    for cls in (VideoRecord, RcRecord):
        names = [f.name for f in fields(cls)]
        have = [n for n in names if n in data]
        if have and len(have) < len(names):
            missing = ", ".join(n for n in names if n not in data)
            raise ValueError(f"the {cls.__name__} part lacks {missing}")
        parts.append(_part(cls, data) if have else None)
    video, rc = parts
    assert video is None or isinstance(video, VideoRecord)
    assert rc is None or isinstance(rc, RcRecord)
    check_session(video, rc)
    return video, rc


def _part(cls: type[VideoRecord] | type[RcRecord], data: dict[str, np.ndarray]) -> VideoRecord | RcRecord:
    kw: dict[str, object] = {}
    for f in fields(cls):
        a = data[f.name]
        if f.name == "calibration":
            if a.dtype.kind not in "US" or a.shape != ():
                raise ValueError(f"calibration: a file name (text), got dtype {a.dtype} shape {a.shape}")
            text = str(a.item().decode("utf-8", "replace") if a.dtype.kind == "S" else a.item())
            if not text.strip():
                raise ValueError("calibration: an empty file name")
            kw[f.name] = text
        elif a.dtype.kind not in "iuf":
            raise ValueError(f"{f.name}: dtype {a.dtype}, not numbers")
        else:
            kw[f.name] = np.asarray(a, dtype=float)
    return cls(**kw)  # type: ignore[arg-type]


def _shape(name: str, a: np.ndarray, shape: tuple[int | None, ...], at_least: int = 1) -> tuple[int, ...]:
    """ValueError unless `a` has `shape` (None: any length >= at_least)."""
    ok = a.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, a.shape, strict=False))
    if not ok or any(s is None and d < at_least for s, d in zip(shape, a.shape, strict=False)):
        dims = [f"n>={at_least}" if s is None else str(s) for s in shape]
        want = f"({', '.join(dims)}{',' if len(dims) == 1 else ''})"
        raise ValueError(f"{name}: shape {a.shape}, expected {want}")
    return tuple(a.shape)


def _finite(name: str, a: np.ndarray, nan_ok: bool = False) -> None:
    bad = np.isinf(a) if nan_ok else ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"{name}: {int(bad.sum())} non-finite values")


def _times(name: str, t: np.ndarray, strict: bool) -> None:
    _finite(name, t)
    d = np.diff(t)
    if (d <= 0).any() if strict else (d < 0).any():
        raise ValueError(f"{name}: not {'increasing' if strict else 'in order'}")


def _rotation(name: str, R: np.ndarray) -> None:
    """ValueError unless R (3, 3, finite) is a rotation: orthonormal columns within ROTATION_TOL, det +1."""
    with np.errstate(over="ignore", invalid="ignore"):  # 1e300 entries: inf, refused below
        err = float(np.abs(R.T @ R - np.eye(3)).max())
        det = float(np.linalg.det(R))
    if not err <= ROTATION_TOL or not det > 0:
        raise ValueError(
            f"{name}: not a rotation (the camera's mount: orthonormal columns, determinant +1), got "
            f"determinant {det:.3g}, columns off orthonormal by {err:.3g}"
        )


def check_session(video: VideoRecord | None, rc: RcRecord | None) -> None:
    """ValueError naming the array when a part's arrays do not have the module docstring's shapes (at
    least 2 poses, 1 frame, 1 marker, 2 commands, 3 yaw samples), a time or pose is non-finite, the times
    are out of order, a pixel is infinite (NaN: not found), R_ic is not a rotation or the times span more
    than MAX_SESSION_SPAN_S."""
    times: list[np.ndarray] = []
    if video is not None:
        (n,) = _shape("t_pose", video.t_pose, (None,), 2)
        _shape("g_wi", video.g_wi, (n, 4))
        _shape("g_w0", video.g_w0, (n, 4))
        (f,) = _shape("t_frames", video.t_frames, (None,))
        (m, _) = _shape("P0", video.P0, (None, 3))
        _shape("pixels", video.pixels, (f, m, 2))
        _shape("R_ic", video.R_ic, (3, 3))
        _shape("t_ic", video.t_ic, (3,))
        _times("t_pose", video.t_pose, strict=True)
        _times("t_frames", video.t_frames, strict=False)
        for name in ("g_wi", "g_w0", "P0", "R_ic", "t_ic"):
            _finite(name, getattr(video, name))
        _rotation("R_ic", video.R_ic)
        _finite("pixels", video.pixels, nan_ok=True)
        times += [video.t_pose, video.t_frames]
    if rc is not None:
        (c,) = _shape("t_cmd", rc.t_cmd, (None,), 2)
        _shape("cmd", rc.cmd, (c,))
        (y,) = _shape("t_yaw", rc.t_yaw, (None,), 3)
        _shape("yaw", rc.yaw, (y,))
        _times("t_cmd", rc.t_cmd, strict=False)
        _times("t_yaw", rc.t_yaw, strict=True)
        _finite("cmd", rc.cmd)
        _finite("yaw", rc.yaw)
        times += [rc.t_cmd, rc.t_yaw]
    if times:
        span = max(float(t.max()) for t in times) - min(float(t.min()) for t in times)
        if span > MAX_SESSION_SPAN_S:
            raise ValueError(f"its times span {span:.3g} s, more than {MAX_SESSION_SPAN_S:g} s (one clock?)")


__all__ = [
    "MAX_SESSION_BYTES",
    "MAX_SESSION_SPAN_S",
    "ROTATION_TOL",
    "RcRecord",
    "VideoRecord",
    "check_session",
    "load_session",
    "save_session",
]
