"""The rows of `flightstack faults` that break the devices' I/O under a flight of the emulated
lab in this process: socket errors in every driver thread (`driver_thread_error`), a full disk under
the recorder (`disk_full`), and a ground robot that does not move when nudged before takeoff
(`robot_not_moving`). FaultRows (mission file, work directory) -> FaultResult, listed in
rows_lab.ROWS; reaction times in `details` (ms), times time.monotonic() s.
"""

from __future__ import annotations

import errno
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from flightstack.faults.lab_flight import (
    emulator_errors,
    event_t,
    fly_inprocess,
    judge_lab_recording,
    patched,
    run_result,
    sub,
    wait_then,
)
from flightstack.faults.result import Checks, FaultResult
from flightstack.recording import run_dir as recorder
from flightstack.sim_backend.emulated_lab import EmulatedLab, command_times, max_gap, ms, rc_times


# ---- driver_thread_error -----------------------------------------------------------------------------------
class FaultySocket:
    """A socket proxy: the first `n` calls of each named method raise OSError(ENETUNREACH), then the real
    socket's method runs (tests/test_driver_threads.py uses it too)."""

    def __init__(self, sock: Any, **fail: int) -> None:
        self._sock = sock
        self._fail = dict(fail)
        self.raised: dict[str, int] = dict.fromkeys(fail, 0)
        self._lock = threading.Lock()

    def __getattr__(self, name: str) -> Any:
        real = getattr(self._sock, name)
        if name not in self._fail:
            return real

        def call(*args: Any, **kw: Any) -> Any:
            with self._lock:
                fail = self.raised[name] < self._fail[name]
                if fail:
                    self.raised[name] += 1
            if fail:
                raise OSError(errno.ENETUNREACH, "Network is unreachable (injected)")
            return real(*args, **kw)

        return call


INJECTED = {
    "state receiver recv_error": 8,
    "command channel recv_error": 6,
    "command channel send_error": 4,
    "monitor_error": 3,
    "video recv_error": 10,
    "robot send_error": 12,
}
"""Errors injected per thread (per drone for the command channel, the monitor and the video receiver)."""


def _inject_thread_errors(backend: Any) -> dict[str, Any]:
    """Socket errors into every driver thread of `backend` (HardwareBackend); returns the counters to
    watch: name -> (Counter, key, expected count)."""
    watch: dict[str, Any] = {}
    drones = {i: d.driver for i, d in backend.lab_drones.items()}
    rx = next(iter(drones.values())).link.rx  # one state receiver per state port (station mode: shared)
    rx._sock = FaultySocket(rx._sock, recvfrom=INJECTED["state receiver recv_error"])
    watch["state receiver"] = (rx.counts, "recv_error", INJECTED["state receiver recv_error"])
    for i, d in drones.items():
        chan = d.link.chan
        n_recv, n_send = INJECTED["command channel recv_error"], INJECTED["command channel send_error"]
        chan._sock = FaultySocket(chan._sock, recv=n_recv, send=n_send)
        watch[f"drone {i} command channel (recv)"] = (chan.counts, "recv_error", n_recv)
        watch[f"drone {i} command channel (send)"] = (chan.counts, "send_error", n_send)
        real_step, boom = d.watchdog.step, [0]

        def step(now: float, real: Callable[[float], None] = real_step, n: list[int] = boom) -> None:
            if n[0] < INJECTED["monitor_error"]:
                n[0] += 1
                raise OSError(errno.ENETUNREACH, "Network is unreachable (injected)")
            real(now)

        d.watchdog.step = step  # the watchdog thread calls self.step: this instance attribute
        watch[f"drone {i} monitor"] = (d.counts, "monitor_error", INJECTED["monitor_error"])
        cam = backend.camera(i)
        if cam._rx is not None:
            cam._rx._sock = FaultySocket(cam._rx._sock, recvfrom=INJECTED["video recv_error"])
            watch[f"drone {i} video"] = (cam.counts, "recv_error", INJECTED["video recv_error"])
    robot = backend.robot
    if robot is not None and robot._link is not None:
        link = robot._link
        real_write, wboom = link.conn.write, [0]

        def write(buf: bytes) -> None:
            if wboom[0] < INJECTED["robot send_error"]:
                wboom[0] += 1
                raise OSError(errno.ENETUNREACH, "Network is unreachable (injected)")
            real_write(buf)

        link.conn.write = write
        watch["robot link"] = (robot.counts, "send_error", INJECTED["robot send_error"])
    return watch


