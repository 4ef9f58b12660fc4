"""`flightstack preflight MISSION`: check every device and file of a hardware mission before anyone flies.

Each device is checked in its own thread, all at once, with the mission's own bounded timeouts; the
whole run is bounded by `deadline_s`, and a device that has not answered by then is a FAIL naming it.
Nothing takes off, nothing moves: the robot is listened to (HEARTBEAT), its parameters read and its EKF
origin set to the lab origin (which moves nothing), never armed, its mode never changed; a Tello gets
`command`, the lab file's SDK 3.0 video settings, `streamon`/`streamoff` and read-only queries.

Rows: (device, check, status, detail) with status PASS, WARN (flyable, but look) or FAIL (do not fly).
The checks (how an operator uses them: docs/real-lab.md):

- certificates: the pair this computer's participant needs (check_certs), not expired;
- computer: the tick's compiled math ("compiled math"), compiled or loaded before any device thread
  starts (a cold compile holds the GIL for seconds);
- files: every camera calibration exists, is valid, was measured (rms_px set; the nominal templates
  are not) and matches the drone's video size, with one marker colour per feature point; the experts
  file, if the mission names one.
- gains: κ of Theorem 1. WARN (never FAIL) when not positive: the paper flies its experiment with
  gains that violate it. Without trained experts, L_μ = 0 gives an upper bound of κ.
- computer: binding sockets to an interface is permitted ("interface binding", when a drone names its
  interface: SO_BINDTODEVICE needs CAP_NET_RAW on Linux before 5.7; drivers/netif.py).
- drone N: its interface, when it names one (exists, link up, an IPv4 address whose subnet holds the
  drone's, no strict reverse-path filter dropping its datagrams: drivers/netif.py; a FAIL here is the
  drone's only row); reachable (SDK mode, confirmed by its state stream), battery ≥
  safety.min_battery_takeoff, temperature, on the ground (flight phase from telemetry), firmware (SDK
  version and serial; FAIL when the mission needs SDK 3.0 — a per-drone video port, the downward camera
  or video settings — and the drone has less: a plain Tello as `paper_experiment`'s drone 1, whose
  camera looks down, is refused in that one line, its camera left unstarted), each SDK 3.0 video setting
  of the lab file (`hardware.video`; FAIL unless the drone answered `ok` at connect, naming the key, the
  drone, its reply and the fix), Wi-Fi signal (`wifi?`, WARN when weak or unanswered); its camera streams
  and the frame size matches the calibration.
- topology: the drones checked from this computer must not share an address or video port through one
  interface (access-point mode: an adapter per drone, `interface:`, or `--id N` on each drone's computer).
- mocap: the server answers; it streams multicast, or at least frames arrive (Motive's unicast frames
  never reach libmotioncapture 1.1); no body shows a Y-up sign (`y_up_signs`: one FAIL naming Motive's
  Up Axis setting); no streamed body is missing from the model definitions read at connect; every body
  (drones, target) is tracked, level (tilt limit) and inside the fence's x/y box (the target too: the
  drones follow it).
- robot: a HEARTBEAT within heartbeat_timeout_s (mode and armed state reported); its own GCS failsafe
  (ArduPilot parameters read over MAVLink, judged by drivers/scamper/failsafe.py): FAIL unless it is on,
  holds the robot, acts within 5 s of our last heartbeat and watches our system id; external
  navigation (drivers/scamper/vehicle.py): FAIL unless AHRS_EKF_TYPE 3, EK3_SRC1_POSXY 6, EK3_SRC1_YAW 6,
  VISO_TYPE 1; EKF origin: FAIL unless the vehicle reports GPS_GLOBAL_ORIGIN after SET_GPS_GLOBAL_ORIGIN;
  GUIDED timeout: FAIL unless GUID_TIMEOUT is within [5 set-point periods, 3 s]; kinematics (FRAME_CLASS,
  FRAME_TYPE, SERVOn_FUNCTION): reported, WARN when unknown.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from flightstack.config.mission import Mission

if TYPE_CHECKING:
    from flightstack.drivers.scamper.link import ScamperConfig
    from flightstack.drivers.scamper.nav import LabOrigin
    from flightstack.drivers.scamper.params import OriginProbe
    from flightstack.drivers.tello.camera import TelloCamera
from flightstack.vision.camera_file import CameraCalibration
from flightstack.vision.picture import picture_of

Status = Literal["PASS", "WARN", "FAIL"]
BODY_WAIT_S = 1.0  # after connecting, how long motion capture gets to report every body (s)


@dataclass(frozen=True)
class CheckRow:
    device: str
    check: str
    status: Status
    detail: str


def _row(device: str, check: str, ok: bool, detail: str, warn: bool = False) -> CheckRow:
    return CheckRow(device, check, "PASS" if ok else ("WARN" if warn else "FAIL"), detail)


# ---- files and gains (no device) ---------------------------------------------------------------------
def check_kernels() -> CheckRow:
    """Compile or load the tick's kernels now (flightstack.paper.kernels_warmup), never mid-flight."""
    from flightstack.paper.kernels_warmup import warm_up

    try:
        took = warm_up()
    except Exception as exc:  # numba missing or broken: the agents could not run
        return _row("computer", "compiled math", False, f"{type(exc).__name__}: {exc}")
    return _row("computer", "compiled math", True, f"kernels ready ({took:.1f} s)")


