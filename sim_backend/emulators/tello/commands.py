"""The Tello emulator's command protocol: receive text datagrams, run them, queue the replies.

`TelloCommands` is one layer of ``TelloEmulator`` (``emulator``). The real drone's behaviour is partly
undocumented; a choice no report backs is marked *unverified*, and clients may rely only on ``ok`` versus
not ``ok`` (error texts differ between firmwares). Sources are abbreviated as in ``tello.py``.

* **Before ``command``** the drone's parser is not active (SDK guides): datagrams are recorded in
  ``commands`` and ``refused`` (as ``"ignored"``), not acted on and not answered (``pre_sdk_reply``).
* **Firmware**: SDK 3.0 by default; with ``faults.sdk_version = "20"`` the SDK-3.0-only verbs
  (``SDK3_ONLY_COMMANDS``) answer ``unknown command: <verb>`` (DJITelloPy #92, #107, #111, #138).
* **Takeoff** answers ``ok`` after ``takeoff_s`` (default the recorded 8.70 s, ``recorded.TAKEOFF_OK_S``;
  ``FAST_TAKEOFF_S`` = 0.3 s for tests not about takeoff; Tello-Python #88 logs one of ~3.9 s) or
  ``faults.takeoff_s`` (slow takeoff, DJITelloPy #31); ``error battery low`` below
  ``MIN_TAKEOFF_BATTERY`` % (real drones: ``error`` or ``error Motor stop``, DJITelloPy #15, #60); ``error``
  while flying (*unverified*). **Land** takes ``land_s`` (real ~1.7 s, Tello-Python #88); ``land`` while
  landed answers ``error Motor stop`` (DJITelloPy #126, #15; RoboMaster-SDK ``TelloStatus``).
* **Busy**: ``takeoff``, ``land`` and moves during a takeoff or landing answer ``error Not joystick``
  (``error Auto land`` during an auto-landing) and do nothing (*unverified* for ``land`` during
  ``takeoff``; both texts are Tello flight replies in the RoboMaster SDK and the MATLAB Tello package).
  Read commands are answered in every phase (*unverified*); flight commands while landed answer
  ``error Motor stop``.
* **``rc``** acts only while ``flying`` (else recorded in ``rc_history`` and ``refused``); no reply unless
  ``faults.rc_replies``; a malformed one goes to ``rejected`` and ``refused``.
* **Its own landing** (15 s without a command, or the battery below ``faults.self_land_battery_pct``):
  ``rc`` is ignored (``refused``), ``takeoff``/``land``/moves answer ``error Auto land``
  (wesbos/javascript-drones#6: it "will ignore any further commands until it has landed").
* **Link and power** (``faults.uplink_down``, ``faults.downlink_down``, ``faults.powered_off``): a datagram
  that never reached the drone is logged in ``uplink_lost`` (not in ``commands``); one lost on its way back
  in ``downlink_lost`` (replies) or ``state_packets_lost``. After a power loss the drone boots out of SDK
  mode and streams nothing until ``command`` (DJITelloPy #169).
* **``emergency``**: no reply (Tello-Python #85, DJITelloPy #125), the motors stop and the drone drops; an
  interrupted takeoff/landing never answers. ``reboot`` (SDK 3.0) does the same and leaves SDK mode.
* **``refused``** holds ``(time, phase at receipt, text, reply or "ignored")`` for every command not
  carried out, also when its reply was lost; successful commands never appear there.
* **Replies** are FIFO (``reply_delay_s`` holds back later ones) and logged in ``replies_sent``;
  ``faults.lost_replies`` drops given verbs' replies, ``faults.duplicate_reply_after_s`` re-sends each later,
  ``faults.stray_replies`` sends a given verb a stray reply ahead of its own (*assumed* trigger).
* Read replies have the real drone's formats (``height?`` -> ``"80dm"``, ``temp?`` -> ``"60~63"``,
  ``time?`` -> ``"0s"``, ``speed?`` -> ``"100.0"``, ``tof?`` -> ``"900mm"``, which djitellopy's ``query_*``
  fail to ``int()``-parse); ``height?`` and ``tof?`` answer the state line's ``h`` and ``tof``
  (*unverified*). ``port <state> <video>`` re-targets the streams; ``downvision 1`` only flips
  ``emu.downvision`` (same video size: one encoder per stream).
* **Video settings** (SDK 3.0, ``flightstack.config.tello_video``): ``setfps high|middle|low`` sets ``fps``
  (30, 15, 5 frames/s), ``setresolution high|low`` the forward stream's size (960 × 720, 648 × 478;
  ``resolution``), ``setbitrate 0..5`` the encoder's target (``bitrate_mbps``: n Mbit/s, 0 auto: libx264's
  own rate control); the stream takes them from its next frame, with a new encoder. Another argument
  answers ``error`` (*unverified*); SDK 2.0 firmware answers ``unknown command: setfps`` (DJITelloPy #144,
  #219), and so does any firmware for a verb in ``faults.unknown_commands``.
* **Several controllers** (e.g. the guardian of drivers/guardian/): in SDK mode commands from any source
  port run and each sender is logged in ``senders``; replies go to the sender (DJITelloPy #143), or with
  ``reply_port_latch=True`` (Tello EDU) to the address of the first ``command`` (DJITelloPy PR #163, #168;
  *unverified*: a second ``command`` does not move the latch).

Not modelled: binary datagrams on the command port (carlospzlz/ctello#7), ``error No valid imu``,
``error, high temp``, ``motoron`` mode, the reply backlog of back-to-back commands.
"""