def _threads_alive(backend: Any) -> dict[str, bool]:
    """Thread name -> alive, for every background thread of the backend's drivers."""
    out: dict[str, bool] = {}
    for i, lab_drone in backend.lab_drones.items():
        d = lab_drone.driver
        rx, chan = d.link.rx, d.link.chan
        out[f"drone {i} state receiver"] = rx is not None and rx._thread.is_alive()
        out[f"drone {i} command channel"] = chan is not None and chan._thread.is_alive()
        out[f"drone {i} monitor"] = d.watchdog.running()
        cam = backend.camera(i)
        out[f"drone {i} video"] = cam._rx is not None and cam._rx.alive()
    if backend.robot is not None:
        out.update({f"robot {k}": v for k, v in backend.robot.threads_alive().items()})
    return out


def driver_thread_error(mission_path: Path, workdir: Path) -> FaultResult:
    """Socket errors injected into every driver thread (state, commands, monitor, video, robot) in flight."""
    wall0 = time.perf_counter()
    name = "driver_thread_error"
    root = workdir / name
    marks: dict[str, float] = {}
    found: dict[str, Any] = {}
    with EmulatedLab(root, duration_s=6.0) as lab:

        def inject(backend: Any) -> None:
            def act() -> None:
                found["watch"] = _inject_thread_errors(backend)

            if not wait_then(lab, marks, act):
                return
            watch = found["watch"]
            deadline = time.monotonic() + 4.0
            while time.monotonic() < deadline:
                if all(cnt[key] >= n for cnt, key, n in watch.values()):
                    break
                time.sleep(0.01)
            marks["counted"] = time.monotonic()
            found["counts"] = {k: int(cnt[key]) for k, (cnt, key, _) in watch.items()}
            found["alive"] = _threads_alive(backend)
            found["setpoints"] = len(lab.rover.setpoint_records())

        run = fly_inprocess(lab, root / "run", injector=inject)
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_fault = marks.get("fault")
        c.check(t_fault is not None, "the pursuit never started: nothing injected")
        t0 = t_fault if t_fault is not None else run.t_start
        watch = found.get("watch", {})
        counts = found.get("counts", {})
        want = {k: n for k, (_, _, n) in watch.items()}
        c.check(bool(want) and counts == want, f"errors counted {counts}, injected {want}")
        alive = found.get("alive", {})
        dead = [k for k, v in alive.items() if not v]
        c.check(bool(alive) and not dead, f"threads dead after the errors: {dead or 'not checked'}")
        t_all = event_t(next(iter(run.safety("land_all")), None))
        c.check(t_all is not None, "no land_all at the end of the mission")
        t_end = t_all if t_all is not None else run.t_end
        gaps = {i: max_gap(rc_times(e), t0, t_end) for i, e in lab.tellos.items()}
        c.check(all(g <= 0.35 for g in gaps.values()), f"rc streams paused {gaps} s (limit 0.35 s)")
        after = {
            i: len(rc_times(e, after=marks.get("counted", t0), before=t_end)) for i, e in lab.tellos.items()
        }
        c.check(all(n >= 10 for n in after.values()), f"rc after the errors: {after}")
        n_sp = found.get("setpoints", 0)
        sp_after = len(lab.rover.setpoint_records()) - n_sp
        c.check(sp_after > 0, "no robot set-point after the errors")
        early = [
            e for e in run.safety() if e["kind"] in ("link_lost", "land", "drone_error") and e["t"] < t_end
        ]
        c.check(not early, f"safety reactions to the errors: {[(e['kind'], e['drone']) for e in early]}")
        c.check(run.end_reason() == "mission complete", f"run ended: {run.end_reason()}")
        emulator_errors(lab, c)
        details = {
            "errors_counted": counts,
            "threads_alive": alive,
            "max_rc_gap_ms": {str(i): ms(g) for i, g in gaps.items()},
            "counted_after_ms": ms(sub(marks.get("counted"), t_fault)),
            "rc_after_errors": {str(i): n for i, n in after.items()},
            "robot_setpoints_after_errors": sp_after,
        }
        observed = (
            f"{sum(counts.values())} socket errors injected in {len(counts)} threads, all counted within "
            f"{details['counted_after_ms']} ms; threads alive {sum(alive.values())}/{len(alive)}; rc streams "
            f"paused at most {details['max_rc_gap_ms']} ms; {after} rc and {sp_after} robot set-points "
            f"after; end: {run.end_reason()}"
        )
        expected = (
            "every error counted (state receiver, command channel send/recv, monitor, video, robot link), "
            "every thread alive; the flight goes on: rc to each Tello never paused > 0.35 s, no link loss "
            "or landing before the mission's end"
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


# ---- disk_full ---------------------------------------------------------------------------------------------
def disk_full(mission_path: Path, workdir: Path) -> FaultResult:
    """Every write of the recording stream fails with ENOSPC from 1 s into pursuit (recorder._write_bytes)."""
    wall0 = time.perf_counter()
    name = "disk_full"
    root = workdir / name
    marks: dict[str, float] = {}
    armed = threading.Event()
    real = recorder._write_bytes

    def full(fd: int, data: bytes) -> None:
        if armed.is_set():
            marks.setdefault("first_enospc", time.monotonic())
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd, data)

    with EmulatedLab(root, duration_s=5.0) as lab, patched(recorder, "_write_bytes", full):
        mission = lab.mission()
        n_ticks = mission.n_ticks
        run = fly_inprocess(
            lab, root / "run", injector=lambda backend: wait_then(lab, marks, armed.set) and None
        )
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_fault = marks.get("fault")
        c.check(t_fault is not None, "the pursuit never started: nothing injected")
        t0 = t_fault if t_fault is not None else run.t_start
        rec = run.rec
        flown = rec.ticks_done if rec is not None else 0
        c.check(flown == n_ticks, f"{flown} of {n_ticks} ticks flown")
        c.check(rec is not None and rec.error is None, f"run error {None if rec is None else rec.error!r}")
        stops = [e for e in (rec.events if rec is not None else []) if e.get("event") == "recording_stopped"]
        c.check(
            len(stops) == 1 and "ENOSPC" in str(stops[0].get("reason")), f"recording_stopped events {stops}"
        )
        written = int(stops[0].get("ticks_written", -1)) if stops else -1
        c.check(0 <= written < n_ticks, f"{written} ticks written to the stream of {n_ticks}")
        status = (run.metrics or {}).get("recording", {})
        c.check(
            status.get("complete") is False and "No space left" in str(status.get("reason")),
            f"metrics recording {status}",
        )
        moving = {i: len(rc_times(e, after=t0 + 0.5, nonzero=True)) for i, e in lab.tellos.items()}
        c.check(all(n > 10 for n in moving.values()), f"non-zero rc after the disk filled: {moving}")
        c.check(
            run.end_reason() == "mission complete"
            or (rec is not None and _rec_end(rec) == "mission complete"),
            f"run ended: {run.end_reason() or (rec and _rec_end(rec))}",
        )
        emulator_errors(lab, c)
        t_stop_wall = float(stops[0]["wall_t"]) if stops else None
        details = {
            "first_enospc_after_fault_ms": ms(sub(marks.get("first_enospc"), t_fault)),
            "ticks_flown": flown,
            "ticks_written": written,
            "recording": status,
            "stop_event_wall_t": t_stop_wall,
        }
        observed = (
            f"ENOSPC from 1 s into pursuit (first write refused +{details['first_enospc_after_fault_ms']} "
            f"ms): recording_stopped after {written} ticks written; flew {flown}/{n_ticks} ticks; metrics "
            f"recording {status}; non-zero rc after the disk filled {moving}; end: "
            f"{None if rec is None else _rec_end(rec)}"
        )
        expected = (
            "the flight goes on to the end (every tick flown, rc on every tick), one `recording_stopped` "
            "event naming ENOSPC, metrics.json says recording complete: false (No space left on device), "
            "drones land"
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
            recording=judge_lab_recording(run, complete=False),
        )


