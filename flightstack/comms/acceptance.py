"""Bounded acceptance of received predictions: what a neighbour's message may claim.

Decoding (messages.py) proves a message is well formed. These bounds say whether it is *physically and
logically possible*; a message outside them is dropped and counted by reason (freshness.py), never
raised, and never changes what the receiver kept of that sender. They hold for authenticated senders
too: mutual TLS says who sent a message, not that its content is sane.

Values (frames as in messages.py; μ is the target's body velocity, ḡ_w the sender's estimate of the
target's pose in Σw):
    var, prior_var       every element in [var_floor, var_ceiling]: a variance of 5e-324 once
                         overflowed the product-of-experts precision (1/var = inf) and made the fused μ NaN
    μ                    |v_x|, |v_y|, |v_z| ≤ max_speed_mps (m/s), |ω| ≤ max_yaw_rate_rps (rad/s)
    ḡ_w                  |x|, |y|, |z| ≤ max_position_m (m), |θ| ≤ max_angle_rad (rad)
Sequence numbers. A sender counts from 0 or 1, so the first message of a sender (or after it left)
must have seq < max_seq_jump, as if its predecessor were seq −1 (otherwise a forged seq 2³²−1
arriving before the real sender's first message takes its slot for `restart_after` ticks and changes a
flight). Afterwards seq must be in (prev, prev + max_seq_jump]: older ones are "old or duplicate seq",
larger jumps "seq jump". Two rules take a lower or a far seq, and only these:

    the gap     a never-seen seq inside the gap that the newest message's stream skipped (the newest
                came as prev + k, k > 1, and this seq is between prev and it) is the stream from before
                the skip going on: it is taken at once, the skip is in doubt. One message d ahead of the
                real sender (a holder of its key; any d ≤ max_seq_jump) is therefore the newest only until
                the real sender's next message; the forged seq stays remembered, and when the real stream
                reaches it with other bytes that is evidence of two streams (streams.py). A network that
                delivers a message after its successor costs one reading of the older message. Likewise
                a second payload under the newest seq replaces it (evidence at once): the real message
                a copy one ahead pre-empted, or a copy of the real one; either is the newest once. And a
                message that resumes the count a restart left (above it, while the count the restart
                took is still below it) is taken at once: that count never stopped (evidence: streams.py).
    restart     `restart_after` consecutive rejected messages whose own seqs increase by at most
                max_seq_jump each, with nothing accepted in between (the stream that held the id stopped),
                are a restarted sender (or a receiver joining a live one), and the newest of them is
                accepted (`restarts` counts it; an event names the sender: freshness.py). A forger
                repeating one seq never makes such a run; a second stream interleaving with the real one
                never does either, because every accepted message of the real one ends the run.

What the refused old seqs say about a second stream under one identity (`max_reorder`, a window of
max_seq_jump seqs, `quarantine_after` pieces of evidence): streams.py.
Stamps: see freshness.py (time base "stamps": a stamp ahead of the receiver's mission clock is not
used; "receiver": outliers cannot become the learned offset, and a stamp must be within bounds of it).

Residual risk, plainly. On a plaintext bus anybody who can reach it can still send *plausible* lies
(a velocity within bounds, a fresh stamp, the next seq): the bounds limit the damage, they do not
authenticate. Somebody who keeps injecting a consistent forged sequence for a sender can alternate
restarts with the real sender: each restart is reported by name (freshness.py), and mutual TLS with
the access control (acl.py) is what stops it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatSeq = Sequence[float] | NDArray[np.float64]  # four floats: a message field as a list or an array


@dataclass(frozen=True)
class AcceptanceBounds:
    """Bounds on a received prediction (units in the names; module docstring)."""

    var_floor: float = 1e-12  # the GP's latent variance is ≥ ~1e-8 here; 1/1e-12 is far from overflow
    var_ceiling: float = 1e12
    max_speed_mps: float = 10.0  # per component of the target's body velocity (the Scamper: ≤ 1 m/s)
    max_yaw_rate_rps: float = 10.0
    max_position_m: float = 1000.0
    max_angle_rad: float = 1000.0  # θ is not wrapped by the observer; only absurd values are refused
    max_seq_jump: int = 1000  # ≥ the messages a live sender can skip (50 s at 20 Hz)
    restart_after: int = 3  # consecutive consistent rejects that mean the sender restarted
    max_reorder: int = 16  # a never-seen seq this far behind the newest is late, further a 2nd stream
    quarantine_after: int = 2  # pieces of evidence of a second stream that quarantine an id (streams.py)
    stamp_ahead_s: float = 0.5  # time base "stamps": a stamp this far past the mission clock is not used

    def __post_init__(self) -> None:
        if not 0 < self.var_floor < self.var_ceiling < math.inf:
            raise ValueError("need 0 < var_floor < var_ceiling < inf")
        for name in ("max_speed_mps", "max_yaw_rate_rps", "max_position_m", "max_angle_rad", "stamp_ahead_s"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be positive and finite")
        if self.max_seq_jump < 1 or self.restart_after < 1 or self.quarantine_after < 1:
            raise ValueError("max_seq_jump, restart_after and quarantine_after must be >= 1")
        if not 1 <= self.max_reorder <= self.max_seq_jump:
            raise ValueError("max_reorder must be in [1, max_seq_jump]")

    @functools.cached_property
    def packed(self) -> NDArray[np.float64]:
        """[var_floor, var_ceiling, max_speed_mps, max_yaw_rate_rps, max_position_m, max_angle_rad]: the
        value bounds as the compiled check takes them (kernels.message_check); computed once (the bounds
        are frozen; the array is the callers' to read, not to change)."""
        return np.array(
            [
                self.var_floor,
                self.var_ceiling,
                self.max_speed_mps,
                self.max_yaw_rate_rps,
                self.max_position_m,
                self.max_angle_rad,
            ],
            dtype=np.float64,
        )

    def violation(self, g: FloatSeq, mu: FloatSeq, var: FloatSeq, prior_var: FloatSeq) -> str | None:
        """The reason these (finite, 4-element) fields are out of bounds, or None. The receive path
        checks the same in compiled form (kernels.message_check, with the decoder's checks)."""
        lo, hi = self.var_floor, self.var_ceiling
        if not all(lo <= v <= hi for v in (*var, *prior_var)):
            return "variance out of bounds"
        if max(abs(mu[0]), abs(mu[1]), abs(mu[2])) > self.max_speed_mps or abs(mu[3]) > self.max_yaw_rate_rps:
            return "mu out of bounds"
        if max(abs(g[0]), abs(g[1]), abs(g[2])) > self.max_position_m or abs(g[3]) > self.max_angle_rad:
            return "pose out of bounds"
        return None


@dataclass
class SeqState:
    """What a sender's seqs say beside its newest one: the run of rejected seqs (the restart rule) and the
    gap its newest skip left (the gap rule)."""

    last: int = -1  # seq of the newest rejected message of the run
    count: int = 0  # its length
    gap: tuple[int, int] | None = None  # (lo, hi): the newest stream came from lo to hi, skipping between

    def taken(self, prev: int | None, seq: int, by_rule: bool) -> None:
        """`seq` was accepted after `prev` (None: the sender's first); by_rule: by the gap or restart rule,
        which leave no gap. A skip forward leaves (prev, seq); the next seq after it keeps the gap."""
        self.count, self.last = 0, -1
        if by_rule or prev is None:
            self.gap = None
        elif seq > prev + 1:
            self.gap = (prev, seq)


def seq_verdict(prev: int | None, seq: int, bounds: AcceptanceBounds) -> str | None:
    """Why `seq` does not follow `prev` ("old or duplicate seq" | "seq jump"), or None; prev None (the
    sender's first message) counts as −1: a sender counts from 0 or 1, its first seq is < max_seq_jump."""
    if prev is None:
        prev = -1
    if seq <= prev:
        return "old or duplicate seq"
    if seq > prev + bounds.max_seq_jump:
        return "seq jump"
    return None


def in_gap(state: SeqState, seq: int, newest: int, bounds: AcceptanceBounds) -> bool:
    """True when `seq` lies in the gap of the newest skip (the gap rule), at most max_seq_jump behind the
    `newest` accepted seq."""
    gap = state.gap
    return gap is not None and gap[0] < seq < gap[1] and newest - seq <= bounds.max_seq_jump


def restart_run(run: SeqState, seq: int, bounds: AcceptanceBounds) -> bool:
    """Extend the rejected run with `seq`; True when it is long enough to be a restarted sender."""
    if run.count and run.last < seq <= run.last + bounds.max_seq_jump:
        run.count += 1
    else:
        run.count = 1
    run.last = seq
    return run.count >= bounds.restart_after


__all__ = ["AcceptanceBounds", "SeqState", "in_gap", "restart_run", "seq_verdict"]
