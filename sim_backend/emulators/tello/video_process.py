"""An emulated Tello's camera in a child process: it renders what the camera sees of the flight, encodes
it as H.264 and streams it as the Tello does, without competing with the flight's loop for the
interpreter lock.

`VideoProcess` (parent side) is the `RemoteVideo` of one `TelloEmulator` (`use_remote_video`): the
emulator's video thread publishes the stream state (`streamon`, its epoch, `downvision`, the `no_video`
fault) and its true pose (its own frame: cm, yaw clockwise in degrees) every 10 ms into a shared-memory
block; `SharedTarget` carries the target's (the rover's) pose in Σw (m, rad), written by the emulated lab
at 100 Hz and read by every camera; `configure` gives the stream's format (the SDK 3.0 settings the
emulator received: frame rate, size, bit rate; the picture is scaled to the size), which the child takes
with a new encoder. The child (`spawn` start method: no inherited threads or locks)
paces frames at `fps` from its `streamon`, reads both poses, renders (`tello_view.CameraView.frame`: the
Tello EDU's downward layout while `downvision` is on and the calibration declares one, at the layout's
size, its encoder rebuilt when the camera is switched), stamps the frame index as a bar code
(`tello_frames.stamp_frame_index`, below the picture in that layout: `tello_view.index_area`), encodes and
sends from the drone's loopback ip to (client_ip, video_port) with the emulator's own
`make_encoder`/`send_frame`.

The way out (`VideoPath`): with the rig's video link (device_links) each frame, rendered and encoded
when taken, leaves the drone latency_s + U(0, jitter_s) after its capture time, or never (lost as a
whole), and each of its datagrams may be lost by itself (the link's `datagram_loss`: a damaged frame);
a newer frame pushes older ones out ahead of it, so the stream stays in order. Then its
datagrams pass the drone's radio (flightstack.netem: the video link seeded by (seed, "tello<id>",
"video"), with the same blackout windows and epoch as the parent's DeviceRadio of that drone, so that a
blackout silences video with commands and state). Both are sent at their due times by one delay line
thread in the child; their counters come back through shared memory (`link_counts`, `network_counts`).

Capture time: every frame sent is recorded with its true capture time, the time.monotonic() (s; Linux
CLOCK_MONOTONIC is one clock for every process of the machine) at which the drone pose it shows was
taken (the target's pose is at most 10 ms apart), and the time it left the drone (before the radio);
`sync` copies these records into the emulator's `video_capture_log` and `video_log`, its counters
(`video_frames_sent`, `video_bytes_sent`, `video_frame_index`) and the child's errors (`errors`). A frame
the video link lost is neither recorded nor counted as sent.

Blocks are float64 arrays with a sequence lock (one writer each: the sequence number is odd while it
writes); records go to a ring of `RING` entries. Stopping: `close()` sets the stop flag and joins (≤ 2 s),
then terminates; the child also exits when its parent is gone (its parent pid changes) and ignores SIGINT
(the parent decides when it stops).
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import multiprocessing
import os
import signal
import socket
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from flightstack.netem import NetworkProfile

from ..device_links import LINK_COUNTERS
from ..radio import COUNTERS
from .base import TelloEmulatorBase
from .recorded import KEYFRAME_INTERVAL_FRAMES
from .video import StreamFormat
from .view import CameraSpec

RING = 1 << 15
"""Capture records kept in shared memory (18 min at 30 fps); `sync` copies them out every 10 ms."""
TRUTH_KEPT = 4096
"""Frames whose true feature pixels `VideoProcess.truth_px` keeps (2.3 min at 30 fps)."""
_RECORD = 4
"""A ring record's doubles before the true pixels: index, t_capture, t_sent, bytes."""
START_TIMEOUT_S = 20.0
"""How long `start()` waits for the child to be ready (imports of numpy, OpenCV and PyAV) (s)."""

