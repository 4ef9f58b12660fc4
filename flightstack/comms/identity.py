"""One identity, one session: which Zenoh session may speak for a participant's id.

Two processes can publish as the same drone: a second copy of `flightstack agent --id 1` started by
mistake, or a peer holding agent-1's own certificate. The key (pred/1, world/cmd/1) and the certificate
are the same for both, so neither the ACL nor the liveliness token (tokens of one key aggregate: the
token stays while either session holds it) tells them apart. What does: every process puts its *session
label* on each prediction and world command it publishes, as the Zenoh attachment

    "<zid> pid <pid> on <host>"       (ASCII, at most MAX_LABEL_CHARS; zid: the Zenoh session id, hex)

and every receiver keeps, per id, the session of the first message it accepted for it (`SessionBook`):
the one the run started with. Messages of any other session for that id are dropped and counted
("second session"), and each such session is reported once by name (`SessionEvent`: "agent-1: a second
session (…) publishes as drone 1"). A message without a label counts as the session "unlabelled".

Nothing at the network layer can tell which of two holders of one certificate is genuine: the first
wins. On a plaintext bus the label is as forgeable as everything else (anybody can claim a zid); it is
there to keep a misconfigured or duplicated process from stalling or steering a run, not to
authenticate (mutual TLS and the ACL do that, acl.py).

A copied label. Anybody who hears a sender's messages can put its label on their own (on plaintext,
or holding the sender's own certificate), and then passes this rule. What such a copy cannot avoid is
the real sender's stream, which goes on beside it: two different payloads under one seq, or the real
messages refused far behind the copy's (streams.py, watched on the receive path). Once two streams are
established under one label, nothing says which is genuine: the id is *quarantined* for the rest of the
run (`quarantine`): every later message for it is dropped and counted ("two sessions under one label"),
the bus forgets its newest message, so fusion leaves it out and the flight goes on; it is reported once
by name ("agent-1: two sessions publish under one label …", kind "second session").

When the first session goes away. Its id leaving the bus (`forget`: every session of it is gone)
clears the owner; the next session to publish claims the id, and its messages pass the sequence and
restart rules (acceptance.py). While a second session still holds the liveliness token, the first one's
departure is not seen by liveliness: its messages simply stop. The id is *not* handed to the second
session (nothing says it is the genuine one): receivers of predictions see the id go stale and leave
it out of fusion; the served world, which waits for each drone's command, treats a drone whose owner is
`silent_for` longer than its bound while another session speaks for it as departed, and lands it
(sim_backend/served/server.py). An id this process hosts is its own from the start (`own`).

Units: times are the receiver's clock (s, time.monotonic() in the buses). Thread safety: none here; the
callers hold their lock.
"""

from __future__ import annotations

import os
import socket
from collections import Counter
from dataclasses import dataclass
from typing import Any, Final

from flightstack.comms.certs import agent_name

MAX_LABEL_CHARS = 160
UNLABELLED = "unlabelled"
SECOND_SESSION: Final = "second session"  # the drop reason, and the event kind
TWO_STREAMS: Final = "two sessions under one label"  # the drop reason of a quarantined id


def session_label(session: Any) -> str:
    """This process's label for the Zenoh `session`: "<zid> pid <pid> on <host>" (bounded)."""
    host = "".join(c for c in socket.gethostname() if c.isascii() and c.isprintable() and c != " ")[:64]
    return f"{session.zid()} pid {os.getpid()} on {host or '?'}"[:MAX_LABEL_CHARS]


def parse_label(attachment: bytes | None) -> str:
    """The session label carried by a sample's attachment; UNLABELLED when there is none or it is not a
    printable ASCII text of at most MAX_LABEL_CHARS characters."""
    if attachment is None or not 0 < len(attachment) <= MAX_LABEL_CHARS:
        return UNLABELLED
    try:
        text = attachment.decode("ascii")
    except UnicodeDecodeError:
        return UNLABELLED
    return text if text.isprintable() else UNLABELLED


