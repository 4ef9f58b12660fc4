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
from flightstack.vision.camera_file import load_calibration


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
    """Read a recording: (video part or None, rc part or None). ValueError when a part is incomplete."""
    with np.load(Path(path), allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    parts: list[VideoRecord | RcRecord | None] = []
    for cls in (VideoRecord, RcRecord):
        names = [f.name for f in fields(cls)]
        have = [n for n in names if n in data]
        if have and len(have) < len(names):
            missing = ", ".join(n for n in names if n not in data)
            raise ValueError(f"{path}: the {cls.__name__} part lacks {missing}")
        kw = {n: (str(data[n]) if n == "calibration" else np.asarray(data[n], dtype=float)) for n in have}
        parts.append(cls(**kw) if have else None)  # type: ignore[arg-type]
    video, rc = parts
    assert video is None or isinstance(video, VideoRecord)
    assert rc is None or isinstance(rc, RcRecord)
    return video, rc


__all__ = ["RcRecord", "VideoRecord", "load_session", "save_session"]
