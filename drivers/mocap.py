"""Motion-capture pose source (implements `flightstack.hal.PoseSource`) on top of `motioncapture`.

The PyPI package `motioncapture` (libmotioncapture bindings) supports the backends mock, vicon, optitrack,
qualisys and vrpn. It gives no timestamps, so every pose is stamped with `clock()` at the moment its frame
was received by the reader thread (receive time, seconds in the clock passed to `MocapPoseSource`; pass the
mission clock's `now` to get stamps comparable with the rest of the stack).

Frames: positions are in the motion-capture world frame Σw (metres, z up); the body rotation is reduced to a
yaw θ about world z (radians, wrapped to (-π, π]) plus a tilt angle (radians, the angle between the body
z axis and world z). Bodies tilted more than `MocapConfig.max_tilt_rad` are refused: a planar pose would
misrepresent them.

The `mock` backend publishes fixed rigid bodies given in its settings, e.g.
    MocapConfig("mock", {"rigid_bodies": "cf1(x,y,z,qw,qx,qy,qz);cf2(...)", "frequency": "100"})
(`frequency` in Hz, integer, default 100).

The reader thread never ends on an error: an exception from `waitForNextFrame` or from reading a frame
(a socket error such as ENETUNREACH, a bad frame, a backend bug) is counted (`counts["reader_error"]` and
`counts["thread_error"]`), logged at the first and every 100th occurrence, recorded as one
"reader_error" event per run of failures (and "reader_recovered" when frames come again), and the thread
reads on after a pause of `ERROR_PAUSE_S` (so a backend that fails at once cannot spin a core). Poses
simply go stale (`latest()` None) while it fails.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import math
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flightstack.drivers.device_threads import ERROR_PAUSE_S, ErrorLog
from flightstack.drivers.native_output import native_stdout
from flightstack.events import Event, MocapKind
from flightstack.hal import StampedPose
from flightstack.paper.geometry import Pose

LOG = logging.getLogger("flightstack.mocap")
RATE_WINDOW_S = 2.0  # window of the receive-rate estimate (s)
MAX_EVENTS = 10_000  # oldest events are dropped beyond this many


class MocapError(RuntimeError):
    """The motion-capture system could not be reached or failed."""


# Default server ports of the backends whose connect() blocks without a timeout.
NATNET_COMMAND_PORT = 1510  # OptiTrack NatNet command port (UDP)
TCP_PORTS = {"vicon": 801, "qualisys": 22222, "vrpn": 3883}


@dataclass(frozen=True)
class NatNetServerInfo:
    """What a NatNet server says of itself in its NAT_SERVERINFO reply (a NAT_CONNECT's answer): the
    application's name, its NatNet version, its data port and whether it streams multicast (and to which
    group). Motive's "Transmission Type" setting decides `multicast`."""

    app: str
    natnet_version: tuple[int, int, int, int]
    data_port: int
    multicast: bool
    group: str

    @staticmethod
    def parse(packet: bytes) -> NatNetServerInfo | None:
        """The reply's fields; None unless it is a NAT_SERVERINFO (message 1) of at least 283 bytes."""
        import struct

        if len(packet) < 283 or packet[:2] != b"\x01\x00":
            return None
        name = packet[4:260].split(b"\0", 1)[0].decode("utf-8", errors="replace")
        v = packet[264:268]
        port, multicast = struct.unpack_from("<H?", packet, 276)
        group = ".".join(str(b) for b in packet[279:283])
        return NatNetServerInfo(name, (v[0], v[1], v[2], v[3]), port, bool(multicast), group)


