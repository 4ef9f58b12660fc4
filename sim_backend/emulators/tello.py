"""Protocol-level emulator of a DJI/Ryze Tello (SDK 2.0/3.0 text protocol) for tests.

The emulator speaks the real wire protocol, so an unmodified client (e.g. ``djitellopy``) can drive it:

* **Commands** arrive as UTF-8 text datagrams on ``emu.address`` (``(ip, port)``, default ip ``127.0.0.2``,
  port picked by the OS).  Replies (``ok`` / ``error ...`` / a value for read commands) are sent back to the
  sender's address *and port* from that same socket, i.e. from the emulator's own ip:port (the real drone
  answers from 192.168.10.1:8889 to the sender's port: DJITelloPy #143, a client on an OS-assigned port got
  its replies).  ``rc``, ``emergency`` and ``reboot`` get no reply, like on the real drone.
* **State** strings (``mid:-1;x:..;...;agz:..;\\r\\n``) are sent at ``state_hz`` (10 Hz) from a socket bound
  to the emulator's IP to ``(client_ip, state_port)`` (default ``127.0.0.1:8890``) once SDK mode is entered.
  ``djitellopy`` routes replies *and* state to a drone object by the datagram's **source IP only**, hence one
  loopback IP per emulated drone (``127.0.0.2``, ``127.0.0.3``, ... for swarms).
* **Video**: after ``streamon`` a thread renders ``frame_source(t, emu)`` (``t`` = stream time ``n / fps`` of
  frame ``n``), encodes it with libx264 (ultrafast, zerolatency, repeat-headers, short GOP) and sends the raw
  Annex-B byte stream in datagrams of at most 1460 bytes to ``(client_ip, video_port)`` (default port 11111).

All traffic is restricted to 127.0.0.0/8: every configured address is validated and replies to a
non-loopback sender are dropped.  All threads are daemons with bounded waits (<= 0.1 s) and ``close()``
joins them.

Fault switches live in :class:`TelloFaults` (module ``tello_faults``, re-exported here, each switch names the
user reports it is based on).  Sources cited below: *DJITelloPy #N* =
https://github.com/damiafuentes/DJITelloPy/issues/N, *Tello-Python #N* =
https://github.com/dji-sdk/Tello-Python/issues/N, the SDK 2.0 and SDK 3.0 user guides (URLs in
``tello_faults``).

Behavioural choices (the real drone's behaviour is partly undocumented; where no report was found the choice
is marked *unverified*; clients must only rely on ``ok`` versus not ``ok``, error texts differ between
firmwares):

* **Before ``command``** (not in SDK mode) the real drone's text parser is not active - the SDK docs only
  say ``command`` must be sent first and that state packets start after it.  The emulator records such
  datagrams in ``commands`` and ``refused`` (as ``"ignored"``) but does not act on them and does not reply
  (configurable with ``pre_sdk_reply``, e.g. ``"error"``).  State packets are only sent in SDK mode.
* **Firmware**: by default a Tello EDU with SDK 3.0 (``sdk?`` -> ``30``).  With ``faults.sdk_version = "20"``
  the SDK-3.0-only verbs (``port``, ``downvision``, ``setfps``, ``setbitrate``, ``setresolution``,
  ``motoron``/``motoroff``, ``multiwifi``, ``reboot``, ``keepalive``, ``hardware?``, ... see
  ``SDK3_ONLY_COMMANDS``) answer ``unknown command: <verb>`` and have no effect (DJITelloPy #92, #107, #111,
  #138).
* **Phases** ``landed`` -> ``takeoff`` -> ``flying`` -> ``landing`` -> ``landed``; every transition is
  appended to ``phase_log``.  The motors run (state field ``time``, integer motor-on seconds, rises) in every
  phase but ``landed``.
* **Takeoff**: the motors start, the drone climbs linearly to ``takeoff_height_cm`` (80 cm) within the
  takeoff's duration but in at most ``TAKEOFF_CLIMB_S`` (2 s, *unverified*), hovers (stabilising) until the
  duration has passed, then replies ``ok``.  The duration is ``takeoff_s`` (default 0.3 s to keep tests fast;
  a real takeoff answers after ~3.9 s, Tello-Python #88) or ``faults.takeoff_s`` when set (slow takeoff:
  DJITelloPy #31, djitellopy waits 20 s).  Refused with ``error battery low`` below ``MIN_TAKEOFF_BATTERY``
  percent (real drones answer ``error`` or ``error Motor stop`` on a low battery: DJITelloPy #15, #60), with
  ``error`` while flying (*unverified* text).
* **Land** descends linearly over ``land_s`` (real: ~1.7 s, Tello-Python #88), the motors stop, then ``ok``.
  ``land`` while landed answers ``error Motor stop`` (DJITelloPy #126: ``end()`` "will hang retrying land()
  and eventually throw an exception" when the drone had already landed; ``error Motor stop`` is among the
  Tello's flight replies in dji-sdk/RoboMaster-SDK's ``TelloStatus`` and what DJITelloPy #15 got from a drone
  that would not spin up).
* **Busy**: ``takeoff``, ``land`` and moves received during a takeoff or landing answer ``error Not joystick``
  (``error Auto land`` during an auto-landing) and are not executed.  *Unverified*: no report gives the
  exact reply to ``land`` during ``takeoff``; the MATLAB support package for Ryze Tello ignores ``error Not
  joystick`` and ``error Auto land`` as replies that arrive while a "previous non-blocking command was not
  run to completion", and the RoboMaster SDK lists both among the Tello's flight replies.  Read commands are
  answered at once in every phase (*unverified*; djitellopy users read state while flying).  Flight commands
  while landed answer ``error Motor stop``.
* **``rc``** sets the joystick targets only in phase ``flying``; received in any other phase it is recorded in
  ``rc_history`` and ``refused`` but has no effect.  No reply, unless ``faults.rc_replies`` (``ok`` while
  flying, ``error Not joystick`` otherwise).  A malformed ``rc`` goes to ``rejected`` and ``refused``.
* **``emergency``**: no reply (Tello-Python #85, confirmed by Ryze support: "some commands do not return";
  DJITelloPy #125), the motors stop at once and the drone drops to h = 0; an interrupted takeoff/landing never
  answers.  ``reboot`` (SDK 3.0) does the same and leaves SDK mode.
* **Auto-land**: while flying, if no datagram (any command, including ``rc``) has been received for
  ``auto_land_s`` seconds (15 s, SDK 2.0/3.0 guides "Safety Function"; DJITelloPy #141) the drone lands by
  itself and ``landed_by_timeout`` is set.
* **Refused commands**: ``refused`` holds ``(time, phase at receipt, text, reply or "ignored")`` for every
  command the drone did not carry out: ignored ones (before ``command``, ``rc`` outside ``flying``, malformed
  ``rc``), and every reply that is not ``ok`` to a control/set command or is ``error ...``/``unknown command:
  ...`` to a read command (phase errors, ``out of range``, ``error_replies``, SDK 2.0 unknown verbs).  A
  refusal whose reply was lost or silenced is still recorded.  Successful commands never appear there.
* **Replies** are sent FIFO (a reply delayed by ``reply_delay_s`` holds back later ones); every datagram sent
  is logged in ``replies_sent``.  ``faults.lost_replies`` drops the reply of given verbs (the command runs);
  ``faults.duplicate_reply_after_s`` sends each reply again later, outside the FIFO order.
* **Motion model** (ground truth, world frame ``x`` forward at takeoff heading, ``y`` right, ``z`` up, yaw
  clockwise in degrees): ``rc a b c d`` sets body-frame velocity targets of 1 cm/s per unit (a = right,
  b = forward, c = up) and 1 deg/s per unit of yaw rate (d = clockwise); the actual velocity follows with a
  first-order lag (``tau_s`` = 0.1 s).  The last ``rc`` stays in effect until the next one.  Discrete moves
  (``forward 50``, ``cw 90``, ``go ...``) are applied instantaneously.  ``vgx/vgy/vgz`` are the world
  velocities in dm/s (rounded), ``h`` the height in cm (1 cm resolution) above the takeoff point,
  ``tof = h + 10`` cm, ``x/y/z`` the integrated position in cm (a test convenience - the real drone reports
  mission-pad coordinates there), pitch/roll are 0.
* **Battery**: ``faults.battery_pct`` is the *set-point*; the reported value drains from it slowly
  (``DRAIN_FLYING_PCT_S`` / ``DRAIN_IDLE_PCT_S``) and re-bases whenever the test writes a new value.
* ``port <state> <video>`` re-targets state and video (djitellopy's ``change_vs_udp``).
* **Video size** is fixed per emulator (``video_size``).  ``downvision 1`` only flips ``emu.downvision``; the
  frame source is expected to render the downward view at the same size (the real EDU downward camera is
  320x240 grey - not emulated, to keep a single encoder per stream).
* Read-command formats follow what the real drone sends (``height?`` -> ``"80dm"``, ``temp?`` -> ``"60~63"``,
  ``time?`` -> ``"0s"``, ``speed?`` -> ``"100.0"``, ``tof?`` -> ``"900mm"``); note that djitellopy's
  ``query_height``/``query_temperature``/``query_flight_time``/``query_speed`` ``int()``-parse these and
  therefore raise ``ValueError`` against the emulator (and, by report, against real drones).

* **Several controllers** (another socket or process of the same computer, e.g. the guardian process of
  drivers/guardian.py): once in SDK mode, commands from any source port are executed, and every datagram's
  sender is logged in ``senders``.  Replies go to the sender (Tello, DJITelloPy #143: a client on an
  OS-assigned port got its replies), or, with ``reply_port_latch=True`` (Tello EDU), always to the address
  that sent the first ``command`` (DJITelloPy PR #163, on EDU drones: a second run of a script on a new
  port "hangs on client_socket.recv" while "sending commands to the drone work[s] perfectly"; PR #168
  re-binds the client to port 8889 for the EDU).  *Unverified*: whether a second ``command`` moves the
  latch; here it does not.

Not modelled: binary (non-text)
datagrams some firmwares send on the command port (carlospzlz/ctello#7), ``error No valid imu`` and
``error, high temp`` refusals, ``motoron`` motor-on mode, battery auto-land, and the gradual reply-queue
backlog users see when sending commands back to back.

Layout: this module is the import path; the code lives in ``tello_emulator`` (``TelloEmulator``: sockets,
threads, start/close), built from ``tello_base`` (configuration, logs, state, reply queue),
``tello_physics`` (phases, motion model, battery, state stream), ``tello_commands`` (text protocol) and
``tello_video`` (H.264 stream), with ``tello_frames`` (frame sources, frame-index bar code), ``tello_net``
(loopback helpers) and ``tello_faults`` (fault switches, reply scheduling).
"""

from __future__ import annotations

from flightstack.ports import free_udp_port

from .tello_commands import text_of as text_of
from .tello_emulator import TelloEmulator
from .tello_faults import SDK3_ONLY_COMMANDS, ReplyScheduler, TelloFaults
from .tello_faults import has_sdk3 as has_sdk3
from .tello_frames import INDEX_BITS as INDEX_BITS
from .tello_frames import (
    FrameSource,
    default_frame_source,
    read_frame_index,
    stamp_frame_index,
)
from .tello_frames import default_square as default_square
from .tello_net import is_loopback, wait_until
from .tello_video import MAX_VIDEO_DATAGRAM as MAX_VIDEO_DATAGRAM

__all__ = [
    "SDK3_ONLY_COMMANDS",
    "FrameSource",
    "ReplyScheduler",
    "TelloEmulator",
    "TelloFaults",
    "default_frame_source",
    "free_udp_port",
    "is_loopback",
    "read_frame_index",
    "stamp_frame_index",
    "wait_until",
]
