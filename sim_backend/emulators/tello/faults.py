"""Fault switches and reply scheduling of the loopback Tello emulator (re-exported by ``tello.py``).

Every switch models something users of the real drone have reported; the sources are named in each switch's
docstring.  Abbreviations: *DJITelloPy #N* = https://github.com/damiafuentes/DJITelloPy/issues/N,
*Tello-Python #N* = https://github.com/dji-sdk/Tello-Python/issues/N, *SDK 2.0 guide* =
https://dl-cdn.ryzerobotics.com/downloads/Tello/Tello%20SDK%202.0%20User%20Guide.pdf, *SDK 3.0 guide* =
https://dl.djicdn.com/downloads/RoboMaster+TT/Tello_SDK_3.0_User_Guide_en.pdf.
"""

from __future__ import annotations

import heapq
import itertools
import math
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["SDK3_ONLY_COMMANDS", "ReplyScheduler", "TelloFaults", "has_sdk3"]

SDK3_ONLY_COMMANDS = frozenset(
    {
        # control/set commands new in the SDK 3.0 guide (table "SDK 2.0 | SDK 3.0" of
        # https://github.com/harleylara/tello-python/blob/main/README.md, DJITelloPy #92)
        "reboot",
        "motoron",
        "motoroff",
        "throwfly",
        "port",
        "setfps",
        "setbitrate",
        "setresolution",
        "multiwifi",
        "wifisetchannel",
        "EXT",
        # found on SDK 3.0 firmware by users (DJITelloPy #92, tellopilots "SDK 3.0 for Tello EDU" thread)
        "downvision",
        "keepalive",
        # read commands new in SDK 3.0
        "hardware?",
        "wifiversion?",
        "ap?",
        "ssid?",
        "active?",
    }
)
"""Verbs an SDK 2.0 firmware answers with ``unknown command: <verb>`` (and ignores).

DJITelloPy #138: ``'unknown command: motoron'`` from a Tello on firmware 01.04.92.01 (SDK 2.0);
DJITelloPy #107: SDK-3.0 video settings unknown to an SDK 2.0 drone; DJITelloPy #111: ``downvision``
(``set_video_direction``) not working on a drone without SDK 3.0."""


def has_sdk3(sdk_version: str) -> bool:
    """True when an ``sdk?`` answer of ``sdk_version`` means SDK 3.0 or later (``"30"``)."""
    try:
        return int(sdk_version) >= 30
    except ValueError:
        return False


