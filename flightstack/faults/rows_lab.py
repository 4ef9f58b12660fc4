"""The rows of `flightstack faults` flown on the emulated lab in this process that concern the
control loop and the link: link loss with a working uplink, a stalled control loop, and a lost land reply
beyond the hard fence. Each is a FaultRow (mission file, work directory) -> FaultResult judged on times
measured at the Tello emulators (sim_backend/emulated_lab.py, lab_flight.py).

`ROWS` lists every emulated-lab row in table order, also those of rows_lab_drivers.py (driver
threads, full disk), rows_lab_cli.py (signals, abort during takeoff: `flightstack fly` in a child process)
and rows_lab_bus.py (clock skew, abort with an agent missing: Zenoh) and rows_lab_process.py
(`process_killed`, `agent_stopped`: the guardian process).

The lab rows fly their own mission (the paper experiment re-pointed at the emulators, mode `none`, a few
seconds of pursuit): `--mission` does not apply to them. Faults start about 1 s into pursuit. Every
reaction time goes into `FaultResult.details` in milliseconds (faults.json); times are time.monotonic()
seconds, the emulators' clock.
"""

from __future__ import annotations

import itertools
import time
from pathlib import Path
from typing import Any

from flightstack.faults import rows_lab_bus, rows_lab_cli, rows_lab_drivers, rows_lab_poses, rows_lab_process
from flightstack.faults.lab_flight import (
    ZERO,
    emulator_errors,
    event_t,
    fly_inprocess,
    run_result,
    sub,
    wait_then,
    within,
)
from flightstack.faults.result import Checks, FaultResult, FaultRow
from flightstack.sim_backend.emulated_lab import (
    EmulatedLab,
    command_times,
    first,
    max_gap,
    ms,
    phase_times,
    rc_times,
)

HOVER_MARGIN_S = 0.1
"""Allowed lateness of a hover beyond its bound (s): two control ticks of 50 ms."""
LAND_MARGIN_S = 0.3
"""Allowed lateness of a land beyond its bound (s): the driver's 150 ms quiet window before a command
and two control ticks."""


# ---- link_loss_uplink --------------------------------------------------------------------------------------
OUTAGE_S = 3.5
"""How long drone 1's state stream stays off (s): detection after 1 s, then at least two land re-sends."""