def probe_server(system: str, settings: dict[str, str], timeout_s: float) -> NatNetServerInfo | None:
    """Check that the server answers before `motioncapture.connect` is called; MocapError otherwise.
    OptiTrack: returns what its reply says (None if the reply is not a server info).

    Why: libmotioncapture's optitrack connect() waits for the server's reply with no timeout and without
    releasing Python's GIL, so a silent server would freeze the whole process (every driver thread, the
    control loop) rather than just the reader thread. OptiTrack: one NatNet NAT_CONNECT datagram to
    `hostname:port_command`, any reply counts. Vicon, Qualisys, VRPN: a TCP connect to the default port
    (or `hostname:port`). `mock` needs no server. A server that dies between the probe and connect() is
    not covered (a window of milliseconds)."""
    import socket
    import struct

    if system == "mock":
        return None
    host = settings.get("hostname", "")
    if not host:
        raise MocapError(f"{system}: settings.hostname is required")
    if system == "optitrack":
        port = int(settings.get("port_command", NATNET_COMMAND_PORT))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(timeout_s)
            try:
                sock.sendto(struct.pack("<HH", 0, 0), (host, port))  # NAT_CONNECT, empty payload
                reply, _ = sock.recvfrom(65535)
            except OSError as exc:
                raise MocapError(
                    f"no OptiTrack NatNet server answered at {host}:{port} within {timeout_s:g} s ({exc})"
                ) from None
        return NatNetServerInfo.parse(reply)
    if system in TCP_PORTS:
        h, _, p = host.rpartition(":") if ":" in host else (host, "", str(TCP_PORTS[system]))
        try:
            socket.create_connection((h, int(p)), timeout=timeout_s).close()
        except OSError as exc:
            raise MocapError(f"no {system} server at {h}:{p} within {timeout_s:g} s ({exc})") from None
    return None


@dataclass(frozen=True)
class MocapConfig:
    """Connection and validity settings of a motion-capture pose source.

    system:            motioncapture backend type ("mock", "vicon", "optitrack", "qualisys", "vrpn").
    settings:          passed verbatim to `motioncapture.connect` (e.g. {"hostname": "10.0.0.2"}).
    connect_timeout_s: how long `start()` waits for `connect()` (s).
    stale_after_s:     a body not received for this long is reported as None (s).
    max_tilt_rad:      a body tilted more than this from level is reported as None (rad).
    """

    system: str = "mock"
    settings: dict[str, str] = field(default_factory=dict)
    connect_timeout_s: float = 5.0
    stale_after_s: float = 0.1
    max_tilt_rad: float = 0.35


def quaternion_to_planar(position: Any, w: float, x: float, y: float, z: float) -> tuple[Pose, float]:
    """Reduce a mocap pose to (yaw-only Pose in Σw, tilt in rad).

    position: (3,) metres in Σw (any float dtype). (w, x, y, z): unit quaternion of the body in Σw (it is
    normalised here; q and -q give the same result). The yaw θ = atan2(R[1,0], R[0,0]) is the Z angle of
    the intrinsic Z-Y-X (yaw-pitch-roll) decomposition, i.e. the heading of the body x axis projected on the
    horizontal plane. The tilt = arccos(R[2,2]) ∈ [0, π] is the angle between the body z axis and world z.
    Raises ValueError for a zero or non-finite quaternion or a non-finite position.
    """
    q = np.array([w, x, y, z], dtype=float)
    n = float(np.linalg.norm(q))
    if not (math.isfinite(n) and n > 1e-9):
        raise ValueError(f"invalid quaternion (w, x, y, z) = {tuple(q)}")
    w, x, y, z = (q / n).tolist()
    r00 = 1.0 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + w * z)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    tilt = math.acos(min(1.0, max(-1.0, r22)))
    yaw = math.atan2(r10, r00)
    return Pose.make(np.asarray(position, dtype=float), yaw), tilt


@dataclass
class _Body:
    """Reader-side state of one rigid body (all times in the source's clock, s)."""

    pose: Pose
    tilt: float
    stamp: float
    raw: tuple[tuple[float, float, float], tuple[float, float, float, float]]  # position m, (w, x, y, z)
    present: bool = True
    refused: bool = False
    receipts: deque[float] = field(default_factory=deque)


