"""One sender, one stream: two processes under one identity and one label, told apart by what a copy
cannot avoid.

The session label (identity.py) tells two sessions apart only while they are honest: anybody who hears
a sender's messages can put its label on their own. What a second process speaking for sender i cannot
avoid is the real sender's own stream: it keeps numbering its messages 1, 2, 3, … once each
(messages.py: seq), whatever the copy does. A network may deliver a message twice (identical bytes) or
late (behind a few of its successors); it never changes one. So, per sender, over a window of the newest
`window` seqs (seq → digest of the message bytes), a message below the newest is

    a duplicate    its seq was seen with the same bytes: no evidence (a repeat older than the window
                   cannot be told from another stream's; a network repeats within milliseconds);
    late           its seq was never seen and is at most `max_reorder` behind the newest: reordering,
                   remembered (a second different payload under it later is a conflict);
    evidence       its seq was seen with *other* bytes ("two payloads under seq N"), or it was never seen
                   and is more than `max_reorder` behind the newest ("seq N arrived M behind the newest"):
                   a stream that the accepted one has overtaken.

A message accepted under a seq seen with other bytes is evidence too: the gap rule of acceptance.py gave
the id back to the stream from before a skip, and that stream has now reached the skipping message's seq
("two payloads under seq N"). So is a message that resumes the count a restart left, while the count
the restart took is still below it ("seq N resumes the count that stopped at M before a restart"): the
restart was a second stream's, and acceptance.py gives the id back to that count.

Interleaving is evidence; a restart is not. The evidence of a refused message is *pending* until the
sender's next accepted message: a plain one (the stream the message fell behind goes on: the two
interleave) confirms it, one taken by the restart rule (the stream that held the id stopped, and these
were the new count's first messages) discards it. Evidence under an accepted seq, and a resumed count,
are confirmed at once. So a sender counting from 0 again, a receiver joining late, duplicates and
reordering within `max_reorder` make no evidence; a copy of any lead makes one piece per message the
real stream sends into it, at the latest when the real stream reaches the copy's seq.

`quarantine_after` confirmed pieces, however far apart, establish two streams: the sender is put in
`found` with the newest evidence. What follows is the caller's: the bus quarantines the id (identity.py);
this module only watches.

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
    pending: list[str] = field(default_factory=list)  # evidence of refused messages since the last accepted
    left: int | None = None  # the newest seq before a restart took the id below it, until passed


class StreamWatch:
    """Per sender, the window of seen seqs and the evidence of a second stream; see the module docstring.
    window: seqs remembered behind the newest (≥ max_reorder); max_reorder: how far behind the newest a
    never-seen seq may arrive and still be a late message; quarantine_after: confirmed pieces of evidence
    that establish two streams."""

    def __init__(self, window: int, max_reorder: int, quarantine_after: int = 2) -> None:
        if not 0 < max_reorder <= window:
            raise ValueError("need 0 < max_reorder <= window")
        if quarantine_after < 1:
            raise ValueError("need quarantine_after >= 1")
        self.window = window
        self.max_reorder = max_reorder
        self.quarantine_after = quarantine_after
        self._streams: dict[int, _Stream] = {}
        self.found: dict[int, str] = {}  # sender → why it has two streams (set once)
        self.evidence: dict[int, int] = {}  # sender → confirmed pieces of evidence

    def seen(self, sender: int, seq: int) -> bool:
        """True when `seq` of `sender` is in the window (accepted, or refused as late or as evidence)."""
        s = self._streams.get(sender)
        return s is not None and seq in s.seen

    def refused_old(self, sender: int, seq: int, dig: bytes, newest: int) -> str | None:
        """A message of `sender` with `seq` and digest `dig` below the newest accepted seq `newest`:
        DUPLICATE, None for a late message, else the evidence ("two payloads under seq N" | "seq N arrived M
        behind the newest"), pending until the sender's next accepted message (module docstring)."""
        s = self._streams.setdefault(sender, _Stream())
        known = s.seen.get(seq)
        if known == dig:
            return DUPLICATE  # the network repeated it
        if known is None and newest - seq <= self.max_reorder:
            s.seen[seq] = dig  # late: a second different payload under it is a conflict
            return None
        if known is None:
            s.seen[seq] = dig
            why = f"seq {seq} arrived {newest - seq} behind the newest"
        else:
            why = f"two payloads under seq {seq}"
        s.pending.append(why)
        return why

    def resumed(self, sender: int, seq: int, newest: int) -> str | None:
        """A message of `sender` above the newest accepted seq `newest`: the evidence when it resumes the
        count a restart left (`seq` above it while `newest` is still below it), confirmed at once; else
        None."""
        s = self._streams.get(sender)
        if s is None or s.left is None or not newest < s.left < seq:
            return None
        why = f"seq {seq} resumes the count that stopped at {s.left} before a restart"
        self._confirm(sender, [why])
        return why

    def accepted(
        self, sender: int, seq: int, dig: bytes, restart: bool = False, left: int | None = None
    ) -> None:
        """A message of `sender` with `seq` and digest `dig` was accepted. restart: by the restart rule (the
        pending evidence is discarded); left: the newest seq before it when the restart went below it (the
        seqs above are forgotten, and a message resuming that count later is evidence)."""
        s = self._streams.setdefault(sender, _Stream())
        evidence = [] if restart else s.pending
        s.pending = []
        known, conflict = s.seen.get(seq), f"two payloads under seq {seq}"
        if known is not None and known != dig and not restart and conflict not in evidence:
            evidence.append(conflict)
        if left is not None:
            s.seen = {q: d for q, d in s.seen.items() if q < seq}  # the seqs above were the previous count's
            s.left = left
        elif s.left is not None and seq >= s.left:
            s.left = None  # the new count passed where the old one stopped
        s.seen[seq] = dig
        if len(s.seen) > 2 * self.window:  # amortised: drop what fell out of the window
            s.seen = {q: d for q, d in s.seen.items() if q > seq - self.window}
        if evidence:
            self._confirm(sender, evidence)

    def _confirm(self, sender: int, evidence: list[str]) -> None:
        n = self.evidence.get(sender, 0) + len(evidence)
        self.evidence[sender] = n
        if n >= self.quarantine_after and sender not in self.found:
            self.found[sender] = f"{evidence[-1]} ({n} pieces of evidence: two streams interleave)"

    def forget(self, sender: int) -> None:
        """The sender left the bus: its window starts again (what was `found` stays found)."""
        self._streams.pop(sender, None)


__all__ = ["DUPLICATE", "StreamWatch", "digest"]