def _rec_end(rec: Any) -> str | None:
    """The reason of the Recording's `end` event (None without one)."""
    ends = [e for e in rec.events if e.get("event") == "end"]
    return str(ends[0]["reason"]) if ends else None


# ---- robot_not_moving --------------------------------------------------------------------------------------
def robot_not_moving(mission_path: Path, workdir: Path) -> FaultResult:
    """The robot's set-points never reach it (ScamperDriver.send_body_velocity dropped): it does not move
    when nudged before takeoff."""
    from flightstack.drivers.scamper.driver import ScamperDriver

    wall0 = time.perf_counter()
    name = "robot_not_moving"
    root = workdir / name
    with (
        EmulatedLab(root, duration_s=3.0) as lab,
        patched(ScamperDriver, "send_body_velocity", lambda self, V: None),
    ):
        x0 = lab.rover.pose_flu().p[:2].copy() if lab.rover is not None else None
        run = fly_inprocess(lab, root / "run")
        x1 = lab.rover.pose_flu().p[:2].copy() if lab.rover is not None else None
        lab.write_log(root / "emulators.json")
        c = Checks()
        rec = run.rec
        error = "" if rec is None else str(rec.error or "")
        c.check("did not move as commanded" in error and "\n" not in error, f"run error {error!r}")
        kinds = [e.get("kind") for e in (rec.events if rec is not None else []) if e.get("event") == "safety"]
        c.check(kinds.count("robot_refuse_takeoff") == 1, f"safety events {kinds}: one robot_refuse_takeoff")
        c.check("takeoff" not in kinds, f"a takeoff was accepted: {kinds}")
        sent = {i: len(command_times(e, "takeoff")) for i, e in lab.tellos.items()}
        c.check(not any(sent.values()), f"takeoff datagrams at the drones: {sent}")
        moved = float(np.hypot(*(x1 - x0))) if x0 is not None and x1 is not None else float("nan")
        c.check(moved < 0.005, f"the robot moved {moved:.3f} m (emulator)")
        emulator_errors(lab, c)
        observed = (
            f"nothing took off (takeoff datagrams {sent}); the robot moved {moved * 1000:.1f} mm; run error: "
            f"{error}"
        )
        return run_result(
            name,
            "the mission stops before takeoff with one line (`robot_refuse_takeoff`): nudged 0.05 m, the "
            "robot did not move as commanded; no takeoff sent",
            observed,
            wall0,
            lab,
            run,
            c,
            {"robot_moved_m": moved, "takeoffs_sent": sent},
            recording=[],
        )


