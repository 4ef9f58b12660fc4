"""What the threads of every device driver share (the Tello's, the motion capture's, the Scamper's): their
errors counted and logged without flooding the log (`ErrorLog`), the pause after one (`ERROR_PAUSE_S`, so
that a persistent error cannot spin a core), and the guardian's mute check evaluated before each send
(`MutedCheck`, `evaluate_mute`)."""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable

ERROR_PAUSE_S = 0.05  # a thread pauses this long (s) after an error before it goes on
MutedCheck = Callable[[], bool]
"""True while the guardian has taken the device over: nothing may be sent."""


class ErrorLog:
    """Counts and logs the errors of driver threads without flooding the log (thread-safe).

    `record(kind, exc)` adds 1 to `counts[kind]` (and to `counts["thread_error"]` unless thread=False)
    and logs a warning naming the source, the kind, the running count and the reason at the first and
    then every `log_every`-th error of that kind. Returns the new count of `kind`.
    """

    def __init__(self, counts: Counter[str], source: str, log: logging.Logger, log_every: int = 100) -> None:
        self.counts = counts
        self.source = source
        self.log = log
        self.log_every = max(1, int(log_every))
        self._lock = threading.Lock()

    def record(self, kind: str, exc: BaseException | str, thread: bool = True) -> int:
        """Count one error of `kind` (reason: an exception or a text); thread=False for a caller's error."""
        with self._lock:
            self.counts[kind] += 1
            if thread:
                self.counts["thread_error"] += 1
            n = self.counts[kind]
        if n == 1 or n % self.log_every == 0:
            why = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
            self.log.warning(
                "%s: %s #%d: %s (logged at the first and every %d-th)",
                self.source,
                kind,
                n,
                why,
                self.log_every,
            )
        return n


def evaluate_mute(check: MutedCheck | None, errors: ErrorLog) -> bool:
    """A driver's mute check (the guardian's takeover flag), evaluated now; one that raises is counted in
    `errors` and does not mute (a wrongly muted drone would keep its last command)."""
    if check is None:
        return False
    try:
        return bool(check())
    except Exception as exc:
        errors.record("muted_check_error", exc, thread=False)
        return False
