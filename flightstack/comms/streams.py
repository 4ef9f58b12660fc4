"""One sender, one stream: two processes under one identity and one label, told apart by what a copy
cannot avoid.

The session label (identity.py) tells two sessions apart only while they are honest: anybody who hears
a sender's messages can put its label on their own. What a second process speaking for sender i cannot
avoid is the real sender's own stream: it keeps numbering its messages 1, 2, 3, … once each
(messages.py: seq), whatever the copy does. A network may deliver a message twice (identical bytes) or
late (behind a few of its successors); it never changes one. So, per sender, over a window of the newest
`window` seqs (seq → digest of the message bytes), a message refused as "old or duplicate seq" is

    a duplicate    its seq was seen with the same bytes: no evidence (a repeat older than the window
                   cannot be told from another stream's; a network repeats within milliseconds);
    late           its seq was never seen and is at most `max_reorder` behind the newest: reordering,
                   remembered (a second different payload under it later is a conflict);
    evidence       its seq was seen with *other* bytes ("two payloads under seq N"), or it was never seen
                   and is more than `max_reorder` behind the newest ("seq N arrived M behind the newest"):
                   a stream that the accepted one has overtaken.

A copy that keeps its seq d ahead of the real sender has every real message refused: each is late until
the real sender reaches the copy's first seq (at most `max_reorder` messages), then each is evidence;
a copy more than `max_reorder` ahead makes every real message evidence at once; a copy behind has its
own messages refused as evidence. A stream counting again from 0 under one label (the restart rule of
acceptance.py taking it back: the seqs above it are forgotten) may be the real stream behind a copy: it
clears no evidence. A duplicate never counts towards that restart rule (freshness.py).

Two streams are established when evidence arrives after an earlier piece of evidence with at least one
message accepted in between (and no more than `window` accepted since): the two streams interleave. One
late message delayed past `max_reorder`, or a sender's single restart, never does that. What follows is
the caller's: the bus quarantines the id (identity.py); this module only watches.

Units: seqs and window sizes in messages. Thread safety: none; the callers hold their lock.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Final

DUPLICATE: Final = "duplicate"  # refused_old: the network repeated a message


def digest(data: bytes) -> bytes:
    """The bytes' 16-byte BLAKE2b digest: what the window keeps per seq."""
    return hashlib.blake2b(data, digest_size=16).digest()


@dataclass
class _Stream:
    seen: dict[int, bytes] = field(default_factory=dict)  # seq → digest, seqs in (newest − window, newest]
    accepted: int = 0  # messages accepted from this sender
    mark: int | None = None  # `accepted` at the newest piece of evidence


class StreamWatch:
    """Per sender, the window of seen seqs and the evidence of a second stream; see the module docstring.
    window: seqs remembered behind the newest (≥ max_reorder); max_reorder: how far behind the newest a
    never-seen seq may arrive and still be a late message."""

    def __init__(self, window: int, max_reorder: int) -> None:
        if not 0 < max_reorder <= window:
            raise ValueError("need 0 < max_reorder <= window")
        self.window = window
        self.max_reorder = max_reorder
        self._streams: dict[int, _Stream] = {}
        self.found: dict[int, str] = {}  # sender → why it has two streams (set once)
        self.evidence: dict[int, int] = {}  # sender → pieces of evidence seen

    def refused_old(self, sender: int, seq: int, dig: bytes, newest: int) -> str | None:
        """A message of `sender` with `seq` and digest `dig`, refused as old (the newest accepted seq is
        `newest`): DUPLICATE, None for a late message, else the evidence ("two payloads under seq N" |
        "seq N arrived M behind the newest"). When it establishes two streams the sender is put in
        `found` (once)."""
        s = self._streams.setdefault(sender, _Stream())
        known = s.seen.get(seq)
        if known == dig:
            return DUPLICATE  # the network repeated it
        if known is None and newest - seq <= self.max_reorder:
            s.seen[seq] = dig  # late: a second different payload under it is a conflict
            return None
        why = (
            f"two payloads under seq {seq}"
            if known is not None
            else f"seq {seq} arrived {newest - seq} behind the newest"
        )
        self.evidence[sender] = self.evidence.get(sender, 0) + 1
        if s.mark is not None and 0 < s.accepted - s.mark <= self.window and sender not in self.found:
            n = self.evidence[sender]
            self.found[sender] = f"{why}, interleaved with accepted messages ({n} refused)"
        s.mark = s.accepted
        return why

    def accepted(self, sender: int, seq: int, dig: bytes, back: bool = False) -> None:
        """A message of `sender` with `seq` and digest `dig` was accepted; back: by the restart rule, below
        the previous newest (the seqs above it are forgotten)."""
        s = self._streams.setdefault(sender, _Stream())
        if back:  # the seqs above it were the previous count's
            s.seen = {q: d for q, d in s.seen.items() if q < seq}
        s.seen[seq] = dig
        s.accepted += 1
        if len(s.seen) > 2 * self.window:  # amortised: drop what fell out of the window
            s.seen = {q: d for q, d in s.seen.items() if q > seq - self.window}

    def forget(self, sender: int) -> None:
        """The sender left the bus: its window starts again (what was `found` stays found)."""
        self._streams.pop(sender, None)


__all__ = ["DUPLICATE", "StreamWatch", "digest"]
