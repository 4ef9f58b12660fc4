"""Which world ticks an agent accepts (served simulation): what the world can have done since the last one.

The world (server.py) publishes tick k, then waits for this agent's cmd of tick k, at most
`step_timeout_s` (the mission's bus.zenoh.lockstep_timeout_s), before it goes on. An agent sends the cmd
of a tick only after accepting it (client.py), so after its newest accepted tick k_a, received at wall
time r_a, the world can have published tick k_a + 1 at once and every further tick only after waiting
`step_timeout_s` for a cmd that cannot have come. Hence, at wall time r,

    k ≤ k_a + 1 + margin_ticks + ⌊(r − r_a + latency_s) / step_timeout_s⌋

(latency_s: how much earlier than its receipt the world may have published k_a; margin_ticks: timer
granularity). The first tick has no reference: the world starts ticking once every agent said hello or
after its start timeout, and then advances one tick per `step_timeout_s` for an agent that has not said
hello yet, so a late agent legitimately starts at any k. A tick must also carry the time of its index,
t = k·dt, within `time_tol_ticks`·dt (the world's clock adds dt per tick: rounding stays orders of
magnitude below that for any run of less than 10⁶ ticks).

Verdicts (counted by the link as drop reasons): "old tick" (k ≤ k_a: a duplicate or a replay), "tick
time went back", "tick time off its index" (|t − k·dt| too large), "tick from the future" (k beyond the
bound above). A refused tick never becomes the reference, so one forged future tick cannot make the
world's later ticks look old. An accepted tick with k > k_a + 1 is a gap (the world went on without
this agent's cmd, e.g. after a lock-step timeout): accepted, counted in `gaps` and `ticks_skipped`.

Residual risk: a forged tick within these bounds (plausible k and t) is accepted on a plaintext bus,
and so is a forged *first* tick with any k (t = k·dt): the agent then waits for a newer tick, the world
for its cmd, and it ends with WorldLostError before it took off (fails safe). Who may publish ticks is
the transport's to authenticate (mutual TLS and the ACL, comms/acl.py).
Units: s (wall seconds on time.monotonic(), mission seconds for t and dt).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from flightstack.sim_backend.served.messages import WorldTick


@dataclass(frozen=True)
class TickBounds:
    """How far the world can get ahead of this agent (module docstring)."""

    dt_s: float  # mission time per tick (s)
    step_timeout_s: float  # the world waits at most this long (wall s) for this agent's cmd of a tick
    latency_s: float = 0.5  # delivery and scheduling allowance (wall s)
    margin_ticks: int = 2
    time_tol_ticks: float = 1e-3  # |t − k·dt| allowed, in ticks

    def __post_init__(self) -> None:
        for name in ("dt_s", "step_timeout_s"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be positive and finite")
        if not (0 <= self.latency_s < math.inf and self.margin_ticks >= 0 and self.time_tol_ticks > 0):
            raise ValueError("latency_s, margin_ticks must be >= 0 and time_tol_ticks > 0")

    def max_k(self, k_ref: int, elapsed_s: float) -> int:
        """The newest tick the world can have published `elapsed_s` (wall s) after tick k_ref arrived."""
        waits = math.floor((max(0.0, elapsed_s) + self.latency_s) / self.step_timeout_s)
        return k_ref + 1 + self.margin_ticks + waits

    def time_mismatch(self, tick: WorldTick) -> bool:
        """True when the tick's time t is not k·dt (within time_tol_ticks·dt)."""
        return abs(tick.t - tick.k * self.dt_s) > self.time_tol_ticks * self.dt_s


def tick_refusal(
    current: WorldTick | None,
    new: WorldTick,
    bounds: TickBounds | None = None,
    ref_wall_s: float | None = None,
    now_wall_s: float = 0.0,
) -> str | None:
    """Why `new` must not replace the newest accepted tick `current` (a reason to count), or None.

    bounds None: only order is checked (old tick, time going back). ref_wall_s: when `current` arrived
    (wall s); now_wall_s: now, on the same clock."""
    if current is not None and new.k <= current.k:
        return "old tick"
    if current is not None and new.t < current.t:
        return "tick time went back"
    if bounds is None:
        return None
    if bounds.time_mismatch(new):
        return "tick time off its index"
    if (
        current is not None
        and ref_wall_s is not None
        and new.k > bounds.max_k(current.k, now_wall_s - ref_wall_s)
    ):
        return "tick from the future"
    return None


__all__ = ["TickBounds", "tick_refusal"]
