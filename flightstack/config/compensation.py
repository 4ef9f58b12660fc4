"""The rig's `compensation:` section: delay-aware estimation and control (docs/equations.md §11).

Off, every agent flies the paper's law. On, each agent
- uses a camera frame at its capture time (the frame's stamp): the observer's error is measured against
  the estimate and the own pose as they were then, and carried forward to now with the estimate's own
  motion since and the target's motion over the delay (the estimate's mean velocity over the last
  second, VELOCITY_WINDOW_S in flightstack.runtime.agent);
- commands for the state at the time the command takes effect: the own pose `command_delay_s` +
  `response_s` ahead, predicted from the commands already sent through a first-order response, and the
  estimate carried along with the observer's present input u_e.

With every latency 0 (frames stamped at the tick, command_delay_s = response_s = 0) it is the paper's
law exactly.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import Field

from flightstack.config.links import LinkSpec
from flightstack.config.types import Strict as _Strict
from flightstack.paper.delay_compensation import MAX_DELAY_S, Compensation

EMULATED_TELLO_RESPONSE_S = 0.1
"""The emulated Tello's velocity response time constant (s): its rc acts through a first-order lag."""

Latency = Annotated[float, Field(ge=0, le=MAX_DELAY_S, allow_inf_nan=False)]


class CompensationSpec(_Strict):
    """`compensation:`. command_delay_s: from sending an rc command to the start of the drone's response
    (s; None: the rig's rc link mean delay, latency_s + jitter_s/2, held to the same MAX_DELAY_S by the
    mission's validation: `stand_in_problem`). response_s: the time constant of the
    drone's first-order velocity response (s; None: the simulated or emulated Tello's; on hardware it must
    be given, e.g. from `flightstack calibrate latency`). history_s: how far back own poses and estimates
    are kept (s); a frame captured earlier is not used and is counted ("frame too old")."""

    enabled: bool = False
    command_delay_s: Latency | None = None
    response_s: Latency | None = None
    history_s: Annotated[float, Field(gt=0, le=MAX_DELAY_S, allow_inf_nan=False)] = 1.0


def stand_in_problem(spec: CompensationSpec, rc: LinkSpec) -> str | None:
    """Why the rc link cannot stand in for an unset command_delay_s (its mean delay beyond
    MAX_DELAY_S, the bound command_delay_s has itself: the compensator predicts that far ahead), or
    None. The message starts with the key to change."""
    delay = rc.latency_s + rc.jitter_s / 2
    if spec.command_delay_s is not None or delay <= MAX_DELAY_S:
        return None
    return (
        f"links.rc.latency_s: with compensation on and compensation.command_delay_s unset, the rc link's "
        f"mean delay latency_s + jitter_s/2 = {delay:g} s stands in for the command delay and must be <= "
        f"{MAX_DELAY_S:g} s (the compensator predicts each command that far ahead); set a shorter rc "
        "link, compensation.command_delay_s, or compensation.enabled: false"
    )


def told(spec: CompensationSpec, rc: LinkSpec, response_s: float) -> Compensation:
    """What the compensator is told: the section's latencies, an unset command delay the rc link's mean
    (latency_s + jitter_s/2), an unset response `response_s` (the rig's drones')."""
    return Compensation(
        rc.latency_s + rc.jitter_s / 2 if spec.command_delay_s is None else spec.command_delay_s,
        response_s if spec.response_s is None else spec.response_s,
        spec.history_s,
    )


def written_out(section: dict[str, Any], rc: LinkSpec, response_s: float) -> dict[str, Any]:
    """A `compensation:` section (as read from YAML) with its unset latencies written out (`told`): for a
    mission that flies emulated devices as hardware, where hardware needs them given."""
    spec = CompensationSpec.model_validate(section)
    if not spec.enabled:
        return dict(section)
    c = told(spec, rc, response_s)
    return {**section, "command_delay_s": c.command_delay_s, "response_s": c.response_s}