# control block (parent writes): sequence, then the fields below; STOP is outside the sequence lock
_ON, _EPOCH, _DOWN, _X, _Y, _Z, _YAW, _T = range(1, 9)
_CTRL_N = 9
_STOP = _CTRL_N
# stats block (child writes): counters, the video link's row (LINK_COUNTERS, delay_mean_ms), the radio's
# video link row (COUNTERS, delay_mean_ms), then the ring of (index, t_capture, t_sent, bytes, the m
# feature points' true pixels u0, v0, u1, v1, ...)
_READY, _FRAMES, _BYTES, _INDEX, _RECORDS = range(5)
_LINK_ROW = (*LINK_COUNTERS, "delay_mean_ms")
_RADIO_ROW = (*COUNTERS, "delay_mean_ms")
_LINK = 5
_RADIO = _LINK + len(_LINK_ROW)
_STATS_HEAD = _RADIO + len(_RADIO_ROW)
# format block (parent writes on a change of the SDK 3.0 settings): fps, width, height, bit rate (0: none)
_FORMAT_N = 4


def f64(raw: Any) -> np.ndarray:
    """A float64 view of a shared RawArray (no copy)."""
    return np.frombuffer(raw, dtype=np.float64)


class SeqBlock:
    """A float64 array in shared memory with a sequence lock: one writer, any number of readers."""

    def __init__(self, raw: Any, n: int) -> None:
        """raw: a multiprocessing RawArray of at least n + 1 doubles; n: fields after the sequence."""
        self.a = f64(raw)
        self.n = n

    def write(self, values: list[float]) -> None:
        a = self.a
        a[0] += 1.0  # odd: writing
        a[1 : 1 + len(values)] = values
        a[0] += 1.0

    def read(self) -> np.ndarray | None:
        """The fields (a copy), or None when no write has completed yet."""
        a = self.a
        for _ in range(1000):
            s0 = a[0]
            v = a[1 : 1 + self.n].copy()
            if s0 == a[0] and s0 % 2 == 0:
                return None if s0 == 0 else v
        return None