def link_loss_uplink(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1's state stream stops for OUTAGE_S while its command uplink keeps working."""
    wall0 = time.perf_counter()
    name = "link_loss_uplink"
    root = workdir / name
    marks: dict[str, float] = {}
    with EmulatedLab(root, duration_s=6.0) as lab:
        e1, e2 = lab.tellos[1], lab.tellos[2]
        mission = lab.mission()
        timeout = mission.hardware.drone(1).link_timeout_s if mission.hardware else 1.0

        def inject(backend: Any) -> None:
            def stop() -> None:
                e1.faults.drop_state = True

            if wait_then(lab, marks, stop):
                time.sleep(OUTAGE_S)
                e1.faults.drop_state = False
                marks["restored"] = time.monotonic()

        run = fly_inprocess(lab, root / "run", injector=inject)
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_fault = marks.get("fault")
        c.check(t_fault is not None, "the pursuit never started: no fault injected")
        t0 = t_fault if t_fault is not None else run.t_start
        lost = run.safety("link_lost")
        t_detect = event_t(next((e for e in lost if e["drone"] == 1), None))
        c.check(
            [e["drone"] for e in lost] == [1], f"link_lost events for drones {[e['drone'] for e in lost]}"
        )
        detect = sub(t_detect, t0)
        c.check(
            within(detect, timeout + 0.25, timeout - 0.2),
            f"link loss detected {detect} s after the stream stopped (link_timeout_s {timeout:g} s)",
        )
        td = t_detect if t_detect is not None else t0
        t_hover = first(rc_times(e1, after=td - 0.005, value=ZERO))
        hover = sub(t_hover, td)
        c.check(within(hover, 2 * mission.dt_s), f"rc 0 0 0 0 {hover} s after detection (limit 2 ticks)")
        moving = rc_times(e1, after=td + mission.dt_s, nonzero=True)
        c.check(not moving, f"{len(moving)} non-zero rc after detection")
        lands = command_times(e1, "land", after=td)
        t_land = first(lands)
        land = sub(t_land, td)
        c.check(within(land, 1.0), f"land received {land} s after detection (limit 1 s)")
        c.check(len(lands) >= 2, f"land received {len(lands)} time(s) during the outage: not re-sent")
        resend = [b - a for a, b in itertools.pairwise(lands)]
        c.check(all(r <= 1.3 for r in resend), f"land re-sent after {resend} s (bound ~1 s)")
        t_down = first(phase_times(e1, "landed", after=td))
        c.check(t_down is not None, "drone 1 never landed after the link loss")
        rc0_before_land = rc_times(e1, after=td - 0.005, before=t_land or td, value=ZERO)
        rc0_gap = max_gap(rc0_before_land, td, t_land) if t_land is not None else None
        # drone 2 flies on: rc every tick until the mission's end, landed only then
        t_all = event_t(next(iter(run.safety("land_all")), None))
        c.check(t_all is not None, "no land_all at the end of the mission")
        gap2 = max_gap(rc_times(e2), t0, t_all) if t_all is not None else None
        c.check(within(gap2, 0.15), f"drone 2's rc stream paused {gap2} s (limit 0.15 s)")
        why2 = [e["detail"] for e in run.safety("land", 2)]
        c.check(len(why2) == 1 and why2[0].startswith("mission complete"), f"drone 2 landed for {why2}")
        c.check(run.end_reason() == "mission complete", f"run ended: {run.end_reason()}")
        emulator_errors(lab, c, blind=True)
        details = {
            "detect_ms": ms(detect),
            "rc0_after_detect_ms": ms(hover),
            "land_after_detect_ms": ms(land),
            "land_sends": len(lands),
            "land_resend_ms": [ms(r) for r in resend],
            "down_after_detect_ms": ms(sub(t_down, td)),
            "rc0_before_land": len(rc0_before_land),
            "rc0_max_gap_before_land_ms": ms(rc0_gap),
            "drone2_max_rc_gap_ms": ms(gap2),
        }
        observed = (
            f"state stream off {OUTAGE_S:g} s: link_lost after {details['detect_ms']} ms; at the emulator rc "
            f"0 0 0 0 +{details['rc0_after_detect_ms']} ms, land +{details['land_after_detect_ms']} ms (sent "
            f"{len(lands)}x, every {details['land_resend_ms']} ms), down +{details['down_after_detect_ms']} "
            f"ms; rc 0 0 0 0 sent {len(rc0_before_land)}x before the land (longest gap "
            f"{details['rc0_max_gap_before_land_ms']} ms); drone 2's rc never paused > "
            f"{details['drone2_max_rc_gap_ms']} ms; end: {run.end_reason()}"
        )
        expected = (
            f"link_lost after link_timeout_s ({timeout:g} s); at drone 1's emulator rc 0 0 0 0 within 2 "
            "ticks of detection and no non-zero rc after it, land within 1 s, re-sent (with rc 0 0 0 0) "
            "about every 1 s while telemetry is silent; drone 1 down; drone 2 flies to the end (rc never "
            "paused > 0.15 s). Known deviation from 'rc 0 0 0 0 every tick': the driver sends no "
            "rc while its land is pending (see details.rc0_max_gap_before_land_ms)"
        )
        return run_result(
            name,
            expected,
            observed,
            wall0,
            lab,
            run,
            c,
            details,
        )


# ---- loop_stall --------------------------------------------------------------------------------------------
STALL_S = 3.0
"""How long one agent's tick blocks (s): longer than the driver's loop_land_s (2 s)."""


class StallingBus:
    """A bus whose publish() blocks once for `stall_s` (s) at its first call after `arm(at)`: an agent's
    tick that hangs, and the whole control loop (safety ticks and the guardian's heartbeat) with it. Every
    other attribute is the wrapped bus's."""

    def __init__(self, inner: Any, stall_s: float) -> None:
        self.inner = inner
        self.stall_s = stall_s
        self.armed_at = float("inf")
        self.t_stall: float | None = None
        self.t_resume: float | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def arm(self, at: float) -> None:
        """Stall at the first publish at or after time.monotonic() `at` (s)."""
        self.armed_at = at

    def publish(self, msg: Any) -> None:
        """Publish through the wrapped bus, after the one stall when it is due."""
        if self.t_stall is None and time.monotonic() >= self.armed_at:
            self.t_stall = time.monotonic()
            time.sleep(self.stall_s)
            self.t_resume = time.monotonic()
        self.inner.publish(msg)


def _sender_of(emu: Any, t: float, text: str, ports: set[int]) -> str:
    """ "driver" when the datagram `text` received at `t` came from one of the driver's ports, else the
    sender's port (another process: the guardian), "?" if the emulator does not log senders."""
    for ts, txt, addr in list(getattr(emu, "senders", [])):
        if ts == t and txt == text:
            return "driver" if addr[1] in ports else f"port {addr[1]} (guardian)"
    return "?"


def loop_stall(mission_path: Path, workdir: Path) -> FaultResult:
    """The control loop stops for STALL_S (an agent's bus publish blocks) in pursuit."""
    wall0 = time.perf_counter()
    name = "loop_stall"
    root = workdir / name
    marks: dict[str, float] = {}
    ports: dict[int, set[int]] = {}
    holder: dict[str, StallingBus] = {}

    def wrap(bus: Any) -> StallingBus:
        holder["bus"] = StallingBus(bus, STALL_S)
        return holder["bus"]

    with EmulatedLab(root, duration_s=6.0) as lab:
        mission = lab.mission()
        hw = mission.hardware.drone(1) if mission.hardware else None
        hover_s, land_s = (hw.loop_hover_s, hw.loop_land_s) if hw else (0.5, 2.0)

        def inject(backend: Any) -> None:
            for i in backend.lab_drones:
                ports[i] = {backend.drone(i).link.chan._sock.getsockname()[1]}
            wait_then(lab, marks, lambda: holder["bus"].arm(time.monotonic()))

        run = fly_inprocess(lab, root / "run", injector=inject, bus_wrapper=wrap)
        lab.write_log(root / "emulators.json")
        bus = holder.get("bus")
        c = Checks()
        t_stall = bus.t_stall if bus is not None else None
        c.check(t_stall is not None, "the loop never stalled (pursuit not reached?)")
        ts = t_stall if t_stall is not None else run.t_start
        t_resume = bus.t_resume if bus is not None and bus.t_resume is not None else ts + STALL_S
        details: dict[str, Any] = {"stall_ms": ms(t_resume - ts)}
        notes = []
        for i, e in lab.tellos.items():
            before = [(t, rc) for t, rc in list(e.rc_history) if t <= ts]
            t_last, last_rc = before[-1] if before else (ts, ZERO)
            t_hover = first(rc_times(e, after=t_last, value=ZERO))
            t_land = first(command_times(e, "land", after=ts))
            hover, land = sub(t_hover, t_last), sub(t_land, t_last)
            if last_rc != ZERO:
                c.check(
                    within(hover, hover_s + HOVER_MARGIN_S),
                    f"drone {i}: rc 0 0 0 0 {hover} s after the loop's last rc (limit {hover_s:g} + "
                    f"{HOVER_MARGIN_S:g} s)",
                )
            c.check(
                within(land, land_s + LAND_MARGIN_S),
                f"drone {i}: land {land} s after the loop's last rc (limit {land_s:g} + {LAND_MARGIN_S:g} s)",
            )
            moving = rc_times(e, after=t_hover or ts, before=t_resume, nonzero=True)
            c.check(not moving, f"drone {i}: {len(moving)} non-zero rc after the hover during the stall")
            t_down = first(phase_times(e, "landed", after=ts))
            c.check(t_down is not None, f"drone {i} never landed after the stall")
            who_h = _sender_of(e, t_hover, "rc 0 0 0 0", ports.get(i, set())) if t_hover else "-"
            who_l = _sender_of(e, t_land, "land", ports.get(i, set())) if t_land else "-"
            details[f"drone{i}"] = {
                "last_rc": list(last_rc),
                "hover_after_last_rc_ms": ms(hover),
                "hover_by": who_h,
                "land_after_last_rc_ms": ms(land),
                "land_by": who_l,
                "down_after_last_rc_ms": ms(sub(t_down, t_last)),
            }
            notes.append(
                f"drone {i} (last rc {last_rc}): hover +{ms(hover)} ms by {who_h}, land +{ms(land)} ms by "
                f"{who_l}, down +{ms(sub(t_down, t_last))} ms"
            )
        reason = run.end_reason() or ""
        c.check(
            reason == "every drone landed" or "GuardianTakeoverError" in reason,
            f"run ended: {reason!r} (expected: every drone landed, or the guardian's takeover)",
        )
        emulator_errors(lab, c, blind=True)
        observed = f"loop stalled {details['stall_ms']} ms: " + "; ".join(notes) + f"; end: {reason}"
        expected = (
            f"at each emulator rc 0 0 0 0 within loop_hover_s ({hover_s:g} s) + {HOVER_MARGIN_S:g} s and "
            f"land within loop_land_s ({land_s:g} s) + {LAND_MARGIN_S:g} s of the loop's last rc, no "
            "non-zero rc after the hover, both down; sent by the driver's loop watchdog or, first when it "
            "runs, by the guardian process (0.5 s stall bound); the run ends (every drone landed, or the "
            "guardian's takeover)"
        )
        return run_result(
            name,
            expected,
            observed,
            wall0,
            lab,
            run,
            c,
            details,
        )


# ---- land_reply_lost ---------------------------------------------------------------------------------------
LAND_S = 2.0
"""Drone 1's emulated landing takes this long (s): its land() blocks a worker thread for ~3.5 s."""


def land_reply_lost(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1 crosses the hard fence (as motion capture sees it: +3 m in x) and its land replies are lost."""
    wall0 = time.perf_counter()
    name = "land_reply_lost"
    root = workdir / name
    marks: dict[str, float] = {}
    with EmulatedLab(root, duration_s=6.0, tello={1: {"land_s": LAND_S}}) as lab:
        e1, e2 = lab.tellos[1], lab.tellos[2]
        e1.faults.lost_replies = {"land"}
        mission = lab.mission()
        dt = mission.dt_s

        def cross() -> None:
            lab.mocap_offset[1] = lab.mocap_offset[1] + (3.0, 0.0, 0.0)

        run = fly_inprocess(lab, root / "run", injector=lambda backend: wait_then(lab, marks, cross) and None)
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_cross = marks.get("fault")
        c.check(t_cross is not None, "the pursuit never started: nothing injected")
        t0 = t_cross if t_cross is not None else run.t_start
        fence = [e for e in run.safety("fence_hard_land") if e["t"] >= t0]
        t_fence = event_t(next((e for e in fence if e["drone"] == 1), None))
        c.check(
            [e["drone"] for e in fence][:1] == [1], f"fence_hard_land events {[e['drone'] for e in fence]}"
        )
        detect = sub(t_fence, t0)
        c.check(within(detect, 2 * dt + 0.05), f"hard fence seen {detect} s after the crossing")
        tf = t_fence if t_fence is not None else t0
        t_hover = first(rc_times(e1, after=tf - 0.005, value=ZERO))
        t_land = first(command_times(e1, "land", after=t0))
        hover, land = sub(t_hover, tf), sub(t_land, tf)
        c.check(within(hover, 2 * dt), f"drone 1: rc 0 0 0 0 {hover} s after the fence event")
        c.check(within(land, 0.5), f"drone 1: land {land} s after the fence event (limit 0.5 s)")
        t_down = first(phase_times(e1, "landed", after=t0))
        c.check(t_down is not None, "drone 1 never landed")
        t_done = (t_down if t_down is not None else t0 + 5.0) + 0.05  # the land's reply is due at touchdown
        land_oks = [
            t
            for t, text, _ in list(e1.replies_sent)
            if t_land is not None and t_land <= t <= t_done and text == "ok"
        ]
        c.check(not land_oks, f"{len(land_oks)} land replies reached the driver (the fault is lost replies)")
        ticks = next((e for e in run.events() if e.get("event") == "safety tick"), {})
        worst = ticks.get("max_ms")
        c.check(
            worst is not None and worst < 1e3 * dt,
            f"longest safety tick {worst} ms (limit one control period, {1e3 * dt:g} ms)",
        )
        t_end1 = t_down if t_down is not None else t0 + 5.0
        gap2 = max_gap(rc_times(e2), t0, t_end1)
        c.check(gap2 <= 3 * dt, f"drone 2's rc paused {gap2} s while drone 1 landed (limit 3 ticks)")
        c.check(flying_at(e2, t_end1), "drone 2 was not flying while drone 1 landed")
        why2 = [e["detail"] for e in run.safety("land", 2)]
        c.check(len(why2) == 1 and why2[0].startswith("mission complete"), f"drone 2 landed for {why2}")
        emulator_errors(lab, c)
        details = {
            "fence_detect_ms": ms(detect),
            "rc0_after_fence_ms": ms(hover),
            "land_after_fence_ms": ms(land),
            "land_replies_received": len(land_oks),
            "down_after_fence_ms": ms(sub(t_down, tf)),
            "safety_tick_ms": {k: ticks.get(k) for k in ("ticks", "p50_ms", "p99_ms", "max_ms")},
            "drone2_max_rc_gap_ms": ms(gap2),
        }
        observed = (
            f"drone 1 beyond the hard fence (motion capture): fence_hard_land +{details['fence_detect_ms']} "
            f"ms; emulator: rc 0 0 0 0 +{details['rc0_after_fence_ms']} ms, land "
            f"+{details['land_after_fence_ms']} ms (replies lost: {len(land_oks)} received), down "
            f"+{details['down_after_fence_ms']} ms; safety tick p50 {_r(ticks.get('p50_ms'))} / p99 "
            f"{_r(ticks.get('p99_ms'))} / max {_r(worst)} ms over {ticks.get('ticks')} ticks; drone 2's rc "
            f"never paused > {details['drone2_max_rc_gap_ms']} ms; end: {run.end_reason()}"
        )
        expected = (
            "drone 1: fence_hard_land, rc 0 0 0 0 and land sent at once (land ≤ 0.5 s), down without any "
            f"land reply; every safety tick shorter than one control period ({1e3 * dt:g} ms); drone 2 stays "
            "supervised (rc never paused > 3 ticks) and flies to the end; both down"
        )
        return run_result(
            name,
            expected,
            observed,
            wall0,
            lab,
            run,
            c,
            details,
        )


def flying_at(emu: Any, t: float) -> bool:
    """The emulator's phase at time t (s) was "flying"."""
    phase = "landed"
    for tp, p in list(emu.phase_log):
        if tp > t:
            break
        phase = p
    return phase == "flying"


def _r(x: float | None) -> str:
    """A time in ms with 2 decimals, '?' when unknown."""
    return "?" if x is None else f"{x:.2f}"


ROWS: dict[str, FaultRow] = {
    "link_loss_uplink": link_loss_uplink,
    "loop_stall": loop_stall,
    "driver_thread_error": rows_lab_drivers.driver_thread_error,
    "land_reply_lost": land_reply_lost,
    "sighup": rows_lab_cli.sighup,
    "double_sigint": rows_lab_cli.double_sigint,
    "disk_full": rows_lab_drivers.disk_full,
    "robot_not_moving": rows_lab_drivers.robot_not_moving,
    "auto_land_in_flight": rows_lab_drivers.auto_land_in_flight,
    "raised_surface": rows_lab_drivers.raised_surface,
    **rows_lab_poses.ROWS,
    "clock_skew": rows_lab_bus.clock_skew,
    "abort_during_takeoff": rows_lab_cli.abort_during_takeoff,
    "abort_agent_missing": rows_lab_bus.abort_agent_missing,
    **rows_lab_process.ROWS,
}
"""The emulated-lab rows, in table order (the last two: the guardian's, rows_lab_process.py)."""