@dataclass
class TelloFaults:
    """Fault switches; plain attributes the test thread may change at any time.

    Unless stated otherwise a switch is read when a command is received.  The defaults describe a healthy
    Tello EDU with SDK 3.0 firmware on a clean link.  To restore the defaults, copy the attributes of a fresh
    ``TelloFaults()`` (``lost_replies``, ``stray_replies`` and ``unknown_commands`` have a
    ``default_factory``: their ``dataclasses.Field.default`` is ``MISSING``).
    """

    silent: bool = False
    """No replies at all (commands are still recorded and executed, like lost reply datagrams)."""
    error_replies: bool = False
    """Reply ``error`` to every command that expects a reply, except ``rc`` (and do not execute it); recorded
    in ``emu.refused``.  Real drones answer ``error`` e.g. to ``takeoff`` on low battery or when not
    calibrated (DJITelloPy #37, #60, #101)."""
    reply_delay_s: float = 0.0
    """Extra latency added to every reply (evaluated when the command is received)."""
    drop_state: bool = False
    """Stop sending state packets."""
    battery_pct: int = 87
    """Battery set-point in percent; the reported value drains slowly from it."""
    no_video: bool = False
    """Stop sending video datagrams (the stream clock keeps running, so frame indices jump)."""
    duplicate_reply_after_s: float | None = None
    """Send every reply a second time, this many seconds after the first (read when the reply is queued).

    Models duplicated/late datagrams on a lab Wi-Fi: UDP gives no guarantee against either, and a reply that
    arrives after its command gave up is taken by djitellopy as the answer to the *next* command (one queue
    per drone, first datum wins - djitellopy 2.5.0 ``send_command_with_return``).  Users see exactly that
    off-by-one: carlospzlz/ctello#7 (https://github.com/carlospzlz/ctello/issues/7: ``sn?`` answered ``ok``,
    ``sdk?`` answered ``unknown command: sn?``), DJITelloPy #2 ("returns false but still partially done"). The
    duplicate bypasses the FIFO ordering of normal replies: it never holds back a later reply, and is logged
    as ``"duplicate"`` in ``emu.replies_sent``.  A lost or silenced reply has no duplicate."""
    lost_replies: set[str] = field(default_factory=set)
    """Verbs (``{"takeoff"}``, ``{"land"}``, ``{"command"}``, ...) whose reply datagram is lost; the command
    is still executed (and still recorded in ``emu.refused`` if it was refused).

    dji-sdk/Tello-Python #85: a Ryze engineer confirms "UDP connections have a high probability of packet
    loss. And some commands have relatively serious packet loss"; DJITelloPy #2 and #31: ``takeoff`` timed out
    in the client while the drone took off; DJITelloPy #167: the drone sent ``ok`` (seen in Wireshark) that
    the client never got; akshayvernekar/telloArduino#4: the reply to ``command`` "is sometimes lost"."""
    stray_replies: dict[str, str] = field(default_factory=dict)
    """Verb → a stray reply the drone sends the moment it receives that verb, ahead of the verb's own answer
    (which still follows, with ``reply_delay_s``, unless ``lost_replies`` names the verb: the stray then
    takes its place).  Outside the FIFO order of normal replies, like a duplicate; logged as ``"stray"`` in
    ``emu.replies_sent``.  Real transcripts of Tello flights show replies against the wrong request
    (``battery?`` answered ``ok``, ``forward 139`` answered ``70``), seen from the client; whether the drone
    or the client crossed them is unknown.  The trigger (a reply sent on receipt of a given verb) is
    *assumed*: no recording here shows when a stray comes."""
    takeoff_s: float | None = None
    """When set, overrides the emulator's ``takeoff_s`` (read when ``takeoff`` is received): a slow takeoff.

    The drone climbs at its normal rate (``TelloEmulator.TAKEOFF_CLIMB_S``) and then hovers, stabilising,
    until the ``ok``.  DJITelloPy #31: takeoff "orients itself using its cameras and sensors ... depending on
    the light and surrounding this can take a few seconds", the 7 s response timeout was exceeded and
    djitellopy now waits ``TAKEOFF_TIMEOUT`` = 20 s (PR #41); dji-sdk/Tello-Python #88 logs a normal takeoff
    ``ok`` after 3.9 s and a ``land`` ``ok`` after 1.7 s."""
    rc_replies: bool = False
    """A firmware that answers ``rc``: ``ok`` while flying, ``error Not joystick`` otherwise (recorded in
    ``emu.refused``).  The SDK 2.0/3.0 guides give ``rc`` no reply and djitellopy sends it without waiting;
    robagar/tello-asyncio#10 (a client that waited for a reply to ``rc`` timed out, "rc has no response by
    design") is why the default is False.  But djitellopy users receive ``error Not joystick`` as the answer
    to *other* commands (DJITelloPy #197; #201: ``forward 100`` answered ``error Not joystick`` mid-mission),
    which is what a reply to an earlier datagram looks like in djitellopy's single reply queue; the MATLAB
    support package for Ryze Tello deliberately ignores ``error Not joystick``/``error Auto land`` replies as
    belonging to "previous non-blocking command[s]".  With this switch a driver that streams ``rc`` next to
    blocking commands sees those stray replies."""
    uplink_down: bool = False
    """Every datagram to the drone is lost (read when one arrives): a Wi-Fi outage from the computer to the
    drone. Lost datagrams go to ``emu.uplink_lost``, not to ``commands``; the drone keeps its last ``rc``
    (SDK guides: ``rc`` sets the sticks until the next one) and lands by itself after ``auto_land_s``
    without a command.  With ``downlink_down`` it is a two-way outage.  A lab Wi-Fi drops in bursts and in
    one direction at a time: dji-sdk/Tello-Python #85 (a Ryze engineer: "UDP connections have a high
    probability of packet loss"), DJITelloPy #167 (an ``ok`` seen in Wireshark that never reached the
    client), DJITelloPy #2 (commands lost while others arrive)."""
    downlink_down: bool = False
    """Every datagram from the drone is lost: replies (logged in ``emu.downlink_lost``), state packets
    (counted in ``emu.state_packets_lost``) and video.  The drone still obeys what it receives."""
    powered_off: bool = False
    """The drone has no power (battery knocked loose in flight; read every simulation tick). On the switch to
    True it falls (motors off at once, height 0); while True it receives nothing (datagrams logged in
    ``emu.uplink_lost``) and sends nothing. On the switch back it boots as after a power cycle: on the ground,
    motor-on time 0, not in SDK mode, no state stream and no video until it gets ``command`` (DJITelloPy #169:
    after a battery swap "all you need to do is call ``drone.connect()`` again, which tells the restarted
    drone your PC controls it"; SMerrony/tellodesk#3: status no longer updated after reconnecting following a
    battery change, https://github.com/SMerrony/tellodesk/issues/3). Each boot is logged in
    ``emu.power_log``."""
    auto_land_notice: bool = False
    """When the drone starts a landing of its own (``auto_land_s`` without a command, or
    ``self_land_battery_pct``), it also sends ``error Auto land`` to its client unprompted. Source: a real
    Tello answered ``error Auto land`` against a ``battery?`` poll right after ``land`` (a user's console
    transcript); that it sends one *unprompted*, and when, is **assumed**."""
    self_land_now: bool = False
    """Set: the drone begins a landing of its own at its next step while flying (what a low battery, an
    overheat or its 15 s timeout make a real Tello do, without their cause; ``landed_by_itself``), then the
    switch clears. rc is refused until it is down, as in every landing of its own."""
    self_land_battery_pct: int | None = 10
    """While flying with the battery below this (%), the drone lands by itself (``landed_by_battery``): rc is
    ignored (recorded in ``refused``) and ``takeoff``/``land``/moves answer ``error Auto land`` until it is
    down. kebhr/scratch3-tello#10 (https://github.com/kebhr/scratch3-tello/issues/10: the Tello blinks red on
    low battery and lands); wesbos/javascript-drones#6 (https://github.com/wesbos/javascript-drones/issues/6:
    during its own landing the drone "will ignore any further commands until it has landed but is still
    sending through status updates"). The threshold is *unverified* (no published number; the emulator refuses
    takeoff below ``MIN_TAKEOFF_BATTERY`` = 10 %, so the two agree); None disables the self-landing."""
    unknown_commands: set[str] = field(default_factory=set)
    """Verbs this firmware does not know, whatever its ``sdk?`` says: answered ``unknown command: <verb>``
    and not carried out (recorded in ``emu.refused``). DJITelloPy #144: ``unknown command: setresolution``
    from a Tello whose app called its firmware up to date; DJITelloPy #219: ``unknown command: setbitrate``
    from a Tello (Boost Combo) with updated firmware."""
    sdk_version: str = "30"
    """The answer to ``sdk?``.  Below ``"30"`` (e.g. ``"20"``, Tello/Tello EDU on SDK 2.0 firmware) every verb
    in :data:`SDK3_ONLY_COMMANDS` (``port``, ``downvision``, ``setfps``, ``setbitrate``, ``setresolution``,
    ``motoron``/``motoroff``, ``multiwifi``, ``reboot``, ``keepalive``, ...) answers
    ``unknown command: <verb>`` and has no effect (DJITelloPy #92, #107, #111, #138)."""