def check_files(mission: Mission) -> list[CheckRow]:
    from flightstack.vision.camera_file import CalibrationError, load_calibration

    rows = []
    for d in mission.drones:
        if d.camera is None or d.camera.calibration is None:
            continue
        path = mission.resolve(d.camera.calibration)
        dev = f"drone {d.id}"
        if not path.is_file():
            rows.append(_row(dev, "camera calibration", False, f"file not found: {path}"))
            continue
        try:
            cal = load_calibration(path)
        except CalibrationError as exc:
            rows.append(_row(dev, "camera calibration", False, str(exc)))
            continue
        if cal.rms_px is None:
            why = f"{path.name}: never measured (rms_px unset); run `flightstack calibrate camera`"
            rows.append(_row(dev, "camera calibration", False, why))
        else:
            rows.append(_row(dev, "camera calibration", True, f"{path.name}: RMS {cal.rms_px:.2f} px"))
        if cal.fiducial is not None:
            from flightstack.vision.fiducial import placement_problem

            fid = cal.fiducial
            misplaced = placement_problem(fid, np.array(mission.target.feature_points, dtype=float))
            what = f"ArUco {fid.dictionary} id {fid.id}, side {fid.side_m:g} m"
            detail = what if misplaced is None else f"{path.name}: {misplaced}"
            rows.append(_row(dev, "fiducial", misplaced is None, detail))
        elif not cal.markers:
            rows.append(
                _row(dev, "marker colours", False, f"{path.name}: no markers; run `calibrate markers`")
            )
        elif len(cal.markers) != len(mission.target.feature_points):
            why = f"{len(cal.markers)} colours for {len(mission.target.feature_points)} feature points"
            rows.append(_row(dev, "marker colours", False, why))
        else:
            rows.append(_row(dev, "marker colours", True, ", ".join(m.name for m in cal.markers)))
    if mission.gp.experts_file is not None:
        p = mission.resolve(mission.gp.experts_file)
        rows.append(
            _row("mission", "GP experts file", p.is_file(), str(p) if p.is_file() else f"not found: {p}")
        )
    return rows


def check_certs(mission: Mission, drone_ids: list[int], all_in_one: bool = False) -> list[CheckRow]:
    """The mission's certificates for what this computer runs. On Zenoh: its participant's
    pair (`agent-N` for `--id N`, `agents` for a process flying all, `all_in_one`) with the mission CA.
    On the in-process bus: the operator's (`fly` verifies loopback aborts with it, `abort` signs).
    FAIL when the mission does not have that participant (`agents` its endpoints do not name), when
    missing, unreadable, of another mission or CA, key readable by others, or expired; WARN within
    WARN_DAYS of expiry."""
    from flightstack.comms.certs import OPERATOR, WARN_DAYS, CertError, agent_name, check_participant
    from flightstack.comms.factory import mission_participants

    z = mission.bus.zenoh if mission.bus.kind == "zenoh" else None
    if z is not None and z.security != "mtls":
        return [_row("bus", "security", False, "plaintext Zenoh on real drones (set security: mtls)")]
    names = [OPERATOR]  # in-process: the fly process verifies the operator's signed aborts
    if z is not None:  # Zenoh: this computer's participant
        names = ["agents" if all_in_one or len(drone_ids) != 1 else agent_name(drone_ids[0])]
    directory = mission.resolve(mission.bus.certs)
    rows = []
    for name in names:
        if name not in mission_participants(mission):
            rows.append(_row("bus", f"certificate {name}", False, "bus.zenoh.endpoints do not name it"))
            continue
        try:
            st = check_participant(directory, name, mission.name)
        except CertError as exc:
            rows.append(_row("bus", f"certificate {name}", False, f"{exc} (flightstack certs)"))
            continue
        detail = f"{directory}: valid until {st.not_after:%Y-%m-%d} ({st.days_left:.0f} days)"
        rows.append(_row("bus", f"certificate {name}", st.days_left >= WARN_DAYS, detail, warn=True))
    return rows


