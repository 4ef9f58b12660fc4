"""The lab file's `video:` section (`hardware.video`, lab-wide, and `hardware.drones[].video`, per drone;
docs/real-lab.md): which Tello SDK 3.0 video settings to ask of each drone (the commands and their
arguments: drivers/tello/sdk_video.py).
"""

from __future__ import annotations

from pydantic import field_validator

from flightstack.config.types import Strict
from flightstack.drivers.tello.sdk_video import BITRATE_ARGS, FPS_ARGS, RESOLUTION_ARGS, VERBS, VideoSetting


class TelloVideoSpec(Strict):
    """SDK 3.0 video settings (`hardware.video`, or a drone's own `video`, which overrides it key by key).
    Each key left out is not sent: the drone keeps its own setting. fps: `setfps` high, middle or low (30,
    15, 5 frames/s); resolution: `setresolution` high or low (720P 960 × 720, 480P 648 × 478, the forward
    camera's); bitrate: `setbitrate` 0 (auto) or 1–5 (Mbit/s). Needs SDK 3.0 (a Tello EDU or Talent)."""

    fps: str | None = None
    resolution: str | None = None
    bitrate: int | None = None

    @field_validator("fps", mode="before")
    @classmethod
    def _fps(cls, v: object) -> object:
        if v is not None and (not isinstance(v, str) or v not in FPS_ARGS):
            raise ValueError(
                f"{v!r} is no `setfps` argument of the Tello SDK 3.0; valid: high (30 frames/s), "
                "middle (15), low (5)"
            )
        return v

    @field_validator("resolution", mode="before")
    @classmethod
    def _resolution(cls, v: object) -> object:
        if v is not None and (not isinstance(v, str) or v not in RESOLUTION_ARGS):
            raise ValueError(
                f"{v!r} is no `setresolution` argument of the Tello SDK 3.0; valid: high (720P), low (480P)"
            )
        return v

    @field_validator("bitrate", mode="before")
    @classmethod
    def _bitrate(cls, v: object) -> object:
        if v is not None and (type(v) is not int or v not in BITRATE_ARGS):
            raise ValueError(
                f"{v!r} is no `setbitrate` argument of the Tello SDK 3.0; valid: 0 (auto) or 1-5 (Mbit/s)"
            )
        return v


def video_settings(
    lab: TelloVideoSpec | None, own: TelloVideoSpec | None, drone_id: int
) -> tuple[VideoSetting, ...]:
    """The settings of drone `drone_id`: its own `video` keys over the lab-wide ones, in VERBS' order."""
    out = []
    for name, verb in VERBS.items():
        for spec, where in ((own, f"hardware.drones[id {drone_id}].video"), (lab, "hardware.video")):
            value = None if spec is None else getattr(spec, name)
            if value is not None:
                out.append(VideoSetting(f"{where}.{name}", f"{verb} {value}"))
                break
    return tuple(out)
