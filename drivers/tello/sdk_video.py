"""The Tello SDK 3.0 video commands: `setfps`, `setresolution` and `setbitrate`, their arguments and what
each does, and one setting as the driver sends it (`VideoSetting`).

The arguments are those of the Tello SDK 3.0 User Guide
(https://dl.djicdn.com/downloads/RoboMaster+TT/Tello_SDK_3.0_User_Guide_en.pdf; its table as
harleylara/tello-python's README restates it, and djitellopy 2.5.0's `FPS_*`, `RESOLUTION_*`,
`BITRATE_*`): `setfps high|middle|low` (30, 15, 5 frames/s), `setresolution high|low` (720P, 480P),
`setbitrate 0..5` (0 auto, n: n Mbit/s). SDK 2.0 firmware answers `unknown command: setbitrate`
(DJITelloPy #144, #219). The frame sizes are measured ones: 720P is 960 × 720, 480P decodes as 648 × 478
(DJITelloPy #213, one user's Tello EDU). The lab file asks for them (flightstack.config.tello_video); the
driver sends them (drivers/tello/video_settings.py); the emulator applies them (sim_backend/emulators/tello/).
"""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass(frozen=True)
class VideoSetting:
    """One SDK 3.0 video setting a lab file asks of a drone: `key` is where the lab file sets it (e.g.
    `hardware.video.fps`), `command` the text sent (e.g. `setfps high`)."""

    key: str
    command: str