def check_gains(mission: Mission) -> CheckRow:
    from flightstack.paper.control import Gains
    from flightstack.paper.gain_analysis import gain_condition, region_samples

    experts: list = []
    if mission.gp.experts_file is not None and mission.resolve(mission.gp.experts_file).is_file():
        from flightstack.learning.training import load_experts

        experts = list(load_experts(mission.resolve(mission.gp.experts_file)).values())
    s = mission.safety
    lo = np.array([s.fence_lo[0], s.fence_lo[1], 0.0])
    hi = np.array([s.fence_hi[0], s.fence_hi[1], 0.0])
    ga = mission.gain_analysis
    cond = gain_condition(
        Gains.make(mission.gains.k_c, mission.gains.k_e, mission.gains.k_s),
        len(mission.drones),
        mission.edge_index_pairs(),
        [d.sees_target for d in mission.drones],
        experts,
        region_samples(lo, hi, min(ga.samples, 500), mission.seed),
        ga.gamma_sq,
        ga.beta,
        ga.eta,
    )
    if experts:
        detail = f"kappa = {cond.kappa:.2f}, lambda_H = {cond.lambda_H:.2f}, L_mu = {cond.L_mu:.2f}"
    else:  # κ = λ_H − (π/2) L_μ λ_P − 1/(2γ²) ≤ its value at L_μ = 0: a necessary condition only
        detail = (
            f"necessary part lambda_H - 1/(2 gamma^2) = {cond.kappa:.2f} (lambda_H = {cond.lambda_H:.2f}); "
            "the full kappa needs trained experts (metrics.json after the run)"
        )
    if cond.kappa <= 0:
        detail += "; Theorem 1 does not apply (the paper's own experiment gains violate it too)"
    return _row("mission", "gain condition", cond.kappa > 0, detail, warn=True)


# ---- devices -------------------------------------------------------------------------------------------
def check_drone(mission: Mission, drone_id: int, with_camera: bool = True) -> list[CheckRow]:
    from flightstack.drivers.lab.hardware import tello_config
    from flightstack.drivers.tello.camera import TelloCamera
    from flightstack.drivers.tello.driver import TelloDriver
    from flightstack.drivers.tello.video_settings import unconfirmed

    assert mission.hardware is not None
    cfg = tello_config(mission, drone_id)
    dev = drone_label(mission, drone_id)
    rows: list[CheckRow] = []
    if cfg.interface is not None:
        row = check_interface(dev, cfg.interface, cfg.host)
        if row.status == "FAIL":
            return [row]  # nothing reaches the drone through it: the one line that says why
        rows.append(row)
    drv = TelloDriver(cfg)
    try:
        try:
            drv.connect()
        except Exception as exc:
            return [*rows, _row(dev, "reachable", False, str(exc))]
        rows.append(_row(dev, "reachable", True, f"SDK mode, state stream at {cfg.host}:{cfg.control_port}"))
        checks = drv.preflight()
        rows += [_row(dev, c.name, c.ok, c.detail, warn=c.warn) for c in checks]
        if not all(c.ok for c in checks if c.name == "firmware"):
            pass  # the firmware row says which SDK 3.0 feature the camera needs: no second line
        elif with_camera and unconfirmed(cfg, drv.video_outcomes):  # its video rows above say why
            rows.append(_row(dev, "camera", False, "not started: a video setting was not confirmed"))
        elif with_camera:
            cal = _calibration(mission, drone_id)
            cam = TelloCamera(
                drv, cfg.command_timeout_s + 2.0, to_picture=None if cal is None else picture_of(cal)
            )
            rows.append(_check_camera(mission, drone_id, dev, cam))
    finally:
        drv.close()
    return rows