# ---- auto_land_in_flight -----------------------------------------------------------------------------------
def auto_land_in_flight(mission_path: Path, workdir: Path) -> FaultResult:
    """1 s into pursuit drone 1 begins a landing of its own and says `error Auto land` unprompted
    (TelloFaults.self_land_now, auto_land_notice: the notice's trigger is assumed, docs/drivers.md)."""
    wall0 = time.perf_counter()
    name = "auto_land_in_flight"
    root = workdir / name
    marks: dict[str, float] = {}
    held: dict[str, Any] = {}

    with EmulatedLab(root, duration_s=6.0) as lab:
        emu1 = lab.tellos[1]

        def land_by_itself() -> None:
            emu1.faults.auto_land_notice = True
            emu1.faults.self_land_now = True

        def inject(backend: Any) -> None:
            held["driver"] = backend.drone(1)
            wait_then(lab, marks, land_by_itself)

        run = fly_inprocess(lab, root / "run", injector=inject)
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_fault = marks.get("fault")
        c.check(t_fault is not None, "the pursuit never started: nothing injected")
        t_own = next((t for t, ph in emu1.phase_log if ph == "landing" and t_fault and t >= t_fault), None)
        c.check(emu1.landed_by_itself and t_own is not None, "drone 1 never began a landing of its own")
        driver = held.get("driver")
        notices = [e for e in (driver.events if driver is not None else []) if e.kind == "error_unanswered"]
        c.check(
            len(notices) == 1 and "Auto land" in notices[0].detail, f"driver 1 error_unanswered {notices}"
        )
        t_notice = notices[0].t if notices else None
        late = rc_times(emu1, after=t_notice + 0.01) if t_notice is not None else []
        c.check(not late, f"{len(late)} rc reached drone 1 after its notice was recorded")
        events = list(run.rec.events) if run.rec is not None else run.events()
        safety = [(e.get("kind"), e.get("drone")) for e in events if e.get("event") == "safety"]
        c.check(("landing_by_drone", 1) in safety, f"no landing_by_drone for drone 1 in {safety}")
        after = (t_own or 0.0) + 0.5
        moving = len(rc_times(lab.tellos[2], after=after, nonzero=True))
        c.check(moving > 10, f"drone 2: {moving} non-zero rc after drone 1 began to land (it flies on)")
        # rc already on its way when drone 1 began to land by itself is ignored by it, as a real one does
        unforeseen = {1: (t_own, t_notice + 0.01)} if t_own is not None and t_notice is not None else {}
        in_flight = emulator_errors(lab, c, unforeseen=unforeseen)
        details = {
            "rc_ignored_before_notice": len(in_flight),
            "notice_after_own_landing_ms": ms(sub(t_notice, t_own)),
            "rc_to_drone_1_after_notice": len(late),
            "drone_2_nonzero_rc_after": moving,
            "safety_events": [k for k, _ in safety],
        }
        observed = (
            f"drone 1 began its own landing +{ms(sub(t_own, t_fault))} ms after the fault; the driver "
            f"recorded {[e.detail for e in notices]} +{details['notice_after_own_landing_ms']} ms after it; "
            f"rc to drone 1 after that: {len(late)} (ignored while it was on its way: {len(in_flight)}); "
            f"drone 2 kept flying ({moving} non-zero rc); safety events {details['safety_events']}"
        )
        expected = (
            "the driver records `error Auto land` (error_unanswered) and sends drone 1 no rc from then on; "
            "the safety layer records landing_by_drone and waits for its touchdown; drone 2 flies on until "
            "the target-lost rules act"
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


# ---- raised_surface ----------------------------------------------------------------------------------------
RAISED_TOF_CM = 31
"""What a real Tello resting on a raised surface (a box, a carpet, a landing pad) reads as `tof`
(users' flight logs); its floor value is 10."""


def raised_surface(mission_path: Path, workdir: Path) -> FaultResult:
    """Drone 1 stands on a raised surface: its `tof` reads 31 cm on the ground, not 10."""
    from flightstack.sim_backend.emulators.tello.recorded import TOF_GROUND_CM

    wall0 = time.perf_counter()
    name = "raised_surface"
    root = workdir / name
    below = float(RAISED_TOF_CM - TOF_GROUND_CM)
    with EmulatedLab(root, duration_s=3.0, tello={1: {"surface": lambda x, y: -below}}) as lab:
        emu1 = lab.tellos[1]
        run = fly_inprocess(lab, root / "run")
        lab.write_log(root / "emulators.json")
        c = Checks()
        t_takeoff = command_times(emu1, "takeoff")
        lands = command_times(emu1, "land")
        early = [t for t in lands if not t_takeoff or t < t_takeoff[0]]
        flew = any(ph == "flying" for _, ph in emu1.phase_log)
        ground_tof = emu1.last_state.split("tof:")[1].split(";")[0] if "tof:" in emu1.last_state else "?"
        c.check(len(t_takeoff) == 1, f"takeoff datagrams at drone 1: {len(t_takeoff)}")
        c.check(not early, f"{len(early)} land(s) sent to drone 1 before its takeoff")
        c.check(flew and emu1.phase == "landed", f"drone 1 flew {flew}, ends {emu1.phase}")
        c.check(len(lands) == 1, f"land datagrams at drone 1: {len(lands)}")
        c.check(ground_tof == str(RAISED_TOF_CM), f"drone 1's tof at rest after the flight: {ground_tof}")
        rec = run.rec
        c.check(rec is not None and rec.error is None, f"run error {None if rec is None else rec.error!r}")
        emulator_errors(lab, c)
        observed = (
            f"drone 1 on a raised surface (tof {ground_tof} cm at rest): takeoff sent {len(t_takeoff)}x, "
            f"land {len(lands)}x ({len(early)} before the takeoff), flew {flew}, ends {emu1.phase}; "
            f"refused {len(emu1.refused)} commands"
        )
        return run_result(
            name,
            "on the ground at connect (the motors' verdict), one takeoff, no land before it, one land at the "
            "end, nothing refused",
            observed,
            wall0,
            lab,
            run,
            c,
            {"takeoffs": len(t_takeoff), "lands": len(lands), "lands_before_takeoff": len(early)},
        )