from __future__ import annotations

import logging
import time

from flightstack.drivers.tello.sdk_video import FPS_ARGS, VERBS, parse_argument

from ..net import is_loopback
from .base import DeferredReply
from .faults import SDK3_ONLY_COMMANDS, has_sdk3
from .physics import TelloPhysics, wrap_deg

LOG = logging.getLogger(f"{__package__}.tello")  # the public module's logger, as before the split

_READ_ONLY_OK = frozenset({"keepalive", "mon", "moff", "mdirection", "wifi", "ap", "EXT"})
_VIDEO_VERBS = frozenset(VERBS.values())  # setfps, setresolution, setbitrate
_MOVES = {"up": (0, 0, 1), "down": (0, 0, -1), "left": (0, -1, 0), "right": (0, 1, 0)}
_MOVES |= {"forward": (1, 0, 0), "back": (-1, 0, 0)}


class TelloCommands(TelloPhysics):
    """The command thread (``_command_loop``), the command handlers and the read-command answers."""

    def command_texts(self) -> list[str]:
        """Snapshot of the received command texts."""
        with self._lock:
            return [text for _, text in self.commands]

    # ------------------------------------------------------------------------------------------- commands
    def _command_loop(self) -> None:
        sock = self._cmd_sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(2048)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    break
                time.sleep(0.01)
                continue
            text = data.decode("utf-8", errors="replace").strip()
            if self.faults.powered_off or self.faults.uplink_down:  # never reached the drone
                why = "powered_off" if self.faults.powered_off else "uplink_down"
                self.uplink_lost.append((time.monotonic(), text, why))
                continue
            try:
                self._handle(text, (str(addr[0]), int(addr[1])))
            except Exception as exc:  # keep serving; surface the problem to the test
                LOG.exception("emulator failed on %r", text)
                self.errors.append(f"{text!r}: {exc!r}")

    def _handle(self, text: str, addr: tuple[str, int]) -> None:
        now = time.monotonic()
        with self._lock:
            self.commands.append((now, text))
            self.senders.append((now, text, addr))
            if self.netns is None and not is_loopback(addr[0]):  # in its namespace: the caller's links only
                self.rejected.append(f"{text} (non-loopback sender {addr[0]})")
                return
            faults, phase = self.faults, self._phase
            words = text.split()
            verb, args = (words[0], words[1:]) if words else ("", [])
            delay = float(faults.reply_delay_s)
            if verb == "command" and self._first_client is None:
                self._first_client = addr
            self._last_client = addr
            to = self._first_client if self.reply_port_latch and self._first_client else addr
            reply_addr = None if faults.silent or verb in faults.lost_replies else to
            if not self.sdk_mode and verb != "command":
                reply = self.pre_sdk_reply
                self._refuse(now, phase, text, "ignored" if reply is None else reply)
                if reply is not None:
                    self._reply(reply, reply_addr, now, delay)
                return
            self._last_cmd_t = now
            stray = faults.stray_replies.get(verb)
            if stray is not None and not faults.silent:
                self._replies.schedule_stray(stray, to, now)
            if verb in faults.unknown_commands or (
                verb in SDK3_ONLY_COMMANDS and not has_sdk3(faults.sdk_version)
            ):
                answer: str | None = f"unknown command: {verb}"
            elif verb == "rc":
                answer = self._rc_command(args, now, phase)
            elif verb in ("emergency", "reboot"):
                self._execute_no_reply(verb, now)
                return
            elif faults.error_replies:
                answer = "error"
            else:
                answer = self._execute(verb, args, now)
                if answer is None:  # takeoff/land: replied on completion by the sim thread
                    self._deferred = DeferredReply(reply_addr, delay)
                    return
            if answer is None:  # rc without a reply
                return
            if _is_refusal(verb, answer):
                self._refuse(now, phase, text, answer)
            self._reply(answer, reply_addr, now, delay)

    def _refuse(self, now: float, phase: str, text: str, reply: str) -> None:
        self.refused.append((now, phase, text, reply))

    def _rc_command(self, args: list[str], now: float, phase: str) -> str | None:
        """Apply one ``rc``; return its reply (only with ``faults.rc_replies``) or None."""
        text = text_of("rc", args)
        try:
            values = tuple(int(a) for a in args)
        except ValueError:
            values = ()
        if len(values) != 4:
            self.rejected.append(text)
            self._refuse(now, phase, text, "ignored")
            return None
        a, b, c, d = (max(-100, min(100, v)) for v in values)
        self.rc_history.append((now, (a, b, c, d)))
        if phase == "flying":
            self._rc[:] = (a, b, c, d)
            return "ok" if self.faults.rc_replies else None
        if self.faults.rc_replies:
            return "error Not joystick"
        self._refuse(now, phase, text, "ignored")
        return None

    def _execute_no_reply(self, verb: str, now: float) -> None:
        """``emergency`` (motors stop at once, the drone drops) or ``reboot``."""
        self._set_landed(now)
        self._deferred = None  # an interrupted takeoff/landing never answers
        self._pos[2] = 0.0
        if verb == "reboot":
            self.sdk_mode = False
            self._first_client = None
            self.streaming = False

    def _busy_reply(self) -> str:
        """Reply to a command that needs a settled drone while it takes off or lands."""
        own = self.landed_by_timeout or self.landed_by_battery or self.landed_by_itself
        auto = own and self._phase == "landing"
        return "error Auto land" if auto else "error Not joystick"

    def _execute(self, verb: str, args: list[str], now: float) -> str | None:
        """Run one reply-expecting command; return the reply, or None when it is deferred."""
        if verb.endswith("?"):
            return self._read(verb)
        if verb == "command":
            self.sdk_mode = True
            return "ok"
        if verb == "takeoff":
            if self._phase in ("takeoff", "landing"):
                return self._busy_reply()
            if self._phase == "flying":
                return "error"
            if self._battery_locked() < self.MIN_TAKEOFF_BATTERY:
                return "error battery low"
            self._rc[:] = 0.0
            self._h_drift = 0.0  # h is relative to the takeoff point: its drift starts at each takeoff
            duration = self.faults.takeoff_s
            self._start_phase("takeoff", now, self.takeoff_s if duration is None else float(duration))
            self.landed_by_timeout = False
            self.landed_by_battery = self.landed_by_itself = False
            return None
        if verb == "land":
            if self._phase == "landed":
                return "error Motor stop"
            if self._phase != "flying":
                return self._busy_reply()
            self._start_phase("landing", now, self.land_s)
            return None
        if verb == "streamon":
            if not self.streaming:
                self._stream_epoch += 1
            self.streaming = True
            return "ok"
        if verb == "streamoff":
            self.streaming = False
            return "ok"
        if verb == "downvision":
            if args not in (["0"], ["1"]):
                return "error"
            self.downvision = args[0] == "1"
            return "ok"
        if verb == "port":
            try:
                state_port, video_port = (int(a) for a in args)
            except ValueError:
                return "error"
            if not (1025 <= state_port <= 65535 and 1025 <= video_port <= 65535):
                return "error"
            self.state_port, self.video_port = state_port, video_port
            return "ok"
        if verb == "speed":
            try:
                speed = float(args[0])
            except (IndexError, ValueError):
                return "error"
            if not 10 <= speed <= 100:
                return "out of range"
            self.speed_setting = speed
            return "ok"
        if verb in _VIDEO_VERBS:
            return self._video_setting(verb, args)
        if verb in ("motoron", "motoroff"):
            return "ok" if self._phase == "landed" else "error"
        if verb in _READ_ONLY_OK:
            return "ok"
        if verb in _MOVES or verb in ("cw", "ccw", "go", "curve", "jump", "flip", "stop"):
            return self._move(verb, args)
        return f"unknown command: {verb}"

    def _video_setting(self, verb: str, args: list[str]) -> str:
        """``setfps``, ``setresolution`` or ``setbitrate`` (SDK 3.0): kept, and applied by the video stream
        from its next frame (``video.TelloVideoStream.stream_format``); an argument the SDK 3.0 guide does
        not list answers ``error`` (*unverified*: no report of the real answer)."""
        arg = parse_argument(verb, args[0]) if len(args) == 1 else None
        if isinstance(arg, int) and verb == "setbitrate":
            self.bitrate_mbps = arg
        elif isinstance(arg, str) and verb == "setfps":
            self.fps = FPS_ARGS[arg]
        elif isinstance(arg, str) and verb == "setresolution":
            self.resolution = arg
        else:
            return "error"
        return "ok"

    def _move(self, verb: str, args: list[str]) -> str:
        if self._phase in ("takeoff", "landing"):
            return self._busy_reply()
        if self._phase != "flying":
            return "error Motor stop"
        if verb == "stop":
            self._rc[:] = 0.0
            return "ok"
        if verb == "flip":
            return "ok" if args in (["l"], ["r"], ["f"], ["b"]) else "error"
        try:
            nums = [int(a) for a in args if not a.startswith("m")]
        except ValueError:
            return "error"
        if verb in _MOVES:
            if len(nums) != 1 or not 20 <= nums[0] <= 500:
                return "out of range"
            fwd, right, up = (nums[0] * k for k in _MOVES[verb])
            self._displace(fwd, right, up)
        elif verb in ("cw", "ccw"):
            if len(nums) != 1 or not 1 <= nums[0] <= 3600:
                return "out of range"
            self._yaw = wrap_deg(self._yaw + (nums[0] if verb == "cw" else -nums[0]))
        elif verb == "go" and len(nums) >= 3:
            self._displace(nums[0], nums[1], nums[2])
        elif verb == "curve" and len(nums) >= 6:
            self._displace(nums[3], nums[4], nums[5])
        elif verb == "jump" and len(nums) >= 3:
            self._displace(nums[0], nums[1], nums[2])
        else:
            return "error"
        return "ok"

    def _read(self, verb: str) -> str:
        h = max(0, round(float(self._pos[2])))  # the true height (baro?)
        values = {
            "battery?": str(self._battery_locked()),
            "speed?": f"{self.speed_setting:.1f}",
            "time?": f"{int(self._motor_s)}s",
            "height?": f"{self._reported_h() // 10}dm",
            "temp?": "60~63",
            "attitude?": f"pitch:0;roll:0;yaw:{round(wrap_deg(self._yaw))};",
            "baro?": f"{12.3 + h / 100:.2f}",
            "tof?": f"{self._reported_tof() * 10}mm",
            "acceleration?": "agx:0.00;agy:0.00;agz:-1000.00;",
            "wifi?": "90",
            "sdk?": str(self.faults.sdk_version),
            "sn?": "0TQEMU" + "".join(f"{int(o):03d}" for o in self.ip.split(".")[1:]),
            "hardware?": "TELLO",
            "active?": "ok",
        }
        return values.get(verb, f"unknown command: {verb}")


def _is_refusal(verb: str, reply: str) -> bool:
    """True when ``reply`` means the drone did not carry out ``verb`` (a read command answers a value)."""
    if reply.startswith(("error", "unknown command")):
        return True
    return not verb.endswith("?") and reply != "ok"


def text_of(verb: str, args: list[str]) -> str:
    """Re-assemble a command from its verb and arguments."""
    return " ".join([verb, *args])