def drone_label(mission: Mission, drone_id: int) -> str:
    """A drone's device name in the table: `drone N (IP)`, `drone N (IP via INTERFACE)`."""
    assert mission.hardware is not None
    hw = mission.hardware.drone(drone_id)
    return f"drone {drone_id} ({hw.ip}{'' if hw.interface is None else ' via ' + hw.interface})"


def check_interface(dev: str, interface: str, drone_ip: str) -> CheckRow:
    """The interface a drone is reached through: exists, link up, an address whose subnet holds the
    drone's, no strict reverse-path filter against it (drivers/netif.py)."""
    from flightstack.drivers.netif import describe, interface_problem, interface_state, route_interface

    state = interface_state(interface)
    problem = interface_problem(state, drone_ip, route_interface(drone_ip))
    return _row(dev, f"interface {interface}", problem is None, problem or describe(state))


def check_binding() -> CheckRow:
    """Whether this process may bind sockets to an interface (SO_BINDTODEVICE; drivers/netif.py)."""
    from flightstack.drivers.netif import binding_privilege

    why = binding_privilege()
    detail = why or "SO_BINDTODEVICE permitted (it needs CAP_NET_RAW on Linux before 5.7)"
    return _row("computer", "interface binding", why is None, detail)


def _calibration(mission: Mission, drone_id: int) -> CameraCalibration | None:
    """Drone drone_id's camera calibration, or None when it has none or it cannot be read (check_files
    reports why)."""
    from flightstack.vision.camera_file import CalibrationError, load_calibration

    spec = next(d for d in mission.drones if d.id == drone_id)
    if spec.camera is None or spec.camera.calibration is None:
        return None
    try:
        return load_calibration(mission.resolve(spec.camera.calibration))
    except (CalibrationError, OSError):
        return None


def _check_camera(mission: Mission, drone_id: int, dev: str, cam: TelloCamera) -> CheckRow:
    from flightstack.vision.camera_file import load_calibration

    spec = next(d for d in mission.drones if d.id == drone_id)
    assert mission.hardware is not None and spec.camera is not None and spec.camera.calibration is not None
    timeout = mission.hardware.drone(drone_id).frame_timeout_s
    try:
        cam.start()
        deadline = time.monotonic() + timeout
        frame = None
        while frame is None or frame.image is None:
            if time.monotonic() > deadline:
                return _row(dev, "camera", False, f"no video frame within {timeout:g} s")
            frame = cam.latest()
            time.sleep(0.02)
        h, w = frame.image.shape[:2]
        detail = f"{spec.camera.mount} camera streaming {w}x{h}"
        path = mission.resolve(spec.camera.calibration)
        if path.is_file():
            with contextlib.suppress(Exception):
                cal = load_calibration(path)
                if (cal.width, cal.height) != (w, h):
                    stream = (
                        ""
                        if cal.stream is None
                        else f" (its picture cut from {cal.stream.width}x{cal.stream.height})"
                    )
                    return _row(
                        dev,
                        "camera",
                        False,
                        f"{detail}, but the calibration is {cal.width}x{cal.height}{stream}",
                    )
        return _row(dev, "camera", True, detail)
    except Exception as exc:
        return _row(dev, "camera", False, f"video: {exc}")
    finally:
        with contextlib.suppress(Exception):
            cam.stop()


UP_AXIS_FIX = (
    "Motive streams Y up (its default): set its streaming setting Up Axis to Z Axis (Motive 2: Data "
    "Streaming pane, Advanced Network Settings; Motive 3: Settings > Streaming), then run preflight again"
)
UNKNOWN_BODY_FIX = (
    "define the rigid body in Motive before `fly` starts, or reconnect (model definitions are read once, "
    "at connect)"
)
UNICAST_FIX = (
    "Motive streams unicast (Transmission Type = Unicast), whose frames libmotioncapture 1.1 cannot "
    "receive: set Transmission Type to Multicast"
)
LEVEL_AT_PREFLIGHT_RAD = math.radians(10.0)  # bodies stand level at preflight; more is a Y-up sign
Y_AXIS_UP_COS = math.cos(math.radians(20.0))  # a body y axis this close to Motive's y: yawed about y
BELOW_FLOOR_M = 0.1  # a body this far below the floor (z) is not where z is up


