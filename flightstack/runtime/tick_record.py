"""Recording one tick: the fields each agent contributes, declared once (DESIGN §7).

`AGENT_FIELDS` names, for every per-drone array of `Recording`, the attribute of the agent's
`TickRecord` it copies (a `Pose` is stored as its vector (x, y, z, θ) in the world frame, m and rad).
`record_tick` writes one row from it plus the truth; `TickBook` keeps the per-drone facts that are
counted or reported as events rather than stored per tick (vision rejections, the detection gate's
verdicts, neighbour changes).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field

from flightstack.events import Event
from flightstack.paper.geometry import Pose
from flightstack.recording.timeseries import Recording
from flightstack.runtime.agent import Agent, TickRecord

#: Recording array (shape (n_ticks, n_drones, ...)) <- TickRecord attribute, in recording order
AGENT_FIELDS: tuple[tuple[str, str], ...] = (
    ("g_bar_w", "g_bar_w"),  # ḡ_w,i: the observer's estimate of the target pose (world)
    ("e_e_meas", "e_e_meas"),  # e_e from the image (zeros when the target is not visible)
    ("u_e", "u_e"),  # observer input u_e,i
    ("mu_used", "mu_used"),  # fused GP mean μ of the target's body velocity
    ("var_own", "var_own"),  # own expert's predictive variance σ²
    ("V_cmd", "V_cmd"),  # body velocity command sent to the drone (m/s, rad/s)
    ("visible", "visible"),  # the target's features were measured this tick
    ("n_fused", "n_fused"),  # experts that entered the fusion
    ("frame_age", "frame_age"),  # age of the camera frame looked at (s); NaN without one
    ("pose_age", "pose_age"),  # age of the own pose used (s); NaN during a dropout
)


def _tick_value(last: TickRecord, attr: str) -> object:
    value = getattr(last, attr)  # a declared TickRecord field (AGENT_FIELDS), never a probe
    return value.as_vector() if isinstance(value, Pose) else value


@dataclass
class TickBook:
    """Per-drone facts kept across ticks: vision rejection counts, the neighbours last used, and the
    camera streams' counts when the mode began (runner.stream_counts)."""

    mode: str
    rejections: dict[int, Counter[str]] = field(default_factory=dict)
    neighbours_used: dict[int, set[int]] = field(default_factory=dict)
    video_at_start: dict[str, dict[str, int]] = field(default_factory=dict)
    gate: dict[int, Counter[str]] = field(default_factory=dict)

    @classmethod
    def of(cls, mode: str, ids: list[int]) -> TickBook:
        return cls(mode, {i: Counter() for i in ids}, {i: set() for i in ids})

    def note(self, rec: Recording, t: float, agent: Agent) -> None:
        """Count the agent's rejection reasons; an event when its set of neighbours changed."""
        i, last = agent.cfg.drone_id, agent.last
        if last.rejection:
            self.rejections[i][last.rejection] += 1
        for why in last.dropped:  # samples refused for their time (agent: stamp_refusal)
            self.rejections[i][why] += 1
        if not last.own_pose_fresh:
            self.rejections[i]["own pose lost (hovered)"] += 1
        if not math.isnan(last.gate_residual_px):
            count_gate(self.gate.setdefault(i, Counter()), last)
        used, prev = set(last.neighbours_used), self.neighbours_used[i]
        if used != prev:  # a neighbour left or rejoined fusion/consensus
            change = {"dropped": sorted(prev - used), "added": sorted(used - prev)}
            rec.events.append(Event(t, i, "neighbours", facts=change).record(self.mode))
            self.neighbours_used[i] = used

    def vision_rejections(self) -> dict[str, dict[str, int]]:
        return {str(i): dict(c) for i, c in self.rejections.items() if c}

    def vision_gate(self) -> dict[str, dict[str, int]]:
        """Per drone with a gated camera, count_gate's counts."""
        return {str(i): dict(c) for i, c in self.gate.items() if c}


GATE_COUNTS = (
    "detections", "accepted", "rejected", "from_damaged", "accepted_damaged", "truth_known", "within_3px",
    "within_3px_accepted", "accepted_over_3px", "accepted_over_10px", "accepted_damaged_over_3px",
    "accepted_damaged_over_10px", "tracked", "tracked_accepted", "tracked_accepted_over_3px", "mended",
    "mended_accepted_over_3px",
)  # fmt: skip
"""What count_gate counts, per tick whose image gave every marker (a frame looked at twice counts twice)."""


def count_gate(c: Counter[str], last: TickRecord) -> None:
    """Count one gated detection (GATE_COUNTS): its verdict, whether its frame was damaged and, where the
    camera knows the truth (simulated cameras), how far its farthest marker was from it (3 and 10 px)."""
    damaged, accepted, err = last.frame_damaged, not last.coasted, last.detection_error_px
    c["detections"] += 1
    c["accepted" if accepted else "rejected"] += 1
    c["from_damaged"] += damaged
    c["accepted_damaged"] += damaged and accepted
    if last.tracked:  # found from where the gate expected it, the detector had not (counted when it happens)
        c["tracked"] += 1
        c["tracked_accepted"] += accepted
    if last.mended:  # counted when it happens, as tracking is
        c["mended"] += 1
        if accepted and err > 3.0:  # False for NaN: the truth unknown
            c["mended_accepted_over_3px"] += 1
    if math.isnan(err):
        return
    c["truth_known"] += 1
    c["within_3px"] += err <= 3.0
    c["within_3px_accepted"] += err <= 3.0 and accepted
    if accepted:
        c["accepted_over_3px"] += err > 3.0
        c["accepted_over_10px"] += err > 10.0
        c["accepted_damaged_over_3px"] += damaged and err > 3.0
        c["accepted_damaged_over_10px"] += damaged and err > 10.0
        if last.tracked:
            c["tracked_accepted_over_3px"] += err > 3.0


def record_tick(
    rec: Recording,
    k: int,
    t: float,
    agents: list[Agent],
    truth: tuple[Pose, dict[int, Pose]],
    book: TickBook,
) -> None:
    """Row k of `rec`: mission time t (s), the truth (g_w0, g_wi: world frame) and AGENT_FIELDS of each
    agent (in recording order); marks the row done (`ticks_done = k + 1`)."""
    g_w0, g_wis = truth
    rec.t[k] = t
    rec.g_w0[k] = g_w0.as_vector()
    for i, a in enumerate(agents):
        rec.g_wi[k, i] = g_wis[a.cfg.drone_id].as_vector()
        for name, attr in AGENT_FIELDS:
            getattr(rec, name)[k, i] = _tick_value(a.last, attr)
        book.note(rec, t, a)
    rec.wall_t[k] = time.time()
    rec.ticks_done = k + 1