class SharedTarget:
    """The target's pose in Σw (x, y m; theta rad; the time.monotonic() it was taken), shared with every
    camera process (write in the parent, read in the children)."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.raw = ctx.RawArray(ctypes.c_double, 5)
        self.block = SeqBlock(self.raw, 4)

    def write(self, x: float, y: float, theta: float) -> None:
        self.block.write([x, y, theta, time.monotonic()])


@dataclass(frozen=True)
class VideoPath:
    """How a camera's frames leave the drone: late by the rig's video link (`link`: LinkSpec fields;
    None: at once), then through the drone's radio (`network`: a flightstack.netem profile, None: clean;
    its blackout windows counted from `epoch`, time.monotonic() s); seeded as the parent's devices are,
    by (seed, drone id) for the link and (seed, "tello<id>", "video") for the radio."""

    seed: int = 0
    drone: int = 0
    link: dict[str, Any] | None = None
    network: NetworkProfile | None = None
    epoch: float = 0.0


class VideoProcess:
    """Parent side of one emulated camera (a `RemoteVideo`, see the module docstring).

    spec: what the camera sees; ip: the drone's loopback address (the video's source); dest: (client ip,
    video port); fps: frames/s; gop_size: frames between keyframes (default the recorded bound,
    `recorded.KEYFRAME_INTERVAL_FRAMES`); target: the shared target pose;
    path: the video link and radio the frames pass (default: none).
    """

    def __init__(
        self,
        spec: CameraSpec,
        ip: str,
        dest: tuple[str, int],
        target: SharedTarget,
        *,
        fps: float = 30.0,
        gop_size: int = KEYFRAME_INTERVAL_FRAMES,
        path: VideoPath | None = None,
    ) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.path = path or VideoPath()
        self.spec, self.ip, self.dest, self.fps, self.gop_size = spec, ip, dest, float(fps), int(gop_size)
        self._ctrl_raw = ctx.RawArray(ctypes.c_double, _CTRL_N + 1)
        self._format_raw = ctx.RawArray(ctypes.c_double, _FORMAT_N + 1)
        self.format = SeqBlock(self._format_raw, _FORMAT_N)
        self._width = _RECORD + 2 * len(spec.feature_points)  # one ring record's doubles
        self._stats_raw = ctx.RawArray(ctypes.c_double, _STATS_HEAD + self._width * RING)
        self._epoch = -1  # the stream epoch last published
        self.truth_px: dict[int, np.ndarray] = {}
        """Frame index -> the feature points' true pixels (m, 2) in that frame (the newest TRUTH_KEPT)."""
        self.ctrl = SeqBlock(self._ctrl_raw, _CTRL_N - 1)
        self._stats = f64(self._stats_raw)
        self._errors_rx, errors_tx = ctx.Pipe(duplex=False)
        self._target = target
        self._read = 0  # capture records copied out so far
        self._t_start = math.nan
        self.process = ctx.Process(
            target=_child_main,
            args=(
                ChildArgs(
                    spec,
                    ip,
                    dest,
                    float(fps),
                    int(gop_size),
                    self._ctrl_raw,
                    target.raw,
                    self._stats_raw,
                    errors_tx,
                    os.getpid(),
                    self.path,
                    self._format_raw,
                ),
            ),
            name=f"tello-camera-{ip}",
            daemon=True,
        )
        self._errors_tx = errors_tx

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) px of the video: the calibration's."""
        return self.spec.size

    def start(self) -> None:
        """Start the child (it imports and warms up in the background: see `wait_ready`)."""
        self.process.start()
        self._errors_tx.close()  # the child holds its end
        self._t_start = time.monotonic()

    def wait_ready(self) -> None:
        """Return once the child is ready; RuntimeError with its error when it died or after
        START_TIMEOUT_S from `start` (the child is then stopped)."""
        deadline = self._t_start + START_TIMEOUT_S
        while self._stats[_READY] == 0.0:
            if not self.process.is_alive() or time.monotonic() > deadline:
                errors = self._drain_errors()
                self.close()
                raise RuntimeError(
                    f"emulated camera of {self.ip} did not start: {'; '.join(errors) or 'timeout'}"
                )
            time.sleep(0.01)

    def publish(
        self, on: bool, epoch: int, downvision: bool, position_cm: tuple[float, float, float], yaw_deg: float
    ) -> None:
        """The stream state and the drone's true pose (its own frame), taken now."""
        x, y, z = position_cm
        if epoch != self._epoch:  # a new stream counts its frames from 0 again: the old truth is another's
            self._epoch = epoch
            self.truth_px.clear()
        self.ctrl.write([float(on), float(epoch), float(downvision), x, y, z, yaw_deg, time.monotonic()])

    def configure(self, fmt: StreamFormat) -> None:
        """The stream's format from now on (frames/s, (width, height) px, bit/s or None: the SDK 3.0
        settings the emulator received: video.TelloVideoStream.stream_format)."""
        fps, (width, height), bit_rate = fmt
        self.format.write([fps, width, height, 0.0 if bit_rate is None else bit_rate])

    def sync(self, emu: TelloEmulatorBase) -> None:
        """Copy the child's counters, new capture records and errors into the emulator's logs."""
        st = self._stats
        n = int(st[_RECORDS])
        if n > self._read:
            ring = st[_STATS_HEAD:].reshape(RING, self._width)
            for k in range(max(self._read, n - RING), n):
                rec = ring[k % RING]
                index, t_cap, t_sent = int(rec[0]), float(rec[1]), float(rec[2])
                emu.video_log.append((index, t_sent))
                emu.video_capture_log.append((index, t_cap, t_sent))
                self.truth_px[index] = rec[_RECORD:].reshape(-1, 2).copy()
            while len(self.truth_px) > TRUTH_KEPT:
                del self.truth_px[next(iter(self.truth_px))]
            self._read = n
        emu.video_frames_sent = int(st[_FRAMES])
        emu.video_bytes_sent = int(st[_BYTES])
        emu.video_frame_index = int(st[_INDEX])
        emu.errors.extend(self._drain_errors())

    def link_counts(self) -> dict[str, float]:
        """What the video link did (device_links.LinkStage.row), as the child last reported."""
        return {name: float(self._stats[_LINK + k]) for k, name in enumerate(_LINK_ROW)}

    def network_counts(self) -> dict[str, float]:
        """What the radio's video link did (radio.DeviceRadio.counts' row), as the child last reported."""
        return {name: float(self._stats[_RADIO + k]) for k, name in enumerate(_RADIO_ROW)}

    def _drain_errors(self) -> list[str]:
        out = []
        try:
            while self._errors_rx.poll():
                out.append(str(self._errors_rx.recv()))
        except (EOFError, OSError):
            pass
        return out

    @property
    def alive(self) -> bool:
        return self.process.is_alive()

    def close(self) -> None:
        """Stop the child (joined within 2 s, else terminated, then killed); idempotent."""
        f64(self._ctrl_raw)[_STOP] = 1.0
        if self.process.pid is not None:
            self.process.join(timeout=2.0)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(timeout=1.0)
            if self.process.is_alive():
                self.process.kill()
                self.process.join(timeout=1.0)
        self._errors_rx.close()