def y_up_signs(
    label: str, position: tuple[float, ...], quat_wxyz: tuple[float, ...], drone: bool, landed_height: float
) -> list[str]:
    """What in one body's newest sample says the stream is Y-up (empty: nothing), for a body standing
    for preflight. position: m in the stream's frame; quat_wxyz: its orientation there.

    Signs: (1) level about Motive's y axis but tilted from z by more than LEVEL_AT_PREFLIGHT_RAD (a level
    body yawed in a Y-up world: its y axis stays vertical, its z axis turns with the yaw); (2) more than
    BELOW_FLOOR_M below the floor z = 0; (3) a drone higher than `landed_height` (m) above the floor: a
    drone stands on the floor for preflight (the drone rows check its own telemetry says so). A level
    Y-up body yawed within 10° of Motive's x axis, standing within [-0.1 m, landed_height] of Motive's
    x-y plane, shows none of them: no frame alone can tell it from a Z-up body."""
    w, x, y, z = quat_wxyz
    n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    w, x, y, z = w / n, x / n, y / n, z / n
    r11 = 1.0 - 2.0 * (x * x + z * z)  # body y axis · Motive's y
    r22 = 1.0 - 2.0 * (x * x + y * y)  # body z axis · Motive's z
    tilt = math.acos(max(-1.0, min(1.0, r22)))
    signs = []
    if tilt > LEVEL_AT_PREFLIGHT_RAD and r11 >= Y_AXIS_UP_COS:
        signs.append(f"{label} is level about y but tilted {math.degrees(tilt):.0f}° from z")
    height = float(position[2])
    if height < -BELOW_FLOOR_M:
        signs.append(f"{label} is {-height:.2f} m below the floor (z)")
    elif drone and height > landed_height:
        signs.append(f"{label} stands {height:.2f} m above the floor (z)")
    return signs


def check_mocap(mission: Mission) -> list[CheckRow]:
    from flightstack.drivers.lab.hardware import body_names, mocap_config
    from flightstack.drivers.mocap import MocapPoseSource

    cfg = mocap_config(mission)
    dev = f"mocap ({cfg.system})"
    src = MocapPoseSource(cfg)
    try:
        try:
            src.start()
        except Exception as exc:
            return [_row(dev, "server", False, str(exc))]
        info = src.server_info
        about = (
            ""
            if info is None
            else (
                f", {info.app} NatNet {'.'.join(map(str, info.natnet_version))}, "
                + (
                    f"multicast {info.group}:{info.data_port}"
                    if info.multicast
                    else f"unicast data port {info.data_port}"
                )
            )
        )
        rows = [_row(dev, "server", True, f"connected ({cfg.settings or 'no settings'}{about})")]
        names = body_names(mission)
        deadline = time.monotonic() + BODY_WAIT_S
        while time.monotonic() < deadline and not all(src.latest(n) for n in names.values()):
            time.sleep(0.02)
        if info is not None and not info.multicast and src.stats()["frames"] == 0:
            return [
                *rows,
                _row(dev, "transmission", False, f"no frame within {BODY_WAIT_S:g} s: {UNICAST_FIX}"),
            ]
        s = mission.safety
        signs = []
        for ours, theirs in names.items():
            sample = src.sample(theirs)
            if sample is not None:
                label = ours if ours == theirs else f"{ours} = {theirs}"
                signs += y_up_signs(label, sample[0], sample[1], ours != "target", s.landed_height)
        if signs:
            return [*rows, _row(dev, "up axis", False, f"{'; '.join(signs)}: {UP_AXIS_FIX}")]
        if src.sample("") is not None:  # libmotioncapture names a body missing from the model definitions ''
            p = src.sample("")[0]  # type: ignore[index]
            where = f"at ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) m"
            rows.append(_row(dev, "bodies", False, f"a body {where} is not in Motive's model definitions: "
                             f"{UNKNOWN_BODY_FIX}"))  # fmt: skip
        for ours, theirs in names.items():
            sp = src.latest(theirs)
            label = ours if ours == theirs else f"{ours} = {theirs}"
            if sp is None:
                tilt, invalid = src.tilt(theirs), src.invalid_run(theirs)
                if invalid:
                    why = (
                        f"streams non-finite poses: its last {invalid} samples were no valid pose (a NaN or "
                        "infinite position or quaternion, or a zero quaternion)"
                    )
                elif tilt is None:
                    why = "never seen"
                elif tilt > cfg.max_tilt_rad:
                    why = f"tilted {math.degrees(tilt):.0f}° (limit {math.degrees(cfg.max_tilt_rad):.0f}°)"
                else:
                    why = "lost (no recent frame)"
                rows.append(_row(dev, f"body {label}", False, why))
                continue
            x, y, z = (float(v) for v in sp.pose.p)
            inside = s.fence_lo[0] <= x <= s.fence_hi[0] and s.fence_lo[1] <= y <= s.fence_hi[1]
            where = f"at ({x:.2f}, {y:.2f}, {z:.2f}) m, {src.rate_hz(theirs):.0f} Hz"
            if not inside:
                box = f"[{s.fence_lo[0]}, {s.fence_hi[0]}]×[{s.fence_lo[1]}, {s.fence_hi[1]}]"
                where += f", OUTSIDE the fence x/y {box}"
            rows.append(_row(dev, f"body {label}", inside, where))
        return rows
    finally:
        src.close()


