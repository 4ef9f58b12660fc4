"""Which request a Tello reply answers: replies carry no identifier, so the driver keeps a ledger of the
requests still owed one.

Every datagram sent except `rc` is a request the drone may answer (`CommandChannel.send` records it), owed
a reply while one can still come: `SLOW_REPLY_S` (s) for `takeoff` and `land`, which a Tello answers when
done (a real one after 6.3–8.7 s and 3.7–4.2 s), `PROMPT_REPLY_S` (s) for the others. A resend of the same
command joins its owed entry (either answer is the answer). Each reply received is given to one request:
the oldest owed one, other than the command waiting for it, that it could answer (an `ok` or `error …` may
answer any request, a real Tello was seen answering `battery?` with `ok`; a value answers only a query,
`…?`); failing that, to the waiting command when the reply is an answer it accepts; else to none. So
the reply to a keep-alive, or a late reply to an earlier request still owed one, never completes a
command. A reply that answers no request the ledger knows of (a duplicate, a reply
crossed by the drone) is not told from the answer when it fits (docs/drivers.md, "Replies").
"""

from __future__ import annotations

import threading
from typing import Literal, NamedTuple

RC_REPLIES = ("error not joystick",)  # firmware answers to rc, never another command's answer
SLOW_VERBS = ("takeoff", "land")
SLOW_REPLY_S = 10.0
"""How long (s) `takeoff` and `land` are owed a reply: the recorded takeoff's `ok` came 8.7 s after it."""
PROMPT_REPLY_S = 1.0
"""How long (s) any other request is owed a reply: answers come within tens of ms; a `streamon` was seen
answered 0.3 s late (behind a stray `70`)."""

ReplyKind = Literal["ok", "error", "value"]


def reply_kind(reply: str) -> ReplyKind:
    """`ok`; `error` for a refusal (`error …`, `unknown command: …`, `out of range`); `value` for the rest."""
    r = reply.strip().lower()
    if r == "ok":
        return "ok"
    return "error" if r.startswith(("error", "unknown", "out of")) else "value"


def is_command_answer(reply: str) -> bool:
    """An answer a command other than a query gets: `ok` or a refusal (never a value)."""
    return reply_kind(reply) != "value"


def is_query(command: str) -> bool:
    return command.strip().endswith("?")


def expected(reply: str, command: str) -> bool:
    """`reply` is the kind `command` normally gets: a value for a query, `ok`/refusal for the others."""
    return (reply_kind(reply) == "value") == is_query(command)


class Request(NamedTuple):
    """A request owed a reply: first sent at `t`, owed until `until` (time.monotonic() s)."""

    t: float
    command: str
    until: float


class ReplyLedger:
    """The requests of one drone still owed a reply (thread-safe: the sender, the reader, the exchange)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._owed: list[Request] = []

    def sent(self, t: float, command: str) -> None:
        """`command` was sent at `t` (s): owed a reply from now; `rc` is none."""
        if command.startswith("rc "):
            return
        late = SLOW_REPLY_S if command.split(" ")[0] in SLOW_VERBS else PROMPT_REPLY_S
        with self._lock:
            self._owed = [r for r in self._owed if r.until >= t]
            same = next((r for r in self._owed if r.command == command), None)
            if same is None:
                self._owed.append(Request(t, command, t + late))
            else:
                self._owed[self._owed.index(same)] = same._replace(until=t + late)

    def place(
        self, t: float, reply: str, waiting: str | None = None, accepted: bool = False
    ) -> Request | None:
        """The request `reply` (received at `t`, s) answers, no longer owed: the oldest owed request sent
        before `t`, other than `waiting` (the command waiting for a reply), that it could answer; else
        `waiting`'s when `accepted` (it takes this reply); else None (module docstring)."""
        if reply.strip().lower() in RC_REPLIES:
            return None
        could = is_query if reply_kind(reply) == "value" else (lambda _c: True)
        with self._lock:
            self._owed = [r for r in self._owed if r.until >= t or r.command == waiting]
            others = (r for r in self._owed if r.command != waiting and r.t < t and could(r.command))
            other = next(others, None)
            if other is not None:
                self._owed.remove(other)
                return other
            if waiting is None or not accepted:
                return None
            own = next((r for r in self._owed if r.command == waiting), Request(t, waiting, t))
            if own in self._owed:
                self._owed.remove(own)
            return own
