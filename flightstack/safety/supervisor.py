"""The mission-wide safety rules over every SafeDrone (DESIGN §7; the rules are stated in docs/safety.md;
flightstack/safety/drone.py has the per-drone ones): target lost → hover then land, land every drone, signal
handlers, the exception guard.

Times in seconds of mission clock.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from types import FrameType, TracebackType
from typing import Any, Literal

from flightstack.hal import Clock
from flightstack.safety.drone import SafeDrone
from flightstack.safety.rules import EventLog, SafetyLimits

__all__ = ["MissionSupervisor"]


class MissionSupervisor:
    """Mission-wide rules over all SafeDrones: target-lost hover, land all, signals, exception guard."""

    def __init__(
        self,
        drones: dict[int, SafeDrone],
        clock: Clock,
        limits: SafetyLimits,
        log: EventLog,
        concurrent_land: bool = False,
    ) -> None:
        """concurrent_land: land_all lands every drone at once, one thread each. For real drones, whose
        land() waits for the touchdown reply (a Tello: seconds): landing them one after the other would
        leave the last one flying for the sum of the others' landings. Simulated drones land instantly;
        they keep the sequential, deterministic order (event logs identical run to run)."""
        self.concurrent_land = concurrent_land
        self.drones = dict(drones)
        self.clock = clock
        self.limits = limits
        self.log = log
        self._lock = threading.RLock()
        self._t0: float | None = None
        self._last_seen: dict[int, float] = {}
        self._known: set[int] = set(self.drones)
        self._lost_episode = False
        self._lost_landing = False
        self._landing_depth = 0
        self._deferred_land: str | None = None
        self.signalled: str | None = None
        """The first signal received inside install_signal_handlers() (later ones are only logged)."""

    def update_visibility(self, visible: dict[int, bool]) -> bool:
        """Record which drones see the target now; True if the mission must hover.

        The mission hovers when every drone (supervised or reported here; a drone missing from `visible`
        counts as not seeing) has not seen the target for longer than target_lost_hover_after seconds.
        A drone that has never seen it counts from the first call. One event per episode.
        """
        with self._lock:
            now = self.clock.now()
            if self._t0 is None:
                self._t0 = now
            self._known.update(visible)
            for i, v in visible.items():
                if v:
                    self._last_seen[i] = now
            if not self._known:
                return False
            lost_for = min(now - self._last_seen.get(i, self._t0) for i in self._known)
            hold = lost_for > self.limits.target_lost_hover_after
            if hold and not self._lost_episode:
                self.log.record(
                    now,
                    None,
                    "target_lost_hover",
                    f"every drone lost the target for {lost_for:.2f} s "
                    f"> {self.limits.target_lost_hover_after:.2f} s: hover",
                )
            self._lost_episode = hold
            if lost_for > self.limits.target_lost_land_after and not self._lost_landing:
                self._lost_landing = True
                limit = self.limits.target_lost_land_after
                why = f"every drone lost the target for {lost_for:.2f} s > {limit:.2f} s: land"
                self.log.record(now, None, "target_lost_land", why)
                self.land_all("target lost")
            return hold

    def land_all(self, reason: str) -> None:
        """Land every drone that is not landed; idempotent.

        A drone whose land() raises is logged (land_failed) and retried by its tick(); with
        `limits.emergency_stop_if_land_fails` it gets emergency_stop() instead. The others are landed
        regardless. An interrupt (KeyboardInterrupt, SystemExit) raised while landing one drone does
        not stop the others from being landed; it is re-raised afterwards.
        """
        with self._lock:
            interrupt: BaseException | None = None
            self._landing_depth += 1
            try:
                pending = [(i, d) for i, d in self.drones.items() if not d.landed]
                pending.sort(key=lambda p: p[1]._land_reason == "link_lost")  # unreachable ones last
                if pending:
                    ids = [i for i, _ in pending]
                    self.log.record(self.clock.now(), None, "land_all", f"{reason}; landing drones {ids}")
                if self.concurrent_land and len(pending) > 1:
                    interrupt = self._land_concurrently(pending, reason)
                else:
                    for i, d in pending:
                        try:
                            self._land_one(i, d, reason)
                        except BaseException as exc:  # keep landing the others first, re-raise after
                            interrupt = interrupt or exc
            finally:
                self._landing_depth -= 1
            if interrupt is not None:
                raise interrupt

    def _land_concurrently(self, pending: list[tuple[int, SafeDrone]], reason: str) -> BaseException | None:
        """_land_one for every drone at once; waits for all of them, even through a Ctrl-C (returned, to be
        re-raised when every landing has been sent and answered or has failed)."""
        errors: list[BaseException] = []

        def one(i: int, d: SafeDrone) -> None:
            try:
                self._land_one(i, d, reason)
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=one, args=p, name=f"land-{p[0]}", daemon=True) for p in pending]
        for th in threads:
            th.start()
        interrupt: BaseException | None = None
        for th in threads:
            while th.is_alive():
                try:
                    th.join()
                except BaseException as exc:  # Ctrl-C while waiting: the landings go on, re-raise after
                    interrupt = interrupt or exc
        return interrupt or (errors[0] if errors else None)

    def _land_one(self, i: int, d: SafeDrone, reason: str) -> None:
        try:
            d.land(reason)
        except Exception as exc:
            why = f"{reason}; land() raised {type(exc).__name__}: {exc}"
            if not self.limits.emergency_stop_if_land_fails:
                return  # logged as land_failed by the drone; its tick() retries the land every period
            try:
                d.emergency_stop(why)
            except Exception as exc2:
                self.log.record(
                    self.clock.now(), i, "emergency_stop_failed", f"{why}; {type(exc2).__name__}: {exc2}"
                )

    def ignore_signals(self, why: str) -> None:
        """From now on a signal is logged and ignored (the run is landing and closing: `why`); call it where
        the landing code starts, so that not even a first Ctrl-C can interrupt it."""
        if self.signalled is None:
            self.signalled = why

    def install_signal_handlers(self) -> contextlib.AbstractContextManager[MissionSupervisor]:
        """Context manager: inside it SIGINT, SIGTERM, SIGHUP (the operator's ssh session dropped), SIGQUIT
        (Ctrl-\\) and SIGTSTP (Ctrl-Z: the process must not freeze with drones in the air) land every
        drone, then raise KeyboardInterrupt once. Every later signal is logged and ignored: a second Ctrl-C
        never interrupts the landing, the closing of the drivers or the disarming of the robot (SIGKILL
        still ends the process; the guardian process then lands the drones).

        Must be entered on the main thread. If the signal interrupts a call into a drone driver, the landing
        is deferred until that call has unwound (the driver may hold a lock): KeyboardInterrupt is raised at
        once, every drone's next command or tick lands it, and leaving the block lands them all. A signal
        received while land_all runs is logged and ignored (the landing it asks for is under way). The
        previous handlers are restored on exit.
        """
        return _SignalHandlers(self)

    def guard(self) -> contextlib.AbstractContextManager[MissionSupervisor]:
        """Context manager: any exception (also KeyboardInterrupt) leaving the block lands all, re-raised."""
        return _Guard(self)

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        now = self.clock.now()
        if self.signalled is not None:
            self.log.record(now, None, "signal", f"{name} after {self.signalled}: ignored, landing continues")
            return
        self.signalled = name
        if self._landing_depth > 0:
            self.log.record(now, None, "signal", f"{name} during land_all: ignored, landing continues")
            return
        # inline (simulated) drones would be re-entered by land_all: defer; background ones only start a job
        busy = [i for i, d in self.drones.items() if d.in_inner_call() and not d.background]
        if busy:
            self._deferred_land = f"signal {name}"
            for d in self.drones.values():
                d.request_abort(f"signal {name}")
            self.log.record(now, None, "signal", f"{name} inside drone {busy}'s driver: landing deferred")
            raise KeyboardInterrupt(f"signal {name}")
        self.log.record(now, None, "signal", f"{name}: landing all")
        self.land_all(f"signal {name}")
        raise KeyboardInterrupt(f"signal {name}")


class _Guard(contextlib.AbstractContextManager[MissionSupervisor]):
    def __init__(self, sup: MissionSupervisor) -> None:
        self._sup = sup

    def __enter__(self) -> MissionSupervisor:
        return self._sup

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> Literal[False]:
        if ev is not None:
            msg = str(ev)
            self._sup.land_all(f"{type(ev).__name__}: {msg}" if msg else type(ev).__name__)
        return False


_HANDLED_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGTSTP") if hasattr(signal, n)
)


class _SignalHandlers(contextlib.AbstractContextManager[MissionSupervisor]):
    _SIGNALS = _HANDLED_SIGNALS

    def __init__(self, sup: MissionSupervisor) -> None:
        self._sup = sup
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> MissionSupervisor:
        if threading.current_thread() is not threading.main_thread():
            raise RuntimeError("install_signal_handlers() must be entered on the main thread")
        try:
            for sig in self._SIGNALS:
                self._previous[sig] = signal.getsignal(sig)
                signal.signal(sig, self._sup._on_signal)
        except BaseException:
            self._restore()
            raise
        return self._sup

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> Literal[False]:
        try:
            reason, self._sup._deferred_land = self._sup._deferred_land, None
            if reason is not None:
                self._sup.land_all(reason)
        finally:
            self._restore()
        return False

    def _restore(self) -> None:
        for sig, prev in self._previous.items():
            signal.signal(sig, prev if prev is not None else signal.SIG_DFL)
        self._previous.clear()