def check_robot(mission: Mission) -> list[CheckRow]:
    from flightstack.drivers.lab.hardware import scamper_config

    cfg = scamper_config(mission)
    if cfg is None:
        return [_row("robot", "link", True, "not driven by this mission (hardware.target is null)")]
    return robot_rows(cfg)


def robot_rows(cfg: ScamperConfig) -> list[CheckRow]:
    """The robot's HEARTBEAT, its GCS failsafe, its external-navigation sources, its EKF origin (set to
    the configured lab origin and read back: nothing moves, nothing is armed), its GUIDED timeout and its
    kinematics, from its parameters (drivers/scamper/failsafe.py, drivers/scamper/vehicle.py). Every
    FAIL is one line saying what to set on the vehicle."""
    from flightstack.drivers.guardian.launcher import GuardianConfig
    from flightstack.drivers.scamper import failsafe as fs
    from flightstack.drivers.scamper import vehicle as sv
    from flightstack.drivers.scamper.nav import LabOrigin
    from flightstack.drivers.scamper.params import probe_vehicle

    dev = f"robot ({cfg.url})"
    names = (*fs.PARAMETERS, *sv.PARAMETERS)
    try:  # a read never ends early: the servo functions answer only as far as the vehicle has them
        probe = probe_vehicle(cfg, names)
    except Exception as exc:
        return [_row(dev, "heartbeat", False, str(exc))]
    hb, values = probe.heartbeat, probe.params.values
    ours = {"flightstack": cfg.source_system, "guardian": GuardianConfig().robot_source[0]}
    verdict = fs.judge_gcs_failsafe(values, ours)
    rows = [
        _row(dev, "heartbeat", True, f"mode {hb.custom_mode}, {'ARMED' if hb.armed else 'disarmed'}"),
        CheckRow(dev, "GCS failsafe", verdict.status, verdict.detail),
    ]
    for check, v in (
        ("external navigation", sv.judge_external_nav(values)),
        ("GUIDED timeout", sv.judge_guided_timeout(values, cfg.stream_hz)),
        ("kinematics", sv.judge_kinematics(values)),
    ):
        rows.append(CheckRow(dev, check, v.status, v.detail))
    origin = LabOrigin(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_alt_m)
    rows.append(_origin_row(dev, probe.origin, origin))
    return rows


