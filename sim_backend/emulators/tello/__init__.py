"""Protocol-level emulator of a DJI/Ryze Tello (SDK 2.0/3.0 text protocol) for tests.

It speaks the real wire protocol, so an unmodified client (e.g. ``djitellopy``) can drive it: commands are
UTF-8 datagrams on ``emu.address`` (default ip ``127.0.0.2``, port from the OS), answered from that socket
to the sender's ip and port (``rc``, ``emergency`` and ``reboot`` unanswered, as on the real drone); state
strings at ``state_hz`` (10 Hz) from the emulator's IP to ``(client_ip, state_port)`` once in SDK mode;
after ``streamon``, H.264 Annex-B video (libx264 ultrafast, zerolatency, repeat-headers, a keyframe
every ``gop_size`` frames: 67 by default, the recorded bound) in datagrams of at most 1460 bytes to
``video_port`` (11111). ``djitellopy`` routes replies and state by source IP only, hence one loopback IP
per emulated drone (127.0.0.2, 127.0.0.3, ...). All traffic stays on 127.0.0.0/8; all threads are
daemons with bounded waits (<= 0.1 s), joined by ``close()``.

The behaviour per command, with the user reports it is based on, is described in ``commands``; the
phases, motion model, battery and state stream in ``physics``; the fault switches in
``faults``. Sources: *DJITelloPy #N* = https://github.com/damiafuentes/DJITelloPy/issues/N,
*Tello-Python #N* = https://github.com/dji-sdk/Tello-Python/issues/N, the SDK 2.0 and SDK 3.0 user guides
(URLs in ``faults``).

Layout: ``emulator`` (``TelloEmulator``: sockets, threads,
start/close) is built from ``base`` (configuration, logs, reply queue), ``physics``,
``commands`` and ``video`` (H.264 stream), with ``frames`` (frame sources, frame-index
bar code), ``net`` (loopback helpers) and ``recorded`` (what recordings of real Tellos show: the takeoff
``ok`` delay, ``h`` steps and drift, ``tof`` over the surface, ``vgz`` positive down, the keyframe interval).
"""
