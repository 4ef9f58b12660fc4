"""A seeded model of an impaired network link (user space, like Linux netem), and the named profiles.

`LinkModel.decide(t, size)` says what becomes of one packet entering one direction of one link at time t
(s, any monotonic clock) with `size` bytes: the times at which it is delivered (none: lost; two:
duplicated). In order of application:

1. blackout: a packet that enters during one of the link's blackout windows is lost ("blackout");
2. rate cap: the packet waits for the link to serialise the ones before it (`rate_bps`); when that wait
   would exceed `queue_s` it is dropped ("queue", a tail drop of the bottleneck's buffer);
3. loss: the Gilbert–Elliott chain (per step: good → bad with probability p, bad → good with r; lost
   with probability `loss_good` in the good state, `loss_bad` in the bad one; netem's `gemodel p r 1-h
   1-k`) ("loss"). A step is one packet (netem), or with `loss_step_s` a slice of time: the chain then
   moves by the time between a link's packets, so that a burst lasts as long on a sparse link (commands)
   as on a dense one (video);
4. delay: `latency_s` + an exponential jitter of mean `jitter_s` + with probability `spike_p` a spike
   uniform in `spike_s`; packets leave in order (a packet is never delivered before one that entered
   earlier, as 802.11 delivers), so one spike holds back the packets behind it, as a retried frame does;
5. reordering: with probability `reorder` a packet is held `reorder_s` longer outside that order (the
   packets behind it overtake it);
6. duplication: with probability `duplicate` a second copy follows 1 ms later.

Every packet draws the same number of random numbers from its link's own generator
(`link_rng(seed, device, link)`), so the n-th packet of a link meets the same decisions for the same seed
and the same packet times, whatever the other links did (and whatever the times, for a chain stepped per
packet). Blackout windows are drawn per device (both directions of
all its radio links share them, as an out-of-range drone loses everything): `blackout_windows`.

Pure: no I/O, no threads, no clock (times are arguments). The emulated lab applies it at its emulators'
sockets (flightstack.sim_backend.emulators.radio); docs/links.md gives the numbers of the profiles and
their sources, and the equivalent `tc netem` commands.
"""

from __future__ import annotations

import bisect
import dataclasses
import hashlib
import math
import random
from collections import Counter
from dataclasses import dataclass, field

LINKS = ("video", "state", "rc", "mocap", "robot", "bus")
"""The links of a lab, each one direction of one kind of data, in both models (the `links:` table's samples
and the radio's packets): a drone's `video` (camera -> computer), `state` (telemetry -> computer) and `rc`
(commands -> drone, and the drone's replies), `mocap` (motion capture -> computer, wired), `robot` (the
ground robot's MAVLink, both ways) and the `bus` between agent processes (TCP)."""
DUPLICATE_GAP_S = 0.001
"""A duplicate follows its original by this much (s)."""


MAX_DELAY_S = 10.0
"""Largest latency, mean jitter, spike, reordering hold, rate-cap queue and loss step a link may have (s):
a bufferbloated or satellite link is late by seconds, none by more (docs/links.md, "Bounds")."""
MIN_RATE_BPS = 1e3
"""Slowest rate cap (bit/s): below 1 kbit/s a 64 KiB chunk would take minutes."""
MAX_RATE_BPS = 1e11
"""Fastest rate cap (bit/s, 100 Gbit/s)."""
MIN_BLACKOUT_S = 0.01
"""Shortest blackout (s): shorter is loss, which the Gilbert–Elliott chain models."""
MIN_BLACKOUT_PERIOD_S = 0.1
"""Shortest period between blackouts' starts (s): at most 36,000 windows in blackout_windows' hour."""
MAX_BLACKOUT_PERIOD_S = 86400.0
"""Latest first blackout and longest period (s, a day)."""


