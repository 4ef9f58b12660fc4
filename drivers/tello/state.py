"""The Tello state stream, parsed strictly: one datagram → one `TelloTelemetry`, or a named rejection.

The Tello sends a state line at about 10 Hz to UDP port 8890 of the computer that sent `command`
(SDK 2.0/3.0 user guides): `mid:-1;x:0;…;h:80;bat:87;baro:12.3;time:12;agx:…;\\r\\n`. Nothing in it is
trusted: a datagram that is not short printable ASCII, is malformed, lacks a field this driver decides on,
or carries a value that is not a finite number is rejected with a reason (the caller drops and counts it).
Every finite number parses: a value outside the physical bounds of `PLAUSIBLE` is kept as sent and only
flagged (`TelloTelemetry.implausible`; the driver records it, drivers/tello/stream_health.py). A real `h`
drifts (one recorded flight by −3.5 cm/s, docs/drivers.md "What a real Tello sends"): rejecting the lines
that carry a drifted value silenced the whole stream. Unknown extra fields are ignored (firmwares differ).

Units as sent by the drone: heights and distances in cm (`h` relative to the takeoff point, `tof` from
the downward time-of-flight sensor: distance to the surface below + 10 cm), velocities `vgx/vgy/vgz` in
dm/s with `vgz` positive **down** and vgx/vgy in the frame of yaw 0 (a recorded real flight:
sim_backend/emulators/tello/recorded.py), `time` = motor-on time in whole
seconds (rises while the motors run), `bat` in percent, temperatures in °C, `baro` in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MAX_STATE_BYTES = 512  # a real state line is ~150–250 bytes

REQUIRED_FIELDS = ("h", "tof", "vgz", "time", "bat")
"""The fields this driver decides on: a line without one of them is rejected."""
PLAUSIBLE: dict[str, tuple[float, float]] = {
    "h": (-1000.0, 3000.0),  # cm; negative when below the takeoff point
    "tof": (0.0, 10000.0),  # cm; 6553 is reported when out of range on some firmwares
    "vgz": (-100.0, 100.0),  # dm/s, positive down
    "time": (0.0, 1e7),  # s
    "bat": (0.0, 100.0),  # %
    "vgx": (-100.0, 100.0),
    "vgy": (-100.0, 100.0),
    "templ": (-40.0, 150.0),
    "temph": (-40.0, 150.0),
    "baro": (-1000.0, 10000.0),
    "pitch": (-180.0, 180.0),
    "roll": (-180.0, 180.0),
    "yaw": (-180.0, 180.0),
    "x": (-1e5, 1e5),  # cm; mission-pad coordinates on a real drone (drivers/tello/identify.py)
    "y": (-1e5, 1e5),
    "z": (-1e5, 1e5),
}
"""field: (lowest, highest) physically plausible value, in the field's unit; the fields that are read."""


class StateRejectedError(ValueError):
    """A state datagram that is dropped; `reason` is a short counter key."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass(frozen=True)
class TelloTelemetry:
    """One state packet as received at `t` (time.monotonic() of this computer, s)."""

    t: float
    h_cm: float
    tof_cm: float
    vgz_dm_s: float  # positive down
    motor_s: float
    bat_pct: float
    temph_c: float | None
    fields: dict[str, float]
    implausible: tuple[str, ...]  # the fields whose value lies outside PLAUSIBLE's bounds (kept as sent)


def parse_state(data: bytes, t: float) -> TelloTelemetry:
    """Parse one state datagram received at `t` (implausible values flagged, module docstring); raise
    StateRejectedError(reason) for anything else."""
    if len(data) > MAX_STATE_BYTES:
        raise StateRejectedError("too_long", f"{len(data)} bytes")
    try:
        text = data.decode("ascii").strip()
    except UnicodeDecodeError:
        raise StateRejectedError("not_ascii") from None
    if not text.isprintable():
        raise StateRejectedError("not_printable")
    values: dict[str, float] = {}
    for item in text.split(";"):
        if not item:
            continue
        key, sep, raw = item.partition(":")
        if not sep:
            raise StateRejectedError("malformed", item[:20])
        if key not in PLAUSIBLE:
            continue  # mpry, mid, agx… and fields of other firmwares
        try:
            v = float(raw)
        except ValueError:
            raise StateRejectedError("bad_number", f"{key}={raw[:20]!r}") from None
        if not math.isfinite(v):
            raise StateRejectedError("not_finite", f"{key}={raw[:20]!r}")
        values[key] = v
    missing = [k for k in REQUIRED_FIELDS if k not in values]
    if missing:
        raise StateRejectedError("missing_field", ",".join(missing))
    return TelloTelemetry(
        t=t,
        h_cm=values["h"],
        tof_cm=values["tof"],
        vgz_dm_s=values["vgz"],
        motor_s=values["time"],
        bat_pct=values["bat"],
        temph_c=values.get("temph"),
        fields=values,
        implausible=tuple(k for k, v in values.items() if not PLAUSIBLE[k][0] <= v <= PLAUSIBLE[k][1]),
    )