# ---- the child ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ChildArgs:
    """What the camera's child process is started with: the camera, its addresses (the drone's ip; the
    client's (ip, port)), rate (frames/s) and keyframe interval (frames), the shared blocks (control,
    target, stats), the error pipe's sending end, the parent's pid, the frames' way out and the stream's
    format block (`VideoProcess.configure`: the SDK 3.0 settings, over `fps` and the camera's size)."""

    spec: CameraSpec
    ip: str
    dest: tuple[str, int]
    fps: float
    gop_size: int
    ctrl_raw: Any
    target_raw: Any
    stats_raw: Any
    errors: Connection
    parent: int
    path: VideoPath
    format_raw: Any


def _child_main(a: ChildArgs) -> None:
    """Render, encode and send frames until the stop flag is set or the parent is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        _run(a)
    except Exception as exc:  # reported to the parent, which logs it in the emulator's errors
        a.errors.send(f"emulated camera {a.ip}: {exc!r}")
    finally:
        a.errors.close()


def _run(a: ChildArgs) -> None:
    from flightstack.config.links import LinkSpec
    from flightstack.hal import DroneIdentity
    from flightstack.paper.geometry import Pose

    from ..device_links import DeviceLinks
    from ..radio import DeviceRadio
    from .frames import stamp_frame_index
    from .video import frame_datagrams, make_encoder, scaled, scaled_pixels
    from .view import CameraView, drone_world_pose, index_area, index_is_checked

    spec, ip, dest, fps, gop_size, path = a.spec, a.ip, a.dest, a.fps, a.gop_size, a.path
    ctrl_raw, target_raw, stats_raw, parent = a.ctrl_raw, a.target_raw, a.stats_raw, a.parent
    ctrl = SeqBlock(ctrl_raw, _CTRL_N - 1)
    formats = SeqBlock(a.format_raw, _FORMAT_N)
    stop = f64(ctrl_raw)
    target = SeqBlock(target_raw, 4)
    st = f64(stats_raw)
    ring = st[_STATS_HEAD:].reshape(RING, _RECORD + 2 * len(spec.feature_points))
    view = CameraView(spec)
    view.image(Pose.make([0.0, 0.0, 1.0], 0.0), Pose.make([0.0, 0.0, 0.0], 0.0))  # warm the renderer's caches
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.bind((ip, 0))
    # the frames' way out: the video link (whole frames, late), then the drone's radio (per datagram)
    radio = None
    if path.network is not None and not path.network.clean:
        device = DroneIdentity(path.drone).label
        radio = DeviceRadio(path.network, path.seed, device, {"video": "video"}, path.epoch)
    sock: Any = raw if radio is None else radio.socket(raw, send=lambda _a: "video", recv=None)
    specs = {} if path.link is None else {"video": LinkSpec(**path.link)}
    line = None if radio is None else radio.delay_line  # the link's stage before the radio's, one thread
    links = DeviceLinks(specs, path.seed, path.drone, f"camera-{ip}", line)
    leaving: list[list[float]] = []  # [index, t_capture, due, bytes, truth...] of frames not left yet
    period = 1.0 / fps
    encoder: Any = None
    epoch, index, t0 = -1.0, 0, 0.0
    fmt: StreamFormat = (fps, spec.size, None)  # until `configure`
    size = spec.size
    st[_READY] = 1.0

    def report(now: float) -> None:
        """Record the frames that have left by now; copy the links' counters."""
        while leaving and leaving[0][2] <= now:
            rec = leaving.pop(0)
            k = int(st[_RECORDS])
            ring[k % RING] = rec
            st[_RECORDS] = k + 1  # after the record: a reader never sees a half-written one
            st[_FRAMES] += 1
            st[_BYTES] += rec[3]
        rows: list[tuple[int, tuple[str, ...], dict[str, float] | None]]
        rows = [(_LINK, _LINK_ROW, links.counts().get("video"))]
        if radio is not None:
            rows.append((_RADIO, _RADIO_ROW, radio.counts()["video"]))
        for at, names, row in rows:
            if row is not None:
                st[at : at + len(names)] = [row[n] for n in names]

    last: np.ndarray | None = None
    try:
        while stop[_STOP] == 0.0 and os.getppid() == parent:
            report(time.monotonic())
            c = ctrl.read()
            if c is None:  # never written, or the writer was preempted mid-write: the last good values
                c = last  # (a torn read is no `streamoff`: the stream and its frame index go on)
            else:
                last = c
            if c is None or c[_ON - 1] == 0.0:
                encoder = None
                time.sleep(0.01)
                continue
            f = formats.read()  # None until configured, or torn: the last good format stays
            now_fmt = fmt if f is None else (float(f[0]), (int(f[1]), int(f[2])), int(f[3]) or None)
            down = bool(c[_DOWN - 1])
            laid_out = down and view.cal.stream is not None  # the EDU's downward layout (view.py)
            want = spec.stream_size(True) if laid_out else now_fmt[1]
            if encoder is None or c[_EPOCH - 1] != epoch or now_fmt != fmt:  # a new setting: a new stream
                fmt = now_fmt
                encoder = make_encoder(want, fmt[0], gop_size, fmt[2])
                epoch, index, t0, period, size = c[_EPOCH - 1], 0, time.monotonic(), 1.0 / fmt[0], want
            elif want != size:  # the camera was switched mid-stream (`downvision`): a new size, a keyframe
                encoder = make_encoder(want, fmt[0], gop_size, fmt[2])
                size = want
            now = time.monotonic()
            due = t0 + index * period
            if due > now:
                wait = min(due - now, 0.05)
                if leaving:
                    wait = min(wait, max(0.0, leaving[0][2] - now))
                time.sleep(wait)
                continue
            if now - due > 3 * period:  # fell behind: skip frames instead of bursting
                index = int((now - t0) / period)
            g_wi = drone_world_pose(spec.start, (c[_X - 1], c[_Y - 1], c[_Z - 1]), c[_YAW - 1])
            tg = target.read()
            if tg is None:
                g_w0 = Pose.make([0.0, 0.0, -1e3], 0.0)  # no target yet: far below the floor, unseen
            else:
                g_w0 = Pose.make([tg[0], tg[1], 0.0], tg[2])
            if laid_out:  # the picture at its place in the layout; its truth in the picture's pixels
                img = view.frame(g_wi, g_w0, True)
                truth = view.true_pixels(g_wi, g_w0).reshape(-1).tolist()
            else:
                img = scaled(view.frame(g_wi, g_w0, False), size)
                truth = scaled_pixels(view.true_pixels(g_wi, g_w0), spec.size, size).reshape(-1).tolist()
            area = index_area(view.cal, img)
            stamp_frame_index(area, index, checked=index_is_checked(area, img))
            datagrams = frame_datagrams(encoder, img, index)
            t_capture = float(c[_T - 1])
            leaves = links.decide("video", t_capture)
            st[_INDEX] = index
            index += 1
            if leaves is None:  # the link lost the whole frame
                continue
            for d in datagrams:
                if not links.keeps("video", t_capture, len(d)):  # one datagram lost: a damaged frame
                    continue
                with contextlib.suppress(OSError):  # nobody listening yet is fine
                    links.send_at(leaves, sock, d, dest, "video")
            leaves = max(leaves, time.monotonic())
            for rec in leaving:  # a newer frame pushes the older ones out ahead of it (radio.DelayLine)
                rec[2] = min(rec[2], leaves)
            nbytes = float(sum(len(d) for d in datagrams))
            leaving.append([float(index - 1), t_capture, leaves, nbytes, *truth])
        report(time.monotonic())
    finally:
        links.close()
        if radio is not None:
            radio.close()
        raw.close()


__all__ = ["RING", "SeqBlock", "SharedTarget", "VideoPath", "VideoProcess"]
