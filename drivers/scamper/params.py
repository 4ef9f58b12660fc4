"""Reading an ArduPilot vehicle's parameters over MAVLink, bounded in time (`read_parameters`).

The MAVLink parameter protocol: ``PARAM_REQUEST_READ`` (target system and component, ``param_id``, and
``param_index`` -1 to ask by name) is answered by a ``PARAM_VALUE`` (``param_id``, the value as a float,
``param_type`` a ``MAV_PARAM_TYPE``, ``param_count``, ``param_index``).  Over UDP a request or its reply can
be lost, duplicated or arrive out of order, and ArduPilot does not answer a name it does not have (older
and newer firmware name some parameters differently).  So:

* every name not yet answered is requested, all at once, then replies are collected for
  ``reply_timeout_s``; names still unanswered are requested again, ``attempts`` rounds in all.  The read
  never takes longer than ``attempts · reply_timeout_s`` (+ one receive wait of ≤ 50 ms);
* a ``PARAM_VALUE`` counts only when it comes from the target (system, component), names a parameter
  asked for, has a known ``MAV_PARAM_TYPE`` and a finite value (integral and in range for an integer
  type); anything else is dropped and counted in ``ParamRead.dropped`` under its reason.  Replies are
  matched by name, so their order does not matter; of duplicates the last valid one counts (a different
  value is counted as ``changed``);
* ``enough(values)`` may end the read early (e.g. when one of two alternative names has answered).

GCS heartbeats are sent meanwhile (1 Hz): a ``udpin`` vehicle only learns our address from what we send.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil

from flightstack.drivers.scamper.link import (
    GCS_HEARTBEAT_PERIOD_S,
    HeartbeatProbe,
    ScamperConfig,
    open_connection,
    send_gcs_heartbeat,
    wait_vehicle_heartbeat,
)
from flightstack.drivers.scamper.nav import LabOrigin

mavlink = mavutil.mavlink

REPLY_TIMEOUT_S = 1.0  # wait for the replies to one round of requests (s)
ATTEMPTS = 3  # rounds of requests for a name that does not answer
RX_WAIT_S = 0.05  # longest single receive wait (s)
PARAM_ID_LEN = 16  # MAVLink param_id: up to 16 ASCII characters
_INT_RANGES = {
    mavlink.MAV_PARAM_TYPE_UINT8: (0, 2**8 - 1),
    mavlink.MAV_PARAM_TYPE_INT8: (-(2**7), 2**7 - 1),
    mavlink.MAV_PARAM_TYPE_UINT16: (0, 2**16 - 1),
    mavlink.MAV_PARAM_TYPE_INT16: (-(2**15), 2**15 - 1),
    mavlink.MAV_PARAM_TYPE_UINT32: (0, 2**32 - 1),
    mavlink.MAV_PARAM_TYPE_INT32: (-(2**31), 2**31 - 1),
    mavlink.MAV_PARAM_TYPE_UINT64: (0, 2**64 - 1),
    mavlink.MAV_PARAM_TYPE_INT64: (-(2**63), 2**63 - 1),
}
_REAL_TYPES = (mavlink.MAV_PARAM_TYPE_REAL32, mavlink.MAV_PARAM_TYPE_REAL64)

Enough = Callable[[Mapping[str, float]], bool]


@dataclass(frozen=True)
class ParamRead:
    """What a read got: values by name, the names that never answered, and the bookkeeping."""

    values: dict[str, float]
    types: dict[str, int]  # name -> MAV_PARAM_TYPE
    missing: tuple[str, ...]  # asked for, never (validly) answered
    requests: int  # PARAM_REQUEST_READ sent
    dropped: Counter[str] = field(default_factory=Counter)  # reason -> PARAM_VALUE dropped
    elapsed_s: float = 0.0


def check_name(name: str) -> str:
    """A parameter name as MAVLink carries it: 1 to 16 printable ASCII characters; ValueError otherwise."""
    if not (1 <= len(name) <= PARAM_ID_LEN and name.isascii() and name.isprintable()):
        raise ValueError(f"not a MAVLink parameter name: {name!r}")
    return name


class ParamCollector:
    """Validates and keeps the PARAM_VALUE replies to a read (pure: no I/O; module docstring's rules)."""

    def __init__(self, target: tuple[int, int], names: Iterable[str]) -> None:
        self.target = target
        self.names = tuple(dict.fromkeys(check_name(n) for n in names))
        self.values: dict[str, float] = {}
        self.types: dict[str, int] = {}
        self.dropped: Counter[str] = Counter()

    def missing(self) -> tuple[str, ...]:
        return tuple(n for n in self.names if n not in self.values)

    def offer(self, msg: Any) -> bool:
        """Take one received message; True when it was a valid reply to this read."""
        try:
            if msg.get_type() != "PARAM_VALUE":
                return self._drop("not PARAM_VALUE")
            if (msg.get_srcSystem(), msg.get_srcComponent()) != self.target:
                return self._drop("other source")
            name, value, ptype = str(msg.param_id), float(msg.param_value), int(msg.param_type)
        except (AttributeError, TypeError, ValueError):
            return self._drop("malformed")
        if name not in self.names:
            return self._drop("not asked for")
        if not math.isfinite(value):
            return self._drop("not finite")
        if ptype in _INT_RANGES:
            lo, hi = _INT_RANGES[ptype]
            if value != math.floor(value) or not lo <= value <= hi:
                return self._drop("not an integer of its type")
        elif ptype not in _REAL_TYPES:
            return self._drop("unknown param_type")
        if name in self.values:
            self.dropped["duplicate" if self.values[name] == value else "changed"] += 1
        self.values[name], self.types[name] = value, ptype
        return True

    def _drop(self, reason: str) -> bool:
        self.dropped[reason] += 1
        return False


def read_parameters(
    conn: Any,
    target: tuple[int, int],
    names: Sequence[str],
    *,
    reply_timeout_s: float = REPLY_TIMEOUT_S,
    attempts: int = ATTEMPTS,
    enough: Enough | None = None,
) -> ParamRead:
    """Read `names` from the vehicle `target` = (system, component) on the pymavlink connection `conn`.

    Never raises for the network (a failed send or receive is counted in ``dropped`` as ``send_error`` /
    ``recv_error``); never takes longer than ``attempts · reply_timeout_s`` + 50 ms.
    """
    if not (math.isfinite(reply_timeout_s) and reply_timeout_s > 0.0) or attempts < 1:
        raise ValueError(f"reply_timeout_s must be > 0 and attempts >= 1, got {reply_timeout_s}, {attempts}")
    col = ParamCollector(target, names)
    requests = 0
    t0 = time.monotonic()
    next_hb = t0 + GCS_HEARTBEAT_PERIOD_S
    for _ in range(attempts):
        for name in col.missing():
            try:
                conn.mav.param_request_read_send(target[0], target[1], name.encode("ascii"), -1)
                requests += 1
            except OSError:
                col.dropped["send_error"] += 1
        round_end = time.monotonic() + reply_timeout_s
        while col.missing() and not (enough is not None and enough(col.values)):
            now = time.monotonic()
            if now >= round_end:
                break
            if now >= next_hb:
                next_hb = now + GCS_HEARTBEAT_PERIOD_S
                send_gcs_heartbeat(conn)
            try:
                msg = conn.recv_match(
                    type="PARAM_VALUE", blocking=True, timeout=min(RX_WAIT_S, round_end - now)
                )
            except (OSError, ValueError):  # a socket error; a reply pymavlink cannot decode
                col.dropped["recv_error"] += 1
                continue
            if msg is not None:
                col.offer(msg)
        if not col.missing() or (enough is not None and enough(col.values)):
            break
    return ParamRead(
        dict(col.values), dict(col.types), col.missing(), requests, col.dropped, time.monotonic() - t0
    )


def probe_parameters(
    config: ScamperConfig, names: Sequence[str], *, enough: Enough | None = None, **kw: Any
) -> tuple[HeartbeatProbe, ParamRead]:
    """Wait for the robot's HEARTBEAT (as `probe_heartbeat`: nothing armed, no mode changed), then read
    `names` from it (`read_parameters`, keyword arguments passed on); raises ScamperLinkError when no
    heartbeat comes within ``heartbeat_timeout_s``."""
    conn = open_connection(config)
    try:
        probe, target = wait_vehicle_heartbeat(conn, config)
        return probe, read_parameters(conn, target, names, enough=enough, **kw)
    finally:
        with contextlib.suppress(OSError):
            conn.close()


@dataclass(frozen=True)
class OriginProbe:
    """What the vehicle said of its EKF origin: GPS_GLOBAL_ORIGIN (degE7, degE7, mm) or None."""

    reported: tuple[int, int, int] | None
    sends: int  # SET_GPS_GLOBAL_ORIGIN sent
    elapsed_s: float


ORIGIN_PROBE_S = 2.0  # preflight's wait for GPS_GLOBAL_ORIGIN (s)
ORIGIN_RESEND_S = 0.5


def confirm_origin(conn: Any, target: tuple[int, int], origin: LabOrigin, timeout_s: float) -> OriginProbe:
    """Set the EKF origin (SET_GPS_GLOBAL_ORIGIN: ArduPilot takes it only while it has none,
    ``GCS_MAVLINK::set_ekf_origin``; nothing moves) and ask for it back (MAV_CMD_REQUEST_MESSAGE 49) every
    ORIGIN_RESEND_S until a GPS_GLOBAL_ORIGIN from `target` arrives or `timeout_s` passed; never raises for
    the network."""
    t0 = time.monotonic()
    lat, lon, alt = origin.as_mavlink()
    sends, next_send = 0, t0
    while (now := time.monotonic()) - t0 < timeout_s:
        if now >= next_send:
            next_send = now + ORIGIN_RESEND_S
            with contextlib.suppress(OSError):
                conn.mav.set_gps_global_origin_send(target[0], lat, lon, alt, 0)
                sends += 1
                conn.mav.command_long_send(
                    target[0], target[1], mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                    float(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN), 0, 0, 0, 0, 0, 0,
                )  # fmt: skip
        try:
            msg = conn.recv_match(type="GPS_GLOBAL_ORIGIN", blocking=True, timeout=RX_WAIT_S)
        except (OSError, ValueError):
            msg = None
        if msg is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == target:
            reported = (int(msg.latitude), int(msg.longitude), int(msg.altitude))
            return OriginProbe(reported, sends, time.monotonic() - t0)
    return OriginProbe(None, sends, time.monotonic() - t0)


@dataclass(frozen=True)
class VehicleProbe:
    """`probe_vehicle`'s answer: heartbeat, parameters, origin."""

    heartbeat: HeartbeatProbe
    params: ParamRead
    origin: OriginProbe


def probe_vehicle(
    config: ScamperConfig,
    names: Sequence[str],
    *,
    enough: Enough | None = None,
    origin_timeout_s: float = ORIGIN_PROBE_S,
) -> VehicleProbe:
    """`probe_parameters`, then `confirm_origin` with the configured lab origin, on one connection
    (nothing armed, no mode changed); raises ScamperLinkError when no heartbeat comes in time."""
    conn = open_connection(config)
    try:
        probe, target = wait_vehicle_heartbeat(conn, config)
        read = read_parameters(conn, target, names, enough=enough)
        origin = LabOrigin(config.origin_lat_deg, config.origin_lon_deg, config.origin_alt_m)
        return VehicleProbe(probe, read, confirm_origin(conn, target, origin, origin_timeout_s))
    finally:
        with contextlib.suppress(OSError):
            conn.close()