def _origin_row(dev: str, probe: OriginProbe, origin: LabOrigin) -> CheckRow:
    if probe.reported is None:
        why = (
            f"no EKF origin: no GPS_GLOBAL_ORIGIN after {probe.sends} SET_GPS_GLOBAL_ORIGIN in "
            f"{probe.elapsed_s:.1f} s; the vehicle drops every set-point without one (check that it takes "
            "MAVLink from this computer and that EK3_SRC1_POSXY is 6)"
        )
        return _row(dev, "EKF origin", False, why)
    lat, lon, alt = probe.reported
    where = f"lat {lat / 1e7:.7f}, lon {lon / 1e7:.7f}, alt {alt / 1000:.2f} m"
    if not origin.matches(lat, lon, alt):
        where += " (not the configured lab origin: the vehicle had one already; it keeps it until reboot)"
    return _row(dev, "EKF origin", True, where)


# ---- all of it ---------------------------------------------------------------------------------------
def run_preflight(
    mission: Mission, deadline_s: float = 9.0, with_camera: bool = True, drone_ids: list[int] | None = None
) -> list[CheckRow]:
    """Every check of the module docstring; devices in parallel; returns within ~deadline_s (s).

    `drone_ids`: the drones of this computer (access-point mode: one each); None = every drone."""
    if mission.hardware is None:
        raise ValueError(
            f"preflight checks hardware; mission {mission.name!r} uses backend {mission.backend!r}"
        )
    ids = [d.id for d in mission.drones] if drone_ids is None else list(drone_ids)
    unknown = sorted(set(ids) - {d.id for d in mission.drones})
    if unknown:
        raise ValueError(f"preflight --id: no drone {unknown} in mission {mission.name!r}")
    shared = mission.hardware.shared_by(ids)
    if shared is not None:
        return [_row("mission", "topology", False, shared)]
    # the tick's compiled math, before any device thread starts: a cold compile holds the GIL for a while
    warm_rows = [check_kernels()]
    if any(mission.hardware.drone(i).interface is not None for i in ids):
        warm_rows.append(check_binding())
    jobs: dict[str, Callable[[], list[CheckRow]]] = {}
    for d in mission.drones:
        if d.id not in ids:
            continue
        jobs[drone_label(mission, d.id)] = (
            lambda i=d.id: check_drone(mission, i, with_camera)  # type: ignore[misc]
        )
    jobs[f"mocap ({mission.hardware.mocap.system})"] = lambda: check_mocap(mission)
    jobs["robot"] = lambda: check_robot(mission)
    results: dict[str, list[CheckRow]] = {}

    def run(name: str, fn: Callable[[], list[CheckRow]]) -> None:
        try:
            results[name] = fn()
        except Exception as exc:  # a bug in a check must not hide the other devices
            results[name] = [_row(name, "check", False, f"{type(exc).__name__}: {exc}")]

    threads = [
        threading.Thread(target=run, args=(n, f), name=f"preflight-{n}", daemon=True) for n, f in jobs.items()
    ]
    t_end = time.monotonic() + deadline_s
    for th in threads:
        th.start()
    rows = [*warm_rows, *check_files(mission), *check_certs(mission, ids, all_in_one=drone_ids is None)]
    try:
        rows.append(check_gains(mission))
    except Exception as exc:
        rows.append(_row("mission", "gain condition", False, f"could not evaluate: {exc}", warn=True))
    for th in threads:
        th.join(max(0.0, t_end - time.monotonic()))
    for name, th in zip(jobs, threads, strict=True):
        if th.is_alive() or name not in results:
            rows.append(
                _row(name, "answer", False, f"no answer within the {deadline_s:g} s preflight deadline")
            )
        else:
            rows.extend(results[name])
    return rows


def format_table(rows: list[CheckRow]) -> str:
    w_dev = max(len("device"), *(len(r.device) for r in rows))
    w_chk = max(len("check"), *(len(r.check) for r in rows))
    lines = [f"{'device':{w_dev}s}  {'check':{w_chk}s}  status  detail", "-" * (w_dev + w_chk + 30)]
    lines += [f"{r.device:{w_dev}s}  {r.check:{w_chk}s}  {r.status:6s}  {r.detail}" for r in rows]
    n_fail = sum(r.status == "FAIL" for r in rows)
    n_warn = sum(r.status == "WARN" for r in rows)
    verdict = "ALL PASS" if not n_fail and not n_warn else f"{n_fail} FAIL, {n_warn} WARN"
    lines.append(f"preflight: {verdict}" + (" — do not fly" if n_fail else ""))
    return "\n".join(lines)
