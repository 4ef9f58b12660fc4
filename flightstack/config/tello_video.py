"""The Tello SDK 3.0 video settings: `setfps`, `setresolution` and `setbitrate`, their arguments and what
each does, and the lab file's `video:` section that asks for them (`hardware.video`, lab-wide, and
`hardware.drones[].video`, per drone; docs/real-lab.md).

The arguments are those of the Tello SDK 3.0 User Guide
(https://dl.djicdn.com/downloads/RoboMaster+TT/Tello_SDK_3.0_User_Guide_en.pdf; its table as
harleylara/tello-python's README restates it, and djitellopy 2.5.0's `FPS_*`, `RESOLUTION_*`,
`BITRATE_*`): `setfps high|middle|low` (30, 15, 5 frames/s), `setresolution high|low` (720P, 480P),
`setbitrate 0..5` (0 auto, n: n Mbit/s). SDK 2.0 firmware answers `unknown command: setbitrate`
(DJITelloPy #144, #219). The frame sizes are measured ones: 720P is 960 × 720, 480P decodes as 648 × 478
(DJITelloPy #213, one user's Tello EDU). The drivers send the settings (drivers/tello/video_settings.py);
the emulator applies them (sim_backend/emulators/tello/).
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import field_validator

from flightstack.config.types import Strict

FPS_ARGS: dict[str, float] = {"high": 30.0, "middle": 15.0, "low": 5.0}
"""`setfps` argument → the stream's frame rate (frames/s)."""
RESOLUTION_ARGS: dict[str, tuple[int, int]] = {"high": (960, 720), "low": (648, 478)}
"""`setresolution` argument → the forward camera's decoded frame size (width, height) px: 720P as every
Tello streams it by default; 480P as DJITelloPy #213 measured it (648 × 478, not 640 × 480)."""
BITRATE_ARGS = range(0, 6)
"""`setbitrate` arguments: 0 the drone chooses (auto), n ≥ 1 a target of n Mbit/s."""
VERBS: dict[str, str] = {"resolution": "setresolution", "fps": "setfps", "bitrate": "setbitrate"}
"""The `video:` key → its SDK 3.0 command, in the order the driver sends them."""


def bit_rate_bps(arg: int) -> int | None:
    """The target bit rate (bit/s) of `setbitrate arg`; None for 0 (auto: the encoder's own choice)."""
    return arg * 1_000_000 if arg > 0 else None


def parse_argument(verb: str, arg: str) -> str | int | None:
    """The argument of SDK command `verb` (`setfps`, `setresolution`, `setbitrate`) as the lab file
    states it (a `setbitrate` argument as int), or None when the SDK 3.0 guide has no such argument."""
    if verb == "setfps":
        return arg if arg in FPS_ARGS else None
    if verb == "setresolution":
        return arg if arg in RESOLUTION_ARGS else None
    if verb == "setbitrate" and arg.isdigit() and int(arg) in BITRATE_ARGS:
        return int(arg)
    return None


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


@dataclass(frozen=True)
class VideoSetting:
    """One SDK 3.0 video setting a lab file asks of a drone: `key` is where the lab file sets it (e.g.
    `hardware.video.fps`), `command` the text sent (e.g. `setfps high`)."""

    key: str
    command: str


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