def sample_label(sample: Any) -> str:
    """parse_label of a zenoh.Sample's attachment; never raises."""
    try:
        att = sample.attachment
        return parse_label(None if att is None else bytes(att.to_bytes()))
    except Exception:
        return UNLABELLED


@dataclass(frozen=True)
class SessionEvent:
    """Another session (`session`) speaks for `sender`, owned by `owner`; its messages are dropped.
    kind: SECOND_SESSION; t: on the receiver's clock (s); text: the report, naming the participant."""

    t: float
    sender: int
    kind: str
    session: str
    owner: str
    text: str


@dataclass
class _Claim:
    owner: str
    heard: float  # the owner's newest message (receiver clock, s)
    others: set[str]  # every other session seen for the id


class SessionBook:
    """Per id, the session that owns it; see the module docstring. what: the verb of the reports
    ("publishes as", "sends commands as"); they name the id's participant (certs.agent_name)."""

    def __init__(self, what: str = "publishes as") -> None:
        self.what = what
        self.claims: dict[int, _Claim] = {}
        self.dropped: Counter[int] = Counter()  # per id: messages of a second session dropped
        self.events: list[SessionEvent] = []
        self.quarantined: set[int] = set()  # ids two streams spoke for under one label (for the run)

    def own(self, sender: int, session: str, t: float) -> None:
        """Claim `sender` for `session` at t (s): a process's own ids, before anybody else is heard."""
        self.claims[sender] = _Claim(session, t, set())

    def admit(self, sender: int, session: str, t: float) -> bool:
        """True when a message of `session` for `sender` received at t (s) may go on to the receive
        checks: nobody owns the id yet, or `session` does. False: a second session's, counted in
        `dropped` and reported once per session (`events`), or any message for a quarantined id."""
        if sender in self.quarantined:
            self.dropped[sender] += 1
            return False
        c = self.claims.get(sender)
        if c is None:
            return True
        if session == c.owner:
            c.heard = max(c.heard, t)
            return True
        if session not in c.others:
            c.others.add(session)
            text = (
                f"{agent_name(sender)}: a second session ({session}) {self.what} drone {sender}; "
                f"dropped, the first session ({c.owner}) keeps it"
            )
            self.events.append(SessionEvent(t, sender, SECOND_SESSION, session, c.owner, text))
        self.dropped[sender] += 1
        return False

    def quarantine(self, sender: int, session: str, t: float, why: str) -> None:
        """Two streams under `session`'s label speak for `sender` (streams.py; why: the evidence): drop
        every later message for it (`admit` refuses them) for the rest of the run; reported once."""
        if sender in self.quarantined:
            return
        self.quarantined.add(sender)
        text = (
            f"{agent_name(sender)}: two sessions publish under one label ({session}) as drone {sender}: "
            f"{why}; both dropped for the rest of the run"
        )
        self.events.append(SessionEvent(t, sender, SECOND_SESSION, session, session, text))

    def claim(self, sender: int, session: str, t: float) -> None:
        """After a message of `session` passed every receive check: it owns `sender` if nobody does (a
        message refused by those checks never claims an id)."""
        if sender not in self.claims:
            self.claims[sender] = _Claim(session, t, set())

    def forget(self, sender: int) -> None:
        """Every session of `sender` left the bus: the next one to publish claims it."""
        self.claims.pop(sender, None)

    def owner(self, sender: int) -> str | None:
        c = self.claims.get(sender)
        return None if c is None else c.owner

    def contested(self, sender: int) -> bool:
        """True when a second session has spoken for `sender`."""
        c = self.claims.get(sender)
        return c is not None and bool(c.others)

    def silent_for(self, sender: int, t: float) -> float:
        """Seconds since the owner of `sender` was last heard (inf: no owner)."""
        c = self.claims.get(sender)
        return float("inf") if c is None else t - c.heard


__all__ = [
    "MAX_LABEL_CHARS",
    "SECOND_SESSION",
    "TWO_STREAMS",
    "UNLABELLED",
    "SessionBook",
    "SessionEvent",
    "parse_label",
    "sample_label",
    "session_label",
]