def _check_range(field_name: str, value: object, lo: float, hi: float, unit: str) -> None:
    """ValueError naming `field_name` unless `value` is a finite real number in [lo, hi] (`unit`: "s",
    "bit/s", or "probability")."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not (number and isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
        what = "a probability" if unit == "probability" else "a finite number"
        unit = f" {unit}" if unit and unit != "probability" else ""
        raise ValueError(f"{field_name} must be {what} in [{lo:g}, {hi:g}]{unit}, got {value!r}")


@dataclass(frozen=True)
class LinkProfile:
    """One direction of one link. Times in s, rates in bit/s, probabilities in [0, 1] per packet."""

    latency_s: float = 0.0
    jitter_s: float = 0.0
    """Mean of the exponential extra delay (its standard deviation too)."""
    spike_p: float = 0.0
    spike_s: tuple[float, float] = (0.1, 0.3)
    loss_p: float = 0.0
    """Gilbert–Elliott: probability good → bad per packet."""
    loss_r: float = 1.0
    """Gilbert–Elliott: probability bad → good per packet (mean burst 1/r packets when loss_bad = 1)."""
    loss_bad: float = 1.0
    """Loss probability in the bad state (netem's 1-h)."""
    loss_good: float = 0.0
    """Loss probability in the good state (netem's 1-k)."""
    loss_step_s: float = 0.0
    """0: the chain takes one step per packet (netem's gemodel). > 0: one step per loss_step_s of time
    between a link's packets (fractional steps: the n-step transition of the chain), so a burst lasts
    about as long on a sparse link (a command a second) as on a dense one (video), as a burst of Wi-Fi
    interference does; p, r and the burst length are then per step."""
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_s: float = 0.03
    rate_bps: float | None = None
    queue_s: float = 0.2
    """Longest wait behind the rate cap before a packet is dropped (s)."""

    def __post_init__(self) -> None:
        for name in ("spike_p", "loss_p", "loss_r", "loss_bad", "loss_good", "duplicate", "reorder"):
            _check_range(f"LinkProfile.{name}", getattr(self, name), 0.0, 1.0, "probability")
        for name in ("latency_s", "jitter_s", "reorder_s", "queue_s", "loss_step_s"):
            _check_range(f"LinkProfile.{name}", getattr(self, name), 0.0, MAX_DELAY_S, "s")
        if not (isinstance(self.spike_s, tuple) and len(self.spike_s) == 2):
            raise ValueError(f"LinkProfile.spike_s must be (low, high) in s, got {self.spike_s!r}")
        lo, hi = self.spike_s
        _check_range("LinkProfile.spike_s", lo, 0.0, MAX_DELAY_S, "s")
        _check_range("LinkProfile.spike_s", hi, lo, MAX_DELAY_S, "s")
        if self.rate_bps is not None:
            _check_range("LinkProfile.rate_bps", self.rate_bps, MIN_RATE_BPS, MAX_RATE_BPS, "bit/s")
        if self.loss_p > 0 and self.loss_r == 0:
            raise ValueError("LinkProfile.loss_r = 0 with loss_p > 0 would stay in the bad state forever")
        if self.loss_step_s > 0 and self.loss_p + self.loss_r > 1:
            raise ValueError("LinkProfile.loss_p + loss_r must be <= 1 for a time-stepped chain")

    def transition(self, bad: bool, steps: float) -> float:
        """Probability of the bad state `steps` steps (≥ 0, fractional allowed) after `bad`: with
        π = p/(p + r) and λ = 1 − p − r, π + (1 − π)·λⁿ from bad and π·(1 − λⁿ) from good."""
        p, r = self.loss_p, self.loss_r
        if p == 0.0:
            return 0.0 if not bad else (1.0 - r) ** steps
        pi, lam = p / (p + r), 1.0 - p - r
        decay = lam**steps if lam > 0 else (1.0 if steps == 0 else (lam if steps == 1 else 0.0))
        return pi + (1.0 - pi) * decay if bad else pi * (1.0 - decay)

    @classmethod
    def bursty(cls, loss: float, burst: float, **kw: object) -> LinkProfile:
        """A profile losing `loss` of the packets (stationary) in bursts of `burst` steps on average
        (the simple Gilbert model: loss_bad = 1, loss_good = 0): r = 1/burst, p = loss·r/(1 − loss);
        a step is a packet, or loss_step_s of time when given."""
        if not (0.0 <= loss < 1.0) or burst < 1.0:
            raise ValueError(f"need 0 <= loss < 1 and burst >= 1, got {loss}, {burst}")
        r = 1.0 / burst
        return cls(loss_p=loss * r / (1.0 - loss), loss_r=r, **kw)  # type: ignore[arg-type]

    @property
    def clean(self) -> bool:
        """True when the link changes nothing."""
        return self == LinkProfile()

    def stationary_loss(self) -> float:
        """Long-run fraction of packets lost by the Gilbert–Elliott chain (blackouts and queue drops
        aside): π_bad·loss_bad + π_good·loss_good with π_bad = p/(p + r)."""
        if self.loss_p == 0.0:
            return self.loss_good
        pi_bad = self.loss_p / (self.loss_p + self.loss_r)
        return pi_bad * self.loss_bad + (1.0 - pi_bad) * self.loss_good

    def mean_burst(self) -> float:
        """Mean length (packets) of a run of consecutive losses in the simple Gilbert model (loss_bad = 1,
        loss_good = 0): 1/r."""
        return 1.0 / self.loss_r

    def netem(self) -> str:
        """The equivalent `tc qdisc ... netem` options (blackouts and spikes have no netem option)."""
        out = []
        if self.latency_s or self.jitter_s:
            out.append(f"delay {1e3 * (self.latency_s + self.jitter_s):g}ms {1e3 * self.jitter_s:g}ms")
            out.append("distribution pareto" if self.jitter_s else "")
        if self.loss_p or self.loss_good:
            out.append(
                f"loss gemodel {100 * self.loss_p:.3g}% {100 * self.loss_r:.3g}% "
                f"{100 * self.loss_bad:.3g}% {100 * self.loss_good:.3g}%"
            )
        if self.duplicate:
            out.append(f"duplicate {100 * self.duplicate:.3g}%")
        if self.reorder:
            out.append(f"reorder {100 * self.reorder:.3g}%")
        if self.rate_bps:
            out.append(f"rate {self.rate_bps / 1e3:g}kbit")
        return " ".join(s for s in out if s) or "(none)"


@dataclass(frozen=True)
class BlackoutPlan:
    """Blackouts of a device's radio: the first starts `first_s` after the link's epoch, then one every
    `every_s`; each lasts a duration uniform in [min_s, max_s] (s), drawn from the device's seed."""

    first_s: float
    every_s: float
    min_s: float
    max_s: float

    def __post_init__(self) -> None:
        _check_range("BlackoutPlan.first_s", self.first_s, 0.0, MAX_BLACKOUT_PERIOD_S, "s")
        _check_range("BlackoutPlan.every_s", self.every_s, MIN_BLACKOUT_PERIOD_S, MAX_BLACKOUT_PERIOD_S, "s")
        _check_range("BlackoutPlan.min_s", self.min_s, MIN_BLACKOUT_S, self.every_s, "s")
        _check_range("BlackoutPlan.max_s", self.max_s, self.min_s, self.every_s, "s")
        if self.max_s >= self.every_s:
            raise ValueError(f"BlackoutPlan.max_s must be < every_s ({self.every_s:g} s), got {self.max_s:g}")


@dataclass(frozen=True)
class NetworkProfile:
    """A named set of link profiles (one per link of LINKS; missing links are clean) and the blackouts of
    the devices' radios (on the links of `blackout_kinds`)."""

    name: str
    description: str
    links: dict[str, LinkProfile] = field(default_factory=dict)
    blackouts: BlackoutPlan | None = None
    blackout_kinds: frozenset[str] = frozenset({"rc", "state", "video", "robot"})

    def link(self, kind: str) -> LinkProfile:
        """The profile of the links of `kind` (KeyError for a kind not in LINKS)."""
        if kind not in LINKS:
            raise KeyError(f"unknown link {kind!r}; known: {', '.join(LINKS)}")
        return self.links.get(kind, LinkProfile())

    @property
    def clean(self) -> bool:
        """True when nothing is impaired."""
        return self.blackouts is None and all(p.clean for p in self.links.values())


_WIFI = LinkProfile.bursty(0.02, 2.0, loss_step_s=0.01, latency_s=0.003, jitter_s=0.010, duplicate=0.001)
_WIRED = LinkProfile(latency_s=0.0005, jitter_s=0.0002)
_CROWDED = LinkProfile.bursty(
    0.05,
    5.0,
    loss_step_s=0.01,
    latency_s=0.005,
    jitter_s=0.020,
    spike_p=0.01,
    spike_s=(0.1, 0.3),
    duplicate=0.005,
    reorder=0.02,
    reorder_s=0.03,
)


def _radio(wifi: LinkProfile, video: LinkProfile) -> dict[str, LinkProfile]:
    """The links of a profile whose drones and robot share one Wi-Fi (`wifi`, the video `video`), with
    the motion capture and the bus on the wired network."""
    return {"rc": wifi, "state": wifi, "video": video, "robot": wifi, "mocap": _WIRED, "bus": _WIRED}


PROFILES: dict[str, NetworkProfile] = {
    "clean": NetworkProfile("clean", "no impairment (loopback as it is)"),
    "lab-wifi": NetworkProfile(
        "lab-wifi",
        "a quiet lab Wi-Fi: 2 % loss in bursts of 2, 3 ms + 10 ms mean jitter; wired motion capture",
        _radio(_WIFI, _WIFI),
    ),
    "crowded": NetworkProfile(
        "crowded",
        "a crowded 2.4 GHz band: 5 % loss in bursts of 5, 20 ms mean jitter, 1 % spikes of 100-300 ms, "
        "2 % reordered, video capped at 2.5 Mbit/s",
        {
            **_radio(_CROWDED, dataclasses.replace(_CROWDED, rate_bps=2.5e6)),
            "bus": LinkProfile(latency_s=0.002, jitter_s=0.005),
        },
    ),
    "outage": NetworkProfile(
        "outage",
        "lab-wifi plus radio blackouts of 1-3 s both ways, from 12 s after the lab starts, every 15 s",
        _radio(_WIFI, _WIFI),
        blackouts=BlackoutPlan(first_s=12.0, every_s=15.0, min_s=1.0, max_s=3.0),
    ),
}
"""The named profiles (`--network NAME`); numbers and sources in docs/links.md."""


def profile(name: str) -> NetworkProfile:
    """The profile called `name` (ValueError naming the known ones)."""
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown network profile {name!r}; known: {', '.join(PROFILES)}") from None


def link_rng(seed: int, *names: str) -> random.Random:
    """A generator for (seed, names...), the same on every machine and Python run (SHA-256, not hash())."""
    digest = hashlib.sha256(repr((int(seed), *names)).encode()).digest()
    return random.Random(int.from_bytes(digest[:8], "little"))


def blackout_windows(
    plan: BlackoutPlan | None, seed: int, device: str, horizon_s: float = 3600.0
) -> list[tuple[float, float]]:
    """(start, end) s after the epoch of every blackout of `device`'s radio within horizon_s."""
    if plan is None:
        return []
    rng = link_rng(seed, device, "blackouts")
    out, start = [], plan.first_s
    while start < horizon_s:
        out.append((start, start + rng.uniform(plan.min_s, plan.max_s)))
        start += plan.every_s
    return out


def gilbert_elliott_step(prof: LinkProfile, bad: bool, t_prev: float | None, t: float) -> float:
    """Probability that a packet at t finds the chain bad, the previous packet (at t_prev; None: none
    yet, the chain starts good) having found it `bad`: one step per packet, or (loss_step_s > 0) one per
    loss_step_s of time in between."""
    if prof.loss_step_s <= 0.0 or t_prev is None:
        return (1.0 - prof.loss_r) if bad else prof.loss_p
    return prof.transition(bad, max(0.0, t - t_prev) / prof.loss_step_s)


class _Windows:
    """Blackout windows (start, end) s after `epoch`, merged where they overlap; `end_at(t)` finds the one
    holding t by bisection (a plan every 0.1 s has 36,000 windows in an hour)."""

    def __init__(self, windows: list[tuple[float, float]], epoch: float) -> None:
        merged: list[list[float]] = []
        for a, b in sorted((epoch + a, epoch + b) for a, b in windows if b > a):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        self.starts = [a for a, _ in merged]
        self.ends = [b for _, b in merged]

    def end_at(self, t: float) -> float | None:
        """The end of the window with start <= t < end, or None."""
        k = bisect.bisect_right(self.starts, t) - 1
        return self.ends[k] if k >= 0 and t < self.ends[k] else None


class _Draws:
    """What LinkModel and StreamModel share: the link's generator, its Gilbert–Elliott state, blackout
    windows, rate cap and in-order delivery, and the delay drawn from a packet's random numbers."""

    N_DRAWS = 8
    """Random numbers drawn per packet, whatever becomes of it (module docstring)."""

    def __init__(
        self,
        prof: LinkProfile,
        seed: int,
        device: str,
        link: str,
        *,
        epoch: float = 0.0,
        blackouts: list[tuple[float, float]] | None = None,
    ) -> None:
        """epoch: the time (same clock as `decide`'s t) the blackout windows count from."""
        self.profile = prof
        self.name = f"{device}/{link}"
        self._rng = link_rng(seed, device, link)
        self._bad = False
        self._t_prev: float | None = None
        self._blackouts = _Windows(blackouts or [], float(epoch))
        self._busy_until = -math.inf  # when the rate cap has serialised every packet so far
        self._last_due = -math.inf  # the latest in-order delivery time so far
        self.counts: Counter[str] = Counter()
        self.delay_sum_s = 0.0
        """The delivered packets' delays summed (s; kept by LinkModel, 0 on a stream)."""

    def _step(self, t: float) -> tuple[list[float], bool]:
        """The packet's random numbers, and whether it is lost to the chain (which every packet moves)."""
        p = self.profile
        u = [self._rng.random() for _ in range(self.N_DRAWS)]
        self._bad = u[0] < gilbert_elliott_step(p, self._bad, self._t_prev, t)
        self._t_prev = t
        return u, u[1] < (p.loss_bad if self._bad else p.loss_good)

    def _delay(self, u: list[float]) -> float:
        """Latency + exponential jitter (u[2]) + a spike with probability spike_p (u[3], u[4]) (s)."""
        p = self.profile
        delay = p.latency_s + (-p.jitter_s * math.log(1.0 - u[2]) if p.jitter_s > 0 else 0.0)
        if u[3] < p.spike_p:
            delay += p.spike_s[0] + u[4] * (p.spike_s[1] - p.spike_s[0])
            self.counts["spiked"] += 1
        return delay


class LinkModel(_Draws):
    """The decisions for one direction of one link (module docstring). Not thread-safe: one caller at a
    time (the emulators lock around it). `counts`: "packets", "delivered", "lost" (Gilbert–Elliott),
    "blackout", "queue", "duplicated", "reordered", "spiked"; `delay_sum_s` the sum of the delivered
    originals' delays (s)."""

    def in_blackout(self, t: float) -> bool:
        """True when t falls in one of the link's blackout windows."""
        return self._blackouts.end_at(t) is not None

    def decide(self, t: float, size: int) -> list[float]:
        """Delivery times (s) of a packet of `size` bytes entering at t: [] lost, one or two (duplicate)."""
        p = self.profile
        self.counts["packets"] += 1
        u, lost = self._step(t)
        if self.in_blackout(t):
            self.counts["blackout"] += 1
            return []
        start = t
        if p.rate_bps is not None:
            start = max(t, self._busy_until)
            if start - t > p.queue_s:
                self.counts["queue"] += 1
                return []
            self._busy_until = start + 8.0 * size / p.rate_bps
            start = self._busy_until
        if lost:
            self.counts["lost"] += 1
            return []
        due = start + self._delay(u)
        if u[5] < p.reorder:
            due += p.reorder_s  # outside the order: neither waits for nor holds back the others
            self.counts["reordered"] += 1
        else:
            due = max(due, self._last_due)
            self._last_due = due
        self.counts["delivered"] += 1
        self.delay_sum_s += due - t
        if u[6] < p.duplicate:
            self.counts["duplicated"] += 1
            return [due, due + DUPLICATE_GAP_S]
        return [due]


class StreamModel(_Draws):
    """The same profile for one direction of a TCP connection: nothing is lost (TCP retransmits), so
    every chunk of bytes is delivered, in order, at the time `decide` returns: rate cap (no drop: the
    sender waits), latency, jitter and spikes as in LinkModel; a Gilbert–Elliott loss costs
    RETRANSMIT_S more (Linux's minimum retransmission timeout); a chunk sent during a blackout is held
    until the blackout ends (then its latency). Duplication and reordering do not exist on a stream.
    Not thread-safe. `counts`: "chunks", "bytes", "retransmitted", "held" (by a blackout), "spiked"."""

    RETRANSMIT_S = 0.2
    N_DRAWS = 5

    def decide(self, t: float, size: int) -> float:
        """When a chunk of `size` bytes written at t reaches the other end (s)."""
        p = self.profile
        self.counts["chunks"] += 1
        self.counts["bytes"] += size
        u, lost = self._step(t)
        start = t
        end = self._blackouts.end_at(t)
        if end is not None:
            start = end
            self.counts["held"] += 1
        if p.rate_bps is not None:
            start = max(start, self._busy_until) + 8.0 * size / p.rate_bps
            self._busy_until = start
        delay = self._delay(u)
        if lost:
            delay += self.RETRANSMIT_S
            self.counts["retransmitted"] += 1
        self._last_due = max(start + delay, self._last_due)
        return self._last_due


__all__ = [
    "LINKS",
    "PROFILES",
    "BlackoutPlan",
    "LinkModel",
    "LinkProfile",
    "NetworkProfile",
    "StreamModel",
    "blackout_windows",
    "gilbert_elliott_step",
    "link_rng",
    "profile",
]
