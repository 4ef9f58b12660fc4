"""The operator's abort (`flightstack abort`): publish at once, then collect acknowledgements.

`send_abort(mission)` publishes one abort (payload {"reason", "id"}) on every channel the mission's
agents can hear, *before* waiting for anyone:
  - Zenoh (`bus.zenoh` section present): the mission's control key, as participant "operator";
  - loopback UDP to 127.0.0.1:`operator_port(mission)` (bus kind "inproc": `flightstack fly` with the
    in-process bus listens there, operator_link.py); on real hardware signed with the operator's key
    from `bus.certs`.
An operator session that has just opened is not yet connected to the agents, so the abort is sent again
as soon as a new agent's presence token is seen (its subscriber is declared by then) and every
`resend_s` until every drone of the mission acknowledged or `timeout_s` passed. Agents acknowledge every
copy; the runner acts on the first. Acknowledgements of another abort (other id) are ignored.

Units: `timeout_s`, `resend_s`: seconds; `AbortAck.time`, `AbortReport.t_sent`: time.monotonic() (s);
`AbortReport.latency_ms`: milliseconds from the first send to the acknowledgement's receipt.
"""

from __future__ import annotations

import time
import uuid
from dataclasses import dataclass, field
from typing import Any

from flightstack.comms.control import (
    ABORT,
    MAX_REASON_CHARS,
    AbortAck,
    ControlEvent,
    encode_control,
    read_ack,
)
from flightstack.config.mission import Mission

POLL_S = 0.002  # how often the Zenoh operator session is checked for acknowledgements (s)


@dataclass
class AbortReport:
    """What one `send_abort` did and heard."""

    abort_id: str
    channels: list[str]  # "zenoh", "loopback 127.0.0.1:PORT"
    expected: list[int]  # every drone id of the mission
    t_sent: float  # time.monotonic() of the first send (s)
    sends: int = 0  # how many times the abort was sent (per channel)
    acks: dict[int, AbortAck] = field(default_factory=dict)  # drone id -> first acknowledgement
    # drones seen on Zenoh: by their liveliness token, or by an acknowledgement that came over Zenoh (an
    # ack can arrive before this fresh session has been told of the tokens: ~7 ms acks were seen in CI)
    present: list[int] | None = None  # None: no Zenoh

    @property
    def missing(self) -> list[int]:
        """Drones of the mission that did not acknowledge."""
        return [i for i in self.expected if i not in self.acks]

    def latency_ms(self, drone: int) -> float:
        """First send → acknowledgement of `drone` received (ms)."""
        return 1e3 * (self.acks[drone].time - self.t_sent)

    def processes(self) -> list[tuple[AbortAck, float]]:
        """One (acknowledgement, latency ms) per acknowledging process, fastest first."""
        seen: dict[tuple[int, str, str, tuple[int, ...]], AbortAck] = {}
        for a in self.acks.values():
            seen.setdefault((a.pid, a.host, a.via, a.drones), a)
        return sorted(((a, 1e3 * (a.time - self.t_sent)) for a in seen.values()), key=lambda x: x[1])


def send_abort(
    mission: Mission,
    reason: str = "operator abort",
    timeout_s: float = 2.0,
    resend_s: float = 0.1,
    *,
    zenoh_bus: Any = None,
) -> AbortReport:
    """Abort `mission` on every channel it listens on and wait up to `timeout_s` (s) for every drone's
    acknowledgement; see the module docstring. Raises only when no channel can be opened.

    zenoh_bus: an operator ZenohBus of this mission that is already open (used, not closed); by default
    one is opened (and closed) when the mission has a zenoh section."""
    from flightstack.comms.operator_link import OPERATOR_HOST, LoopbackOperatorClient, operator_port

    expected = sorted(d.id for d in mission.drones)
    abort_id = uuid.uuid4().hex
    payload: dict[str, Any] = {"reason": reason[:MAX_REASON_CHARS], "id": abort_id}  # longer: refused
    zbus: Any = None
    udp: LoopbackOperatorClient | None = None
    channels: list[str] = []
    try:
        if mission.bus.kind == "inproc":
            port = operator_port(mission)
            udp = LoopbackOperatorClient(mission.name, port)
            channels.append(f"loopback {OPERATOR_HOST}:{port}")
        if zenoh_bus is not None:
            zbus = zenoh_bus
            channels.append("zenoh")
        elif mission.bus.zenoh is not None:
            from flightstack.comms.factory import make_bus

            zbus = make_bus(mission, "operator", set(), kind="zenoh")
            channels.append("zenoh")
        datagram = encode_control(mission.name, ABORT, payload, [])
        if udp is not None and not mission.simulated:  # real drones hear only aborts the operator signed
            from flightstack.comms.factory import operator_key
            from flightstack.comms.operator_link import signed_datagram

            datagram = signed_datagram(datagram, operator_key(mission, private=True))

        def send() -> None:
            if udp is not None:
                udp.send(datagram)
            if zbus is not None:
                zbus.publish_control(ABORT, payload)

        seen_alive: set[int] = zbus.alive() if zbus is not None else set()  # already reached by send()
        report = AbortReport(abort_id, channels, expected, time.monotonic())
        send()
        report.sends = 1
        last_send = report.t_sent
        deadline = report.t_sent + max(0.0, timeout_s)
        while True:
            events: list[tuple[ControlEvent, str]] = []
            if zbus is not None:
                events += [(e, "zenoh") for e in zbus.control_events()]
            if udp is not None:
                wait = POLL_S if zbus is not None else 0.02
                events += [
                    (e, "loopback") for e in udp.receive(min(wait, max(deadline - time.monotonic(), 0)))
                ]
            else:
                time.sleep(POLL_S)
            for ev, via in events:
                ack = read_ack(ev, abort_id, set(expected), via)
                if ack is not None:
                    for i in ack.drones:
                        report.acks.setdefault(i, ack)
            now = time.monotonic()
            if not report.missing or now >= deadline:
                break
            alive = zbus.alive() if zbus is not None else set()
            if alive - seen_alive or now - last_send >= resend_s:
                seen_alive |= alive
                send()
                report.sends += 1
                last_send = now
        if zbus is not None:
            acked_on_zenoh = {i for i, ack in report.acks.items() if ack.via == "zenoh"}
            report.present = sorted((zbus.alive() | acked_on_zenoh) & set(expected))
        return report
    finally:
        if udp is not None:
            udp.close()
        if zbus is not None and zbus is not zenoh_bus:
            zbus.close()


__all__ = ["AbortReport", "send_abort"]
