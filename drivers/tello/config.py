"""The Tello driver's settings, errors and reply parsers (used by drivers/tello/driver.py; SDK 2.0/3.0).

Times in seconds, temperature in °C, ports UDP.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from flightstack.drivers.tello.phase import PhaseThresholds
from flightstack.drivers.tello.rc import RcGains
from flightstack.drivers.tello.sdk_video import VideoSetting

DEFAULT_VIDEO_PORT = 11111
SETUP_ATTEMPTS = 4
"""Tries of each video set-up command (the SDK 3.0 video settings, `port`, `downvision 1`, `streamon`; all
idempotent): on a lossy Wi-Fi (2 % loss in bursts of 2 both ways) two tries of one command failed in a
few % of start-ups."""
TELLO_OWN_TIMEOUT_S = 15.0
"""A flying Tello that hears no command datagram for this long lands by itself; until then it flies its
last `rc` on (s; SDK 2.0/3.0 guides, "Safety Function"; DJITelloPy #141). What is left when no process of
ours can command it: the safety layer bounds its climb by it (hal.HoldsLastCommand)."""


SDK3_FIX = (
    "update the firmware (SDK 3.0: a Tello EDU or Talent), or fly without them (access-point mode with "
    "the default video port, the forward camera, no `video:` keys in the lab file)"
)
"""What to do when a mission needs SDK 3.0 features the drone's firmware lacks (`sdk3_features`)."""
DOWNWARD_FIX = (
    "only a Tello EDU (or Talent) on SDK 3.0 has the downward camera: fly one as this drone (a plain Tello "
    "can be a drone with the forward camera), or update this EDU's firmware"
)
"""What to do when a drone whose camera looks down has firmware below SDK 3.0 (a plain Tello, most likely):
in `paper_experiment` that is drone 1, the one that sees the target."""


def sdk3_fix(downward_camera: bool) -> str:
    """What to do when the firmware lacks the SDK 3.0 features a drone needs (DOWNWARD_FIX or SDK3_FIX)."""
    return DOWNWARD_FIX if downward_camera else SDK3_FIX


class TelloLinkError(ConnectionError):
    """The drone does not answer (connect) or its state stream stopped."""


class TelloCommandError(RuntimeError):
    """A blocking command (takeoff, land, streamon, …) failed or was not confirmed in time."""


@dataclass(frozen=True)
class TelloConfig:
    """One Tello. `host` is its IP; `control_port` 8889 and `state_port` 8890 on a real drone.

    `bind_ip`: local address of its command, state and video sockets ("" = all). `interface`: the
    network interface it is reached through (None: the routing table's choice); every socket that talks
    to it is bound to that interface (drivers/netif.py), so that drones sharing an address (access-point
    Tellos are all 192.168.10.1) are told apart by their adapters. Times in s, temperature in °C.
    """

    host: str
    control_port: int = 8889
    video_port: int = DEFAULT_VIDEO_PORT
    state_port: int = 8890
    bind_ip: str = ""
    interface: str | None = None
    rc_gains: RcGains = field(default_factory=RcGains)
    connect_timeout_s: float = 5.0
    command_timeout_s: float = 3.0
    takeoff_timeout_s: float = 20.0
    land_timeout_s: float = 15.0
    link_timeout_s: float = 1.0
    keepalive_s: float = 5.0
    """While takeoff() waits for its `ok`, a `battery?` probe every keepalive_s holds off the auto-land."""
    loop_hover_s: float = 0.5
    loop_land_s: float = 2.0
    land_resend_s: float = 0.5
    """During a land, `rc 0 0 0 0` + `land` this often (s) while telemetry is silent. The driver sends no
    rc on every tick during a land: whether a stick command cancels a Tello's landing is not documented,
    so a hover goes out only right before each land."""
    land_confirm_s: float = 1.5
    """A land is sent again (with `rc 0 0 0 0` first) only when, this long (s) after the last one, telemetry
    proves the drone holding its height (drivers/tello/phase.py `holding_after_land`): a lost land, or
    one lost with its hover on a one-way outage, leaves the drone on its last rc. A real Tello's descent
    shows 0.76 s after its `land` (vgz 1 dm/s, h one 10 cm step; 3 dm/s at 1.07 s) in the recorded
    flight (docs/drivers.md, "What a real Tello sends"): 1.5 s leaves it twice that."""
    rejoin_s: float = 1.0
    """While the state stream is silent, `command` at most this often (s): a drone that rebooted streams
    again only after it (drivers/tello/rejoin.py)."""
    quiet_s: float = 0.15
    min_battery_pct: float = 30.0
    max_temperature_c: float = 85.0
    min_wifi_snr: float = 20.0
    downward_camera: bool = False
    video_settings: tuple[VideoSetting, ...] = ()
    """SDK 3.0 video settings (`setfps`, `setresolution`, `setbitrate`) sent and confirmed at connect
    (drivers/tello/video_settings.py)."""
    phase: PhaseThresholds = field(default_factory=PhaseThresholds)

    def __post_init__(self) -> None:
        if not self.keepalive_s < TELLO_OWN_TIMEOUT_S:
            raise ValueError(f"keepalive_s must be below the Tello's {TELLO_OWN_TIMEOUT_S:g} s auto-land")
        if not 0.0 < self.loop_hover_s < self.loop_land_s < TELLO_OWN_TIMEOUT_S:
            raise ValueError(
                f"need 0 < loop_hover_s < loop_land_s < {TELLO_OWN_TIMEOUT_S:g} s (the Tello's own auto-land)"
            )
        if not (self.land_resend_s > 0.0 and self.land_confirm_s > 0.0 and self.rejoin_s > 0.0):
            raise ValueError("land_resend_s, land_confirm_s and rejoin_s must be > 0")
        if not self.quiet_s >= 0.15:
            raise ValueError("quiet_s must be at least 0.15 s")

    @property
    def sdk3_features(self) -> list[str]:
        """The SDK-3.0-only features this configuration needs (empty: SDK 2.0 will do)."""
        need = []
        if self.video_port != DEFAULT_VIDEO_PORT:
            need.append(f"per-drone video port {self.video_port} (`port`)")
        if self.downward_camera:
            need.append("downward camera (`downvision`)")
        if self.video_settings:
            need.append(f"video settings ({', '.join(f'`{v.command}`' for v in self.video_settings)})")
        return need


@dataclass(frozen=True)
class PreflightCheck:
    """One check; `warn`: a failed check is a warning (flyable, but look), not a blocker."""

    name: str
    ok: bool
    detail: str
    warn: bool = False


SDK_VERSIONS = {"13": "1.3", "20": "2.0", "30": "3.0"}
"""The `sdk?` answers of the SDK versions that exist (the 1.3, 2.0 and 3.0 user guides), as read. Any other
value (`70`, `59`: a battery or Wi-Fi reading crossed into its place) is no version."""


def parse_sdk(reply: str) -> str | None:
    """`sdk?` reply ("20", "30") → "2.0", "3.0" (`SDK_VERSIONS`); None for anything else."""
    return SDK_VERSIONS.get(reply.strip())


def parse_serial(reply: str) -> str | None:
    r = reply.strip()
    return r if r.isalnum() and 6 <= len(r) <= 24 and not r.isdigit() else None


def parse_int_reply(reply: str) -> str | None:
    r = reply.strip()
    return r if r.isdigit() and len(r) <= 3 else None
