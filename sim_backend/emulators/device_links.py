"""The rig's links (flightstack.config.links) applied at an emulated device, where its data is produced.

A link of the rig's `links:` makes one kind of a device's data late and lossy: each sample leaves the
device (or, for commands, is acted on) latency_s + U(0, jitter_s) after it was produced (or received),
and is lost with probability `loss`. The emulated lab applies them in its emulators, before the radio
(flightstack.netem, radio.py): a sample first waits for its link, then passes the device's radio.

* `LinkStage`: one link's decisions, drawn by the simulated lab's own model (config.links.LinkDelays)
  from a generator seeded as the simulated lab seeds it (the mission's seed, the link, the device's
  number: a drone's id, 0 for the motion capture and the robot), so both labs make the same decisions
  for the same seed; with counters.
* `DeviceLinks`: the stages of one device and the delay line that sends its late datagrams (the device
  radio's line when it has one: one scheduler thread per device, the link's stage before the radio's).
* `DeviceLinks.socket` wraps a device's socket (or its radio's) in the one socket wrapper,
  radio.ImpairedSocket, with the device's links as its decider. `sendto` (a sample leaving the device): the
  stage of `send(addr)` decides and the datagram leaves by the wrapped socket when due, as part of that
  link's stream (radio.DelayLine: a newer sample pushes older ones out ahead of it, so the stream stays in
  order and its newest sample arrives when due). `recvfrom` (commands entering the device): every datagram
  is decided when it reaches the device and handed to the device's receive loop when due, in order of due
  time (a later command can overtake an earlier one, as in the simulated lab).
* A video frame is decided as a whole: `DeviceLinks.decide("video", t_capture)` gives its due time (None:
  lost) and the camera schedules its datagrams (`send_at`); each datagram of a frame that leaves is then
  kept or lost by itself (`keeps`: the link's `datagram_loss` in bursts of `datagram_burst`, a
  flightstack.netem Gilbert chain stepped once per datagram, seeded by the mission's seed, the device and
  the link), so that a loss damages a frame as on a real Tello instead of removing it.

`emulated_links(links)`: the links the emulated lab applies. Profile `perfect` is what the emulated lab
did before links were modelled: nothing late (its rc 50 ms is the simulated lab's command-to-effect
latency; the emulated Tello's own first-order response stands for it); links written out in `links:` and
every link of another profile are applied as they are. Rates: a link's `rate_hz` sets the device's own
rate (the Tello's state stream, the camera's frame rate, the motion capture's frame rate); commands have
no rate. Times are time.monotonic() seconds.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from flightstack.config.links import LINKS, NONE, LinkSpec, LinksSpec
from flightstack.netem import LinkModel, LinkProfile

from .radio import Address, DelayLine, ImpairedSocket, Sender, counter_row

EMULATED_LINKS = ("video", "state", "rc", "mocap", "robot")
"""The links the emulators apply (the bus is between agent processes, not a device's)."""
LINK_COUNTERS = ("samples", "lost", "delivered", "datagrams", "datagrams_lost")
"""The counters every stage reports, 0 included (plus delay_mean_ms of the delivered samples); the
datagram pair counts only with a datagram loss (LinkStage.keeps)."""


def emulated_links(links: LinksSpec) -> dict[str, LinkSpec]:
    """The links the emulated lab applies (module docstring; EMULATED_LINKS): link name -> spec, perfect
    ones left out."""
    out = {}
    for name in EMULATED_LINKS:
        spec = links.emulated(name)
        if not spec.perfect:
            out[name] = spec
    return out


class LinkStage:
    """The decisions of one link of one device (thread-safe): `decide(t)` -> due time or None (lost)."""

    def __init__(self, spec: LinkSpec, seed: int, link: str, device: int) -> None:
        from flightstack.config.links import LinkDelays

        self.spec = spec
        self.name = link
        self._delays = LinkDelays(spec, np.random.default_rng([int(seed), LINKS.index(link), int(device)]))
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.delay_sum_s = 0.0
        self._datagrams = None
        if spec.datagram_loss > 0:
            prof = LinkProfile.bursty(spec.datagram_loss, spec.datagram_burst)
            self._datagrams = LinkModel(prof, seed, f"device{device}", f"{link}-datagrams")

    def keeps(self, t: float, size: int) -> bool:
        """Whether one datagram (`size` bytes, sent at t s) of a sample that left survives the link's
        datagram loss (always, without one)."""
        if self._datagrams is None:
            return True
        with self._lock:
            self.counts["datagrams"] += 1
            kept = bool(self._datagrams.decide(t, size))
            self.counts["datagrams_lost"] += not kept
            return kept

    @property
    def late(self) -> bool:
        """True when a sample can be late (else it leaves at once, unless lost)."""
        return self.spec.latency_s > 0 or self.spec.jitter_s > 0

    def decide(self, t: float) -> float | None:
        """When a sample produced (or received) at t (s) is due, None when it is lost."""
        with self._lock:
            self.counts["samples"] += 1
            if self._delays.lost():
                self.counts["lost"] += 1
                return None
            d = self._delays.delay()
            self.counts["delivered"] += 1
            self.delay_sum_s += d
            return t + d

    def row(self) -> dict[str, float]:
        """The counters and delay_mean_ms (JSON-ready)."""
        with self._lock:
            return counter_row(LINK_COUNTERS, self.counts, self.delay_sum_s)


class DeviceLinks:
    """The applied links of one emulated device (module docstring).

    specs: link name -> spec (perfect ones are left out); seed: the mission's seed; device: the device's
    number in the seed (a drone's id; 0 for the motion capture and the robot); name: for the thread;
    delay_line: the device radio's (None: its own, started on first use and stopped by `close`)."""

    def __init__(
        self,
        specs: dict[str, LinkSpec],
        seed: int,
        device: int,
        name: str,
        delay_line: DelayLine | None = None,
    ) -> None:
        self.name = name
        self.stages = {k: LinkStage(v, seed, k, device) for k, v in specs.items() if not v.perfect}
        self._own_line = delay_line is None
        self.delay_line = DelayLine(f"{name}-links") if delay_line is None else delay_line

    def applies(self, link: str) -> bool:
        """True when `link` changes anything on this device."""
        return link in self.stages

    def spec(self, link: str) -> LinkSpec:
        """The spec of `link` (NONE when it is not applied)."""
        stage = self.stages.get(link)
        return NONE if stage is None else stage.spec

    def decide(self, link: str, t: float) -> float | None:
        """When a sample of `link` produced at t is due (t when the link is not applied; None: lost)."""
        stage = self.stages.get(link)
        return t if stage is None else stage.decide(t)

    def keeps(self, link: str, t: float, size: int) -> bool:
        """Whether a datagram of `link` sent at t survives its datagram loss (LinkStage.keeps)."""
        stage = self.stages.get(link)
        return True if stage is None else stage.keeps(t, size)

    def fates(self, link: str, t: float, size: int) -> list[float]:
        """LinkDecider (radio.py): `decide` as a list ([]: lost)."""
        due = self.decide(link, t)
        return [] if due is None else [due]

    def send(self, dues: list[float], sock: Sender, data: bytes, addr: Address, link: str) -> None:
        """LinkDecider: `send_at` (a sample has one due time)."""
        for due in dues:
            self.send_at(due, sock, data, addr, link)

    def send_at(self, due: float, sock: Sender, data: bytes, addr: Address, link: str) -> None:
        """Send `data` by `sock` at `due`, in order with `link`'s other samples (at once when the link
        is never late)."""
        stage = self.stages.get(link)
        if stage is None or not stage.late:
            sock.sendto(data, addr)
        else:
            self.delay_line.schedule(due, sock, data, addr, stream=link)

    def socket(
        self,
        sock: Any,
        send: Callable[[Address], str | None] | None = None,
        recv: str | None = None,
        on_lost: Callable[[bytes, float], None] | None = None,
    ) -> Any:
        """`sock` wrapped (module docstring): datagrams it sends pass link `send(addr)` (None: unchanged),
        datagrams it receives pass link `recv`; on_lost(data, t) for every received datagram the link
        loses. `sock` itself when `recv` is not applied and `send` is None."""
        if send is None and (recv is None or not self.applies(recv)):
            return sock
        return ImpairedSocket(sock, self, send, recv, on_lost)

    def counts(self) -> dict[str, dict[str, float]]:
        """Per applied link: LINK_COUNTERS and delay_mean_ms (JSON-ready)."""
        return {name: stage.row() for name, stage in self.stages.items()}

    def close(self) -> None:
        """Stop the delay line when it is the device's own (a radio's is stopped by the radio)."""
        if self._own_line:
            self.delay_line.close()


__all__ = ["EMULATED_LINKS", "LINK_COUNTERS", "DeviceLinks", "LinkStage", "emulated_links"]
