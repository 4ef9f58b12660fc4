"""The SDK 3.0 video settings of a lab file (`setresolution`, `setfps`, `setbitrate`; TelloConfig's
`video_settings`, flightstack.config.tello_video), sent by `TelloDriver.connect()` after `command` and
`sdk?`, before any `streamon`, each confirmed by `ok`.

A refusal is never ignored: an answer other than `ok` (`unknown command: setfps` from SDK 2.0 firmware,
`error`, ...) or none within SETUP_ATTEMPTS tries of `command_timeout_s` each is kept in the outcome;
preflight FAILs one line per such setting (`refusal`: the key, the drone, the reply and the fix), and
`TelloCamera.start()` refuses to stream. On firmware without SDK 3.0 (`sdk?` below 30, or unanswered)
nothing is sent: each setting is refused before sending, as `port` and `downvision` are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from flightstack.drivers.tello.config import SETUP_ATTEMPTS, TelloConfig
from flightstack.drivers.tello.sdk_video import VideoSetting
from flightstack.drivers.tello.status import DriverEvents

FIX = "remove the key or update the firmware (the SDK 3.0 video settings need a Tello EDU or Talent)"


class Answering(Protocol):
    """What sending a setting needs of the driver's exchange (drivers/tello/exchange.py)."""

    def answer(self, command: str, timeout: float, attempts: int = 2) -> str | None: ...


@dataclass(frozen=True)
class SettingOutcome:
    """What became of one setting: `reply` is the drone's answer (None: none came, or `why_unsent`
    says why it was not sent)."""

    setting: VideoSetting
    reply: str | None
    why_unsent: str | None = None

    @property
    def ok(self) -> bool:
        return self.why_unsent is None and self.reply is not None and self.reply.strip().lower() == "ok"

    def refusal(self, host: str) -> str:
        """One line: the key, the command, the drone and what it answered, and the fix."""
        s = self.setting
        if self.why_unsent is not None:
            what = f"not sent to Tello {host}: {self.why_unsent}"
        elif self.reply is None:
            what = f"Tello {host} did not answer ({SETUP_ATTEMPTS} tries)"
        else:
            what = f"Tello {host} answered {self.reply.strip()!r}"
        return f"{s.key} (`{s.command}`): {what}; {FIX}"


def has_sdk3(sdk_version: str | None) -> bool:
    """True when the `sdk?` answer (parsed: "3.0") means SDK 3.0 or later."""
    return sdk_version is not None and float(sdk_version) >= 3.0


def send_video_settings(
    cfg: TelloConfig, sdk_version: str | None, exchange: Answering, events: DriverEvents
) -> tuple[SettingOutcome, ...]:
    """Send each of `cfg.video_settings` and wait for its answer (SETUP_ATTEMPTS tries); on firmware
    without SDK 3.0 send none. Each outcome is also an event (`video_setting`, `video_setting_refused`)."""
    out = []
    for s in cfg.video_settings:
        if not has_sdk3(sdk_version):
            said = "did not answer `sdk?`" if sdk_version is None else f"reports SDK {sdk_version}"
            got = SettingOutcome(s, None, f"it {said}, and SDK 3.0 is needed")
        else:
            got = SettingOutcome(s, exchange.answer(s.command, cfg.command_timeout_s, SETUP_ATTEMPTS))
        out.append(got)
        if got.ok:
            events.add("video_setting", s.command)
        else:
            events.add("video_setting_refused", got.refusal(cfg.host))
    return tuple(out)


def outcomes_of(cfg: TelloConfig, outcomes: tuple[SettingOutcome, ...]) -> list[SettingOutcome]:
    """The outcome of each setting of `cfg`, in its order (one without an outcome in `outcomes`: not sent,
    the driver never connected)."""
    got = {o.setting: o for o in outcomes}
    return [got.get(s, SettingOutcome(s, None, "the driver has not connected")) for s in cfg.video_settings]


def unconfirmed(cfg: TelloConfig, outcomes: tuple[SettingOutcome, ...]) -> list[str]:
    """One line (`SettingOutcome.refusal`) per setting of `cfg` the drone did not confirm with `ok`."""
    return [o.refusal(cfg.host) for o in outcomes_of(cfg, outcomes) if not o.ok]