class MocapPoseSource:
    """`hal.PoseSource` backed by a motion-capture system, read in a background thread.

    Call `start()` (connects, bounded by `connect_timeout_s`), then `latest(body)` from any thread; `close()`
    stops the reader. `events` records (time s, kind, body name) transitions: "body_found", "body_lost",
    "body_regained", "tilt_refused", "tilt_ok", "bad_sample", "reader_error" (detail: the error),
    "reader_recovered", "reader_join_timeout". `counts`: "reader_error", "thread_error" (errors so far).
    """

    def __init__(
        self,
        cfg: MocapConfig,
        connect: Callable[[str, dict[str, str]], Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """connect defaults to `motioncapture.connect` (imported lazily in `start`); clock returns seconds."""
        self.cfg = cfg
        self._connect = connect
        self._clock = clock
        self._lock = threading.Lock()
        self._bodies: dict[str, _Body] = {}
        self._invalid: Counter[str] = Counter()  # per body: samples refused since its last valid one
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._connect_error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._mc: Any = None
        self._frames = 0
        self._last_frame: float | None = None
        self._reader_error: str | None = None  # the last error of the reader thread (kept after recovery)
        self.server_info: NatNetServerInfo | None = None  # OptiTrack: the server's reply to the probe
        self._failing = False  # the reader's last attempt failed
        self.events: list[Event] = []  # source mocap; detail: the body's name
        self.counts: Counter[str] = Counter()
        self.errors = ErrorLog(self.counts, f"mocap {cfg.system} reader", LOG)

    # ---- lifecycle --------------------------------------------------------------------------------------
    def start(self) -> None:
        """Connect in a daemon thread, then read frames; MocapError if connect fails or times out.

        On timeout the thread blocked in `connect()` is left behind as a daemon (the motioncapture backends
        cannot be interrupted); if it ever returns it exits without reading.
        """
        if self._thread is not None:
            raise MocapError("MocapPoseSource.start() called twice")
        connect = self._connect
        if connect is None:
            self.server_info = probe_server(self.cfg.system, self.cfg.settings, self.cfg.connect_timeout_s)
            try:
                connect = importlib.import_module("motioncapture").connect
            except ImportError as exc:
                raise MocapError(f"cannot import motioncapture: {exc}") from exc
        self._thread = threading.Thread(
            target=self._run, args=(connect,), name=f"mocap-{self.cfg.system}", daemon=True
        )
        # the library's own lines while it connects ("Using unicast from server …") get a level and a name
        capture: contextlib.AbstractContextManager[list[str]] = (
            native_stdout() if self._connect is None else contextlib.nullcontext([])
        )
        with capture as said:
            self._thread.start()
            connected = self._connected.wait(self.cfg.connect_timeout_s)
        for line in said:
            print(f"info: mocap {self.cfg.system} (libmotioncapture): {line}", file=sys.stderr)
        if not connected:
            self._stop.set()
            raise MocapError(
                f"no {self.cfg.system} server answered within {self.cfg.connect_timeout_s:g} s "
                f"(settings {self.cfg.settings})"
            )
        if self._connect_error is not None:
            raise MocapError(
                f"connecting to {self.cfg.system} failed (settings {self.cfg.settings}): "
                f"{self._connect_error}"
            ) from self._connect_error

    def close(self, join_timeout_s: float = 1.0) -> None:
        """Stop the reader thread, waiting at most join_timeout_s (s) for it to leave `waitForNextFrame`."""
        self._stop.set()
        th = self._thread
        if th is not None and th.is_alive() and th is not threading.current_thread():
            th.join(join_timeout_s)
            if th.is_alive():
                self._event("reader_join_timeout", "")

    def __enter__(self) -> MocapPoseSource:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- PoseSource -------------------------------------------------------------------------------------
    def latest(self, body: str) -> StampedPose | None:
        """Newest pose of `body` stamped with its receive time; None if never seen, stale or too tilted."""
        now = self._clock()
        with self._lock:
            b = self._bodies.get(body)
            if b is None or b.refused or now - b.stamp > self.cfg.stale_after_s:
                return None
            return StampedPose(b.stamp, b.pose)

    def sample(
        self, body: str
    ) -> tuple[tuple[float, float, float], tuple[float, float, float, float]] | None:
        """The newest sample of `body` as the system gave it, even if stale or refused: (position (3,) m,
        quaternion (w, x, y, z)) in the system's own frame; None if never seen."""
        with self._lock:
            b = self._bodies.get(body)
            return None if b is None else b.raw

    def invalid_run(self, body: str) -> int:
        """How many samples of `body` in a row, up to the newest, were not a valid pose (a non-finite
        position or quaternion, a zero quaternion: event `bad_sample`); 0 when the newest was valid."""
        with self._lock:
            return self._invalid[body]

    def tilt(self, body: str) -> float | None:
        """Tilt (rad, body z vs world z) of the newest sample of `body`, even if stale; None if never seen."""
        with self._lock:
            b = self._bodies.get(body)
            return None if b is None else b.tilt

    def rate_hz(self, body: str) -> float:
        """Receive rate of `body` (Hz) over the last ~2 s; 0 if fewer than 2 samples or stale."""
        now = self._clock()
        with self._lock:
            b = self._bodies.get(body)
            if b is None:
                return 0.0
            return self._rate_locked(b, now)

    def stats(self) -> dict[str, Any]:
        """Diagnostics: connection, reader state, frames/age (s), per body rate (Hz), age (s), tilt (rad)."""
        now = self._clock()
        th = self._thread
        with self._lock:
            bodies = {
                name: {
                    "rate_hz": self._rate_locked(b, now),
                    "age_s": now - b.stamp,
                    "tilt_rad": b.tilt,
                    "present": b.present,
                    "refused": b.refused,
                }
                for name, b in self._bodies.items()
            }
            return {
                "system": self.cfg.system,
                "connected": self._connected.is_set() and self._connect_error is None,
                "reader_alive": th is not None and th.is_alive(),
                "reader_error": self._reader_error,
                "reader_failing": self._failing,
                "reader_errors": self.counts["reader_error"],
                "frames": self._frames,
                "last_frame_age_s": None if self._last_frame is None else now - self._last_frame,
                "bodies": bodies,
                "events": len(self.events),
            }

    # ---- internals --------------------------------------------------------------------------------------
    def _rate_locked(self, b: _Body, now: float) -> float:
        r = b.receipts
        while r and r[0] < now - RATE_WINDOW_S:
            r.popleft()
        if len(r) < 2 or now - r[-1] > self.cfg.stale_after_s or r[-1] <= r[0]:
            return 0.0
        return (len(r) - 1) / (r[-1] - r[0])

    def _event(self, kind: MocapKind, name: str) -> None:
        self.events.append(Event(self._clock(), None, kind, name, source="mocap", clock="monotonic"))
        if len(self.events) > MAX_EVENTS:
            del self.events[: len(self.events) - MAX_EVENTS]

    def _run(self, connect: Callable[[str, dict[str, str]], Any]) -> None:
        try:
            mc = connect(self.cfg.system, dict(self.cfg.settings))
        except Exception as exc:
            self._connect_error = exc
            self._connected.set()
            return
        if self._stop.is_set():  # start() already gave up on us
            return
        self._mc = mc
        self._connected.set()
        while not self._stop.is_set():
            try:
                mc.waitForNextFrame()
                if self._stop.is_set():
                    break
                t = self._clock()
                self._ingest(t, mc.rigidBodies)
            except Exception as exc:  # the reader must outlive any error: count, log, read on
                self._reader_failed(exc)
                self._stop.wait(ERROR_PAUSE_S)

    def _reader_failed(self, exc: Exception) -> None:
        """Count and log one reader error; the first of a run of failures is an event."""
        why = f"{type(exc).__name__}: {exc}"
        self.errors.record("reader_error", why)
        with self._lock:
            self._reader_error = why
            if not self._failing:
                self._failing = True
                self._event("reader_error", why)

    def _ingest(self, t: float, rigid_bodies: Any) -> None:
        """Store one frame received at t (s): update seen bodies, mark vanished ones lost."""
        seen: set[str] = set()
        with self._lock:
            self._frames += 1
            self._last_frame = t
            if self._failing:
                self._failing = False
                self._event("reader_recovered", f"after {self.counts['reader_error']} errors in all")
            for name, rb in rigid_bodies.items():
                rot = rb.rotation
                try:
                    pose, tilt = quaternion_to_planar(rb.position, rot.w, rot.x, rot.y, rot.z)
                except ValueError:
                    self._event("bad_sample", name)
                    self._invalid[name] += 1
                    continue
                seen.add(name)
                self._invalid.pop(name, None)
                refused = tilt > self.cfg.max_tilt_rad
                p = rb.position
                raw = (
                    (float(p[0]), float(p[1]), float(p[2])),
                    (float(rot.w), float(rot.x), float(rot.y), float(rot.z)),
                )
                b = self._bodies.get(name)
                if b is None:
                    b = self._bodies[name] = _Body(pose, tilt, t, raw, refused=False)
                    self._event("body_found", name)
                elif not b.present:
                    self._event("body_regained", name)
                if refused != b.refused:
                    self._event("tilt_refused" if refused else "tilt_ok", name)
                b.pose, b.tilt, b.stamp, b.present, b.refused, b.raw = pose, tilt, t, True, refused, raw
                b.receipts.append(t)
            for name, b in self._bodies.items():
                if b.present and name not in seen:
                    b.present = False
                    self._event("body_lost", name)