class ReplyScheduler:
    """Queue of reply datagrams, each sent at its due time by :meth:`run` (one thread).

    Normal replies leave in the order they were queued (FIFO, like the drone's single command interpreter): a
    reply is never sent before one queued earlier, so a reply delayed by ``reply_delay_s`` holds back later
    normal replies.  Duplicates (``duplicate_reply_after_s``) and strays (``stray_replies``) are outside that
    order: they neither wait for nor hold back normal replies.  Every datagram sent is appended to
    :attr:`sent` as ``(time.monotonic(), text, "normal" | "duplicate" | "stray")`` immediately before it
    leaves the socket (a failed send is also reported in the emulator's ``errors``).
    """

    def __init__(
        self, lock: threading.RLock, errors: list[str], blocked: Callable[[], bool] | None = None
    ) -> None:
        """``lock``: the emulator's lock (replies are queued while holding it); ``errors``: its error list;
        ``blocked``: True while the downlink is down (a due reply then goes to :attr:`lost`, not out)."""
        self.cond = threading.Condition(lock)
        self.sent: list[tuple[float, str, str]] = []
        self.lost: list[tuple[float, str, str]] = []
        """``(time.monotonic(), text, kind)`` of every reply lost on a downlink that was down when due."""
        self._blocked = blocked
        self._errors = errors
        self._heap: list[tuple[float, int, str, tuple[str, int], str]] = []
        self._seq = itertools.count()
        self._last_normal_due = -math.inf

    def schedule(
        self, text: str, addr: tuple[str, int] | None, now: float, delay: float, duplicate_after: float | None
    ) -> None:
        """Queue ``text`` for ``addr`` (None = lost: nothing is sent) at ``now + delay``, FIFO among normal
        replies, plus a duplicate ``duplicate_after`` seconds after the normal one when that is not None."""
        if addr is None:
            return
        with self.cond:
            due = max(now + max(0.0, delay), self._last_normal_due)
            self._last_normal_due = due
            heapq.heappush(self._heap, (due, next(self._seq), text, addr, "normal"))
            if duplicate_after is not None:
                dup_due = due + max(0.0, float(duplicate_after))
                heapq.heappush(self._heap, (dup_due, next(self._seq), text, addr, "duplicate"))
            self.cond.notify_all()

    def schedule_stray(self, text: str, addr: tuple[str, int], now: float) -> None:
        """Queue ``text`` for ``addr`` at ``now``, outside the FIFO order of normal replies (a stray)."""
        with self.cond:
            heapq.heappush(self._heap, (now, next(self._seq), text, addr, "stray"))
            self.cond.notify_all()

    def wake(self) -> None:
        """Wake :meth:`run` (used on shutdown)."""
        with self.cond:
            self.cond.notify_all()

    def run(self, sock: socket.socket, stop: threading.Event) -> None:
        """Send due replies from ``sock`` until ``stop`` is set (waits are bounded by 0.1 s)."""
        while not stop.is_set():
            with self.cond:
                if not self._heap:
                    self.cond.wait(0.1)
                    continue
                due, _, text, addr, kind = self._heap[0]
                wait = due - time.monotonic()
                if wait > 0:
                    self.cond.wait(min(wait, 0.1))
                    continue
                heapq.heappop(self._heap)
            if self._blocked is not None and self._blocked():
                self.lost.append((time.monotonic(), text, kind))
                continue
            # recorded just before it leaves, so that a client holding the datagram always finds the record
            self.sent.append((time.monotonic(), text, kind))
            try:
                sock.sendto(text.encode("utf-8"), addr)
            except OSError as exc:  # never on loopback in practice; tests assert emu.errors == []
                self._errors.append(f"reply {text!r} to {addr} failed: {exc!r}")
