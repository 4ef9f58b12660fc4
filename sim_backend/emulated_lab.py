"""The emulated lab: Tello emulators, a NatNet (OptiTrack) server and a MAVLink rover on loopback, and a
mission pointing at them (`EmulatedLab`, a context manager). The `emulated-lab` rig flies it (the flight
starts it: flightstack.runtime.flight), and so do the fault table's lab rows (flightstack/faults/lab_flight.py
flies and judges them).

What the drones did is judged at the emulators: every Tello emulator keeps `commands`, `rc_history`,
`phase_log` and `replies_sent` with their receive/send times; `lab.write_log(path)` saves them, and the
helpers below (`command_times`, `rc_times`, `phase_times`, `max_gap`) measure reaction times on them.

The emulators ship in the package (flightstack.sim_backend.emulators) and are imported lazily
when a lab starts. Without the optional packages av, motioncapture and pymavlink, starting a lab raises
`LabUnavailableError` saying what is missing (the row then reports a crash).

Cameras: with an experiment (`flightstack run EXP --rig emulated-lab`) every drone's camera renders what it
sees of the flight through its mount's calibration, at 30 fps, in a child process per drone
(`emulators/tello/video_process.py`; the lab publishes the rover's pose to them every 10 ms); the fault
table keeps a fixed view of the markers (`marker_image`), rendered in the emulators' own threads.

Addresses (all 127.0.0.0/8): the Tellos own 127.0.0.6 and 127.0.0.7 (`config.rig.emulated_tello_ip`), each
on a free port, so two labs can fly at once (station mode: both send their state
to one free port of 127.0.0.1); NatNet and the rover use 127.0.0.1 with OS-assigned ports; the operator
channel of the in-process bus is a free UDP port of 127.0.0.1 (`bus.operator_port`). Or, with
`tello_netns` (`TelloPlace`), each Tello in a network namespace of the caller's as an access-point Tello
is: 192.168.10.1, the real ports 8889/8890/11111, reached through its own interface (the mission's
`interface:`); the fixed marker view only.

Units: every recorded time is time.monotonic() seconds (Linux CLOCK_MONOTONIC, shared by every process of
the machine, so the event times of a child `fly` process compare with the emulators' records directly);
durations in seconds; positions in metres in the motion-capture world (z up) unless marked cm.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace, TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from flightstack.config.rig import MISSION_CONFIGS, emulated_tello_ip
from flightstack.hal import TARGET_BODY, DroneIdentity, FrameTruth, register_frame_truth
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.recorded import LAND_OK_S, LAND_TOUCHDOWN_S, TAKEOFF_OK_S

if TYPE_CHECKING:
    from flightstack.config.links import LinkSpec, LinksSpec

LAB_IDS = (1, 2)
"""The drones of the fault table's lab."""
DRONE_STARTS: dict[int, tuple[tuple[float, float, float], float]] = {
    1: ((-0.5, -0.5, 0.05), 0.0),
    2: ((-0.5, 0.2, 0.05), 0.3),
}
"""Where each drone stands before takeoff: position (m, mocap world) and yaw (rad, counter-clockwise);
drones of other ids stand 0.7 m apart along y from (-0.5, -0.5)."""
ROVER_START = (-0.5, -0.5)
"""The rover's start in the mocap world (m): the square's corner."""
LEVEL = (1.0, 0.0, 0.0, 0.0)
"""Quaternion (w, x, y, z) of a level body facing world x."""
MISSIONS = MISSION_CONFIGS
CALIBRATION = MISSIONS / "cameras" / "tello_down_sim.yaml"
VIDEO_SIZE = (320, 240)
"""Frame size (px) of the fixed marker view (that of CALIBRATION)."""
VIDEO_FPS = 15.0
"""Rate of the fixed marker view (frames/s)."""
LIVE_VIDEO_FPS = 30.0
"""Rate of the cameras that render the flight (frames/s): the Tello's; each at its calibration's size."""
TAKEOFF_S = FAST_TAKEOFF_S
"""The emulated Tellos' takeoff (s) on perfect links: a fast climb, not the recorded 8.7 s (the emulator's
default, sim_backend/emulators/tello/recorded.py), which would add 8.4 s to every takeoff of every lab
flight. With the Tello's own links (`--links tello`) the emulated Tellos take off and land as the
recording did: the takeoff's `ok` at TAKEOFF_OK_S, the touchdown LAND_TOUCHDOWN_S and the land's `ok`
LAND_OK_S after the command."""
TAKEOFF_HOVER_S = 1.0
"""With a late state link or an impaired network, each emulated Tello hovers this long at height before
its takeoff `ok` (s),
as a real one does for seconds: the driver trusts an `ok` only when telemetry shows the drone at height,
and a fast climb's `ok` would otherwise arrive before the late state that shows it."""
MOCAP_RATE_HZ = 100.0
"""The emulated motion capture's frame rate when the mocap link names none (Hz)."""
TARGET_PERIOD_S = 0.01
"""How often the lab publishes the rover's pose to the camera processes (s)."""
NETWORK_LOG = "network_log.json"
"""The emulated lab's log (EmulatedLab.log, with every link's counters) written into the lab's directory
after a flight on an impaired network or with late links."""
TRUTH_PERIOD_S = 0.05
"""How often the lab samples each drone's true position for the fence judgement (s)."""
MOCAP_NOISE_M = 5e-6
"""σ of the emulated motion capture's position noise per axis (m): the recorded Motive session
(../shared/data/peers/natnet/, one still body, 518 frames) moves 4–8 µm frame to frame. A real capture
never repeats a sample (flightstack/safety/pose_check.py relies on it); without noise the emulated drones
did, hovering in their takeoff."""
MOCAP_NOISE_RAD = 6e-5
"""σ of the emulated motion capture's yaw noise (rad): the same recording's quaternion moves about 3e-5 a
component frame to frame."""


TELLO_PORTS = {"control_port": 8889, "state_port": 8890, "video_port": 11111}
"""A real Tello's ports (SDK 2.0/3.0 guides): the emulators in network namespaces use them."""


@dataclass(frozen=True)
class TelloPlace:
    """Where one emulated Tello lives when not on loopback: inside network namespace `netns` (made by the
    caller, `ip netns add`) at `ip`, its client at `client_ip` on the link into it, whose end on the
    client's side is `interface` (the mission names it: hardware.drones[].interface)."""

    netns: str
    interface: str
    ip: str = "192.168.10.1"
    client_ip: str = "192.168.10.2"


class LabUnavailableError(RuntimeError):
    """The emulated lab cannot start here: not a source checkout, or an optional package is missing."""


# ---- lazy imports of the emulators -------------------------------------------------------------------------
def load_emulators() -> SimpleNamespace:
    """The emulator classes (TelloEmulator, NatNetEmulator, MavlinkRoverEmulator);
    LabUnavailableError naming the optional package that is missing."""
    try:
        import av  # noqa: F401  # the emulators encode H.264 video
        import motioncapture  # noqa: F401  # the driver's NatNet client
        import pymavlink  # noqa: F401  # the rover's MAVLink
    except ImportError as exc:
        raise LabUnavailableError(
            "the emulated lab needs the optional packages av, motioncapture and pymavlink (pip install -e "
            f"'.[tello,mocap,scamper]'): {exc}"
        ) from exc
    from flightstack.sim_backend.emulators.natnet import NatNetEmulator
    from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator
    from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
    from flightstack.sim_backend.emulators.tello.video_process import SharedTarget, VideoProcess

    return SimpleNamespace(
        TelloEmulator=TelloEmulator,
        NatNetEmulator=NatNetEmulator,
        MavlinkRoverEmulator=MavlinkRoverEmulator,
        SharedTarget=SharedTarget,
        VideoProcess=VideoProcess,
    )


def _yaw_quaternion(theta: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a yaw of theta rad about z."""
    return (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))


def marker_image() -> np.ndarray:
    """What the downward camera of a drone hovering 0.9 m above the target sees: the four markers of the
    mission (rendered once with the calibration's lens; the emulators send it as every frame)."""
    from flightstack.config.mission import CAMERA_MOUNTS
    from flightstack.paper.geometry import Pose, rot_z
    from flightstack.sim_backend.scene.render import RenderOptions, render_markers
    from flightstack.vision.camera_file import load_calibration

    cal = load_calibration(CALIBRATION)
    p0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])
    g_i0 = Pose.make([0.05, -0.03, -0.9], 0.3)
    r_ic = CAMERA_MOUNTS["down"]
    centres = (p0 @ rot_z(g_i0.theta).T + g_i0.p) @ r_ic
    normals = np.tile(r_ic.T @ np.array([0.0, 0.0, 1.0]), (4, 1))
    img, _, _ = render_markers(cal, centres, normals, RenderOptions(marker_radius_m=0.03))
    return np.ascontiguousarray(img)


# ---- the lab -----------------------------------------------------------------------------------------------
@contextmanager
def running_lab(mission: Any, lab_dir: Path) -> Iterator[Any]:
    """The `emulated-lab` rig: an EmulatedLab for `mission` (a flightstack Mission), logging in lab_dir;
    yields the mission re-pointed at the running devices. Every device stops when the block ends."""
    from flightstack.config.mission import mission_to_dict
    from flightstack.sim_backend.build import initial_drone_pose

    doc = mission_to_dict(mission)
    doc["start_emulators"] = False  # the written mission flies the running emulators
    starts = {}  # on the ground below where the simulated lab starts them: the same experiment
    for k, d in enumerate(mission.drones):
        above = initial_drone_pose(mission, k)
        starts[d.id] = ((float(above.p[0]), float(above.p[1]), DRONE_STARTS[1][0][2]), float(above.theta))
    with EmulatedLab(
        lab_dir,
        experiment=doc,
        network=mission.links.network,
        seed=mission.seed,
        links=mission.links,
        starts=starts,
    ) as running:
        try:
            yield running.mission()
        finally:
            if running.radios or running.links:  # what the links and the network did, per device
                running.write_log(Path(lab_dir) / NETWORK_LOG)


class EmulatedLab:
    """Two Tello emulators, NatNet and a rover on loopback, and `mission_path` flying them (a context
    manager: `with EmulatedLab(dir) as lab:`; every thread and child process is stopped on exit).

    workdir: where the mission and its calibration are written. duration_s: pursuit (s). tello: extra
    TelloEmulator keyword arguments per drone id (e.g. {2: {"land_s": 2.0}}). mission_edit: called with
    the mission dict (YAML) before it is written. `mocap_offset[i]` (m, world x/y/z) is added to drone i's
    motion-capture position from the moment it is set (a drone displaced as motion capture sees it).
    starts: drone id -> where it stands before takeoff ((x, y, z) m and yaw rad, mocap world); default
    DRONE_STARTS (`running_lab` passes the simulated lab's starts, so both labs fly the same experiment).

    experiment: a resolved mission document on the emulated-lab rig (`flightstack run EXP --rig
    emulated-lab`): its drones, modes and camera mounts are flown as they are, and every camera renders
    what it sees of the flight (live cameras, below). Without it (the fault table): the paper experiment,
    mode `none`, both cameras downward, both streaming a fixed view of the markers (15 fps, 320×240,
    rendered in the emulators' threads) that the fault rows were judged with.

    live_cameras (default: with an experiment): each drone's camera is its calibration (intrinsics,
    distortion, size) on its mount, rendered from the drone's true pose and the rover's, at 30 fps, in a
    child process per drone (tello_video_process.VideoProcess); `cameras[i]` is drone i's process handle.

    network: the impairment profile of every emulated device's links (flightstack.netem.PROFILES; the
    mission's `links.network`, `--network`), seeded by `seed` (the mission's seed) per device and link; its
    blackout windows count from the lab's start. "clean": the emulators' sockets are not wrapped at all.
    What each link did: `network_counts()`, also in `log()`. The live cameras' video leaves from their
    child processes through the same video link model, seeded alike, with the drone's blackout windows and
    epoch (tello_video_process.VideoPath); its counters are the drone's "video" link.

    links: the rig's `links:` (flightstack.config.links.LinksSpec; the mission's, `--links`), applied in
    the emulators where the data is produced, before the radio (emulators/device_links.py; which links and
    how: `emulated_links`): each drone's `video` (frames leave late, taken at its rate: the cameras' fps),
    `state` (at its rate, each datagram late), `rc` (every command acted on late), `mocap` (frames late,
    at its rate) and `robot` (MAVLink commands acted on late); seeded by `seed` per device and link as the
    simulated lab seeds them. Profile `perfect` changes nothing here. What each link did: `link_counts()`.

    tello_netns: drone id -> TelloPlace: that Tello lives in a network namespace of the caller's, at its
    own address with the real ports (TELLO_PORTS), reached through the place's interface (the written
    mission names it, topology access_point); needs the fixed marker view (live_cameras False).
    """

    def __init__(
        self,
        workdir: Path,
        *,
        duration_s: float = 5.0,
        tello: dict[int, dict[str, Any]] | None = None,
        mission_edit: Callable[[dict[str, Any]], None] | None = None,
        experiment: dict[str, Any] | None = None,
        live_cameras: bool | None = None,
        network: str = "clean",
        seed: int = 0,
        links: LinksSpec | None = None,
        starts: dict[int, tuple[tuple[float, float, float], float]] | None = None,
        tello_netns: dict[int, TelloPlace] | None = None,
    ) -> None:
        from flightstack.config.links import LinksSpec
        from flightstack.netem import profile
        from flightstack.sim_backend.emulators.device_links import emulated_links

        self.network = profile(network)
        self.seed = int(seed)
        self.link_specs = emulated_links(links if links is not None else LinksSpec())
        """Link name -> the spec the emulators apply (perfect links left out)."""
        self.links: dict[str, Any] = {}
        """Device name ("tello<i>", "natnet", "rover") -> its DeviceLinks (none when no link applies)."""
        self.radios: dict[str, Any] = {}
        """Device name ("tello<i>", "natnet", "rover") -> its DeviceRadio (none on a clean network)."""
        self.workdir = Path(workdir).resolve()  # the mission written there names its files absolutely
        self._experiment = experiment
        ids = [int(d["id"]) for d in experiment["drones"]] if experiment is not None else list(LAB_IDS)
        self.places = dict(tello_netns or {})
        self.ips = {i: emulated_tello_ip(k) for k, i in enumerate(ids)}
        self.ips.update({i: p.ip for i, p in self.places.items()})
        self.starts = starts or {
            i: DRONE_STARTS.get(i, ((-0.5, -0.5 + 0.7 * k, 0.05), 0.0)) for k, i in enumerate(ids)
        }
        self.duration_s = float(duration_s)
        self._tello_kw = tello or {}
        self._mission_edit = mission_edit
        self.mocap_offset: dict[int, np.ndarray] = {i: np.zeros(3) for i in self.ips}
        self.tellos: dict[int, Any] = {}
        self.natnet: Any = None
        self.rover: Any = None
        self.mission_path: Path = self.workdir / "mission.yaml"
        self.operator_port = 0
        self.t_start = math.nan
        self.truth: list[tuple[float, int, tuple[float, float, float]]] = []
        """(time.monotonic(), drone id, true position (m, world)) about every TRUTH_PERIOD_S per drone:
        where the emulator flies the drone, without `mocap_offset`."""
        self._truth_t: dict[int, float] = {}
        self._mocap_noise = np.random.default_rng(0)  # MOCAP_NOISE_M: one stream, read by the NatNet thread
        self.live_cameras = experiment is not None if live_cameras is None else bool(live_cameras)
        if self.places and self.live_cameras:
            raise ValueError("Tellos in network namespaces (tello_netns) need the fixed marker view")
        self.cameras: dict[int, Any] = {}
        self._target: Any = None
        self._publisher: threading.Thread | None = None
        self._stop = threading.Event()

    # ---- lifecycle -------------------------------------------------------------------------------------
    def __enter__(self) -> EmulatedLab:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
        """Start every emulator and write the mission (LabUnavailableError outside a checkout)."""
        emu = load_emulators()
        self.workdir.mkdir(parents=True, exist_ok=True)
        state_port = TELLO_PORTS["state_port"] if self.places else free_udp_port()
        self._make_radios()
        self._make_links()
        video = self.link_spec("video")
        if self.live_cameras:
            self._target = emu.SharedTarget()
            fps = video.rate_hz or LIVE_VIDEO_FPS
            for i, ip in self.ips.items():
                port = free_udp_port()
                cam = emu.VideoProcess(
                    self.camera_spec(i),
                    ip,
                    ("127.0.0.1", port),
                    self._target,
                    fps=fps,
                    path=self._video_path(i),
                )
                kw: dict[str, Any] = {
                    "state_port": state_port,
                    "video_port": port,
                    "video_size": cam.size,
                    "fps": fps,
                    **self._tello_links(i),
                }
                kw.update(self._tello_kw.get(i, {}))
                self.tellos[i] = emu.TelloEmulator(ip, **kw)
                self.tellos[i].use_remote_video(cam)
                self.cameras[i] = cam
                register_frame_truth(ip, port, _truth_of(cam))
        else:
            image = marker_image()
            empty = np.full_like(image, 96)  # a grey floor without markers
            for i, ip in self.ips.items():
                frame = image if self._sees_markers(i) else empty
                kw = {
                    "state_port": state_port,
                    "video_port": free_udp_port(),
                    "frame_source": lambda t, e, img=frame: img,
                    "video_size": VIDEO_SIZE,
                    "fps": video.rate_hz or VIDEO_FPS,
                    **self._tello_links(i),
                }
                place = self.places.get(i)
                if place is not None:  # a real Tello's address and ports, in the caller's namespace
                    kw.update(
                        port=TELLO_PORTS["control_port"],
                        video_port=TELLO_PORTS["video_port"],
                        client_ip=place.client_ip,
                        netns=place.netns,
                    )
                kw.update(self._tello_kw.get(i, {}))
                self.tellos[i] = emu.TelloEmulator(ip, **kw)
        bodies = {self.body(i): i for i in self.ips}
        self.natnet = emu.NatNetEmulator(
            {
                **{
                    name: (self.starts[i][0], _yaw_quaternion(self.starts[i][1]))
                    for name, i in bodies.items()
                },
                "scamper": ((*ROVER_START, 0.0), LEVEL),
            },
            rate_hz=self.link_spec("mocap").rate_hz or MOCAP_RATE_HZ,
            radio=self.radios.get("natnet"),
            links=self.links.get("natnet"),
        )
        self.rover = emu.MavlinkRoverEmulator(
            heartbeat_hz=5.0,
            radio=self.radios.get("rover"),
            links=self.links.get("rover"),
        )
        self.natnet.set_pose_provider("scamper", self._rover_pose)
        for name, i in bodies.items():
            self.natnet.set_pose_provider(name, lambda i=i: self._drone_pose(i))
        if self._target is not None:
            self._publish_target()
            for cam in self.cameras.values():  # the children import in parallel
                cam.start()
            for cam in self.cameras.values():
                cam.wait_ready()
            self._publisher = threading.Thread(
                target=self._target_loop, name="emulated-lab-target", daemon=True
            )
            self._publisher.start()
        for e in self.tellos.values():
            e.start()
        self.natnet.start()
        self.operator_port = free_udp_port()
        self.mission_path = self.write_mission()
        self.t_start = time.monotonic()

    def _make_radios(self) -> None:
        """One DeviceRadio per device when the network impairs anything (one epoch: now)."""
        if self.network.clean:
            return
        from flightstack.sim_backend.emulators.radio import DeviceRadio

        epoch = time.monotonic()
        tello_links = {"command": "rc", "reply": "rc", "state": "state", "video": "video"}
        for i in self.ips:
            name = DroneIdentity(i).label
            self.radios[name] = DeviceRadio(self.network, self.seed, name, tello_links, epoch)
        self.radios["natnet"] = DeviceRadio(self.network, self.seed, "natnet", {"frames": "mocap"}, epoch)
        self.radios["rover"] = DeviceRadio(
            self.network, self.seed, "rover", {"uplink": "robot", "downlink": "robot"}, epoch
        )

    def link_spec(self, name: str) -> Any:
        """The spec of link `name` the emulators apply (config.links.NONE when none)."""
        from flightstack.config.links import NONE

        return self.link_specs.get(name, NONE)

    def _make_links(self) -> None:
        """One DeviceLinks per device some link applies to, on its radio's delay line when it has one."""
        from flightstack.sim_backend.emulators.device_links import DeviceLinks

        def make(name: str, device: int, kinds: tuple[str, ...]) -> None:
            specs = {k: v for k, v in self.link_specs.items() if k in kinds}
            if specs:
                radio = self.radios.get(name)
                line = None if radio is None else radio.delay_line
                self.links[name] = DeviceLinks(specs, self.seed, device, name, line)

        for i in self.ips:
            make(DroneIdentity(i).label, i, ("rc", "state", "video"))
        make("natnet", 0, ("mocap",))
        make("rover", 0, ("robot",))

    def _tello_links(self, i: int) -> dict[str, Any]:
        """TelloEmulator keyword arguments of drone i's radio, links and state rate."""
        kw: dict[str, Any] = {"takeoff_s": TAKEOFF_S}
        name = DroneIdentity(i).label
        if name in self.radios:
            kw["radio"] = self.radios[name]
        if name in self.links:
            kw["links"] = self.links[name]
        state = self.link_spec("state")
        if state.rate_hz is not None:
            kw["state_hz"] = state.rate_hz
        if not state.perfect:  # the Tello's own links (`--links tello`): its recorded takeoff and landing
            kw.update(takeoff_s=TAKEOFF_OK_S, land_s=LAND_TOUCHDOWN_S, land_ok_s=LAND_OK_S)
        elif not self.network.clean:  # late or lost telemetry: the takeoff's `ok` must not beat the
            # climb's state (the radio delays and loses state datagrams too)
            kw["takeoff_s"] = TAKEOFF_S + TAKEOFF_HOVER_S
            kw["takeoff_hover_s"] = TAKEOFF_HOVER_S
        return kw

    def _video_path(self, i: int) -> Any:
        """How drone i's live camera frames leave it: the video link, then its radio (VideoPath)."""
        from flightstack.sim_backend.emulators.tello.video_process import VideoPath

        video = self.link_specs.get("video")
        radio = self.radios.get(DroneIdentity(i).label)
        return VideoPath(
            seed=self.seed,
            drone=i,
            link=None if video is None else video.model_dump(),
            network=None if radio is None else self.network,
            epoch=0.0 if radio is None else radio.epoch,
        )

    def network_counts(self) -> dict[str, dict[str, dict[str, float]]]:
        """Per device and link, what its radio did (DeviceRadio.counts); empty on a clean network. A live
        camera's "video" row is its child process's (the parent's own video link is then unused)."""
        out = {name: r.counts() for name, r in self.radios.items()}
        for i, cam in self.cameras.items():
            if DroneIdentity(i).label in out:
                out[DroneIdentity(i).label]["video"] = cam.network_counts()
        return out

    def link_counts(self) -> dict[str, dict[str, dict[str, float]]]:
        """Per device and applied link, what the rig's link did (device_links.LinkStage.row); a live
        camera's "video" row is its child process's."""
        out = {name: links.counts() for name, links in self.links.items()}
        if "video" in self.link_specs:
            for i, cam in self.cameras.items():
                out.setdefault(DroneIdentity(i).label, {})["video"] = cam.link_counts()
        return out

    def body(self, i: int) -> str:
        """Drone i's rigid-body name in the emulated motion capture."""
        return f"tello_{'ab'[i - 1]}" if self._experiment is None and i in (1, 2) else f"tello_{i}"

    def _sees_markers(self, i: int) -> bool:
        if self._experiment is None:
            return True
        d = next(d for d in self._experiment["drones"] if int(d["id"]) == i)
        return bool(d.get("sees_target", True)) and (d.get("camera") or {}).get("mount", "down") == "down"

    def _drone_doc(self, i: int) -> dict[str, Any]:
        assert self._experiment is not None
        return dict(next(d for d in self._experiment["drones"] if int(d["id"]) == i))

    def calibration_path(self, i: int) -> Path:
        """Drone i's camera calibration: the experiment's (the rig's for its mount), else CALIBRATION."""
        if self._experiment is None or not self.live_cameras:
            return CALIBRATION
        return Path(self._drone_doc(i)["camera"]["calibration"])

    def camera_spec(self, i: int) -> Any:
        """What drone i's live camera sees: its calibration on its mount, the experiment's markers (the
        render's marker radius; no pixel noise: the H.264 encoding makes its own), the render's floor
        (`sim.render.floor`), its start pose."""
        from flightstack.config.mission import CAMERA_MOUNTS
        from flightstack.sim_backend.emulators.tello.view import CameraSpec
        from flightstack.vision.camera_file import load_calibration

        doc = self._experiment or {}
        cam = self._drone_doc(i).get("camera") or {} if self._experiment is not None else {}
        mount = str(cam.get("mount", "down"))
        p0 = (doc.get("target") or {}).get("feature_points") or [
            [0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]
        ]  # fmt: skip
        render = (doc.get("sim") or {}).get("render") or {}
        radius = render.get("marker_radius_m", 0.03)
        (x, y, z), yaw = self.starts[i]
        return CameraSpec(
            calibration=load_calibration(self.calibration_path(i)).to_dict(),
            R_ic=tuple(tuple(float(v) for v in row) for row in CAMERA_MOUNTS[mount]),
            t_ic=tuple(float(v) for v in cam.get("offset", (0.0, 0.0, 0.0))),
            feature_points=tuple(tuple(float(v) for v in q) for q in p0),
            start=(float(x), float(y), float(z), float(yaw)),
            marker_radius_m=float(radius),
            seed=int(doc.get("seed", 0)) * 100 + i,
            floor=str(render.get("floor", "plain")),
        )

    def close(self) -> None:
        """Stop every emulator and camera process (bounded joins); idempotent."""
        self._stop.set()
        if self._publisher is not None:
            self._publisher.join(timeout=1.0)
        for e in self.tellos.values():
            e.close()
        for i, cam in self.cameras.items():
            cam.close()
            register_frame_truth(self.ips[i], cam.dest[1], None)
        if self.natnet is not None:
            self.natnet.close()
        if self.rover is not None:
            self.rover.close()
        for r in self.radios.values():  # (idempotent; a device that never started does not own its radio)
            r.close()
        for links in self.links.values():
            links.close()

    # ---- the live cameras' target ----------------------------------------------------------------------
    def _publish_target(self) -> None:
        g, q = self._rover_pose()
        self._target.write(float(g[0]), float(g[1]), 2.0 * math.atan2(q[3], q[0]))

    def _target_loop(self) -> None:
        """Publish the rover's pose to the camera processes every TARGET_PERIOD_S until close."""
        while not self._stop.wait(TARGET_PERIOD_S):
            with suppress(Exception):  # a rover not yet up: the cameras keep its last pose
                self._publish_target()

    # ---- motion capture --------------------------------------------------------------------------------
    def _rover_pose(self) -> tuple[Any, tuple[float, float, float, float]]:
        """The rover's mocap pose: its start is ROVER_START, θ = 0 (the rover integrates FLU from there)."""
        from flightstack.paper.geometry import Pose, compose

        g = compose(Pose.make([*ROVER_START, 0.0], 0.0), self.rover.pose_flu())
        return self._noisy(g.p, g.theta)

    def _noisy(self, p: Any, theta: float) -> tuple[Any, tuple[float, float, float, float]]:
        """A body's true pose (p m, θ rad) as motion capture gives it: with Motive's noise (MOCAP_NOISE_M)."""
        noise = self._mocap_noise.normal(0.0, 1.0, 4)
        return np.asarray(p) + MOCAP_NOISE_M * noise[:3], _yaw_quaternion(theta + MOCAP_NOISE_RAD * noise[3])

    def _drone_pose(self, i: int) -> tuple[Any, tuple[float, float, float, float]]:
        """Drone i's mocap pose: the emulator flies (x forward, y right, z up) cm, yaw clockwise deg, from
        its start; the world is FLU (y left, yaw counter-clockwise); plus `mocap_offset[i]`."""
        from flightstack.sim_backend.emulators.tello.view import drone_world_pose

        emu = self.tellos[i]
        (x0, y0, z0), yaw0 = self.starts[i]
        g = drone_world_pose((x0, y0, z0, yaw0), emu.position_cm, emu.yaw_deg)
        now = time.monotonic()
        if now - self._truth_t.get(i, -math.inf) >= TRUTH_PERIOD_S:
            self._truth_t[i] = now
            self.truth.append((now, i, (float(g.p[0]), float(g.p[1]), float(g.p[2]))))
        return self._noisy(np.asarray(g.p) + self.mocap_offset[i], g.theta)

    # ---- the mission -----------------------------------------------------------------------------------
    def write_mission(self) -> Path:
        """The experiment on the emulated-lab rig, its `hardware:` pointing at the running emulators, the
        operator channel on a free port; returns the resolved mission file written. Without an experiment
        (the fault table): the paper experiment, mode `none`, `duration_s` of pursuit, cameras downward."""
        from flightstack.config.rig import emulated_hardware, resolved_document
        from flightstack.vision.camera_file import load_calibration

        cal_files = {}
        for i in self.tellos:
            cal = load_calibration(self.calibration_path(i)).to_dict()
            cal["rms_px"] = 0.3  # a measured calibration (preflight fails on the never-measured templates)
            cal["device"] = "emulated tello"
            name = "cal.yaml" if self.calibration_path(i) == CALIBRATION else f"cal_{i}.yaml"
            cal_files[i] = self.workdir / name
            cal_files[i].write_text(yaml.safe_dump(cal, sort_keys=False))
        if self._experiment is not None:
            m = dict(self._experiment)
        else:
            m = resolved_document("paper_experiment", "emulated-lab")
            m["name"] = f"emulated_lab_{self.workdir.name}"[:60]
            m["duration_s"] = self.duration_s
            m["compare_modes"] = ["none"]
            for d in m["drones"]:
                d["camera"]["mount"] = "down"
        m["start_emulators"] = False  # it flies the emulators running here (`run` must not start its own)
        if m.get("compensation"):  # the emulated Tellos' latencies written out: hardware needs them given
            from flightstack.config.compensation import EMULATED_TELLO_RESPONSE_S, written_out
            from flightstack.config.links import LinksSpec

            rc = LinksSpec.model_validate(m.get("links") or {}).emulated("rc")
            m["compensation"] = written_out(m["compensation"], rc, EMULATED_TELLO_RESPONSE_S)
        m["bus"] = {**m.get("bus", {}), "kind": "inproc", "operator_port": self.operator_port}
        for d in m["drones"]:
            d["camera"]["calibration"] = str(cal_files[int(d["id"])])
        first = next(iter(self.tellos.values()))
        ports = {
            "state_port": first.state_port,
            "drones": {
                i: {"control_port": e.address[1], "video_port": e.video_port} for i, e in self.tellos.items()
            },
            "natnet": self.natnet.settings(),
            "rover_url": self.rover.url,
        }
        hw = emulated_hardware(list(self.tellos), ports)
        hw["max_frame_age_s"] = max_frame_age_s(self.link_specs.get("video"))
        hw["mocap"]["bodies"] = {DroneIdentity(i).name: self.body(i) for i in self.tellos} | {
            TARGET_BODY: "scamper"
        }
        if self.places:  # access-point Tellos, each through its own interface
            hw["topology"] = "access_point"
            for d in hw["drones"]:
                place = self.places[int(d["id"])]
                d.update(ip=place.ip, interface=place.interface)
        m["hardware"] = hw
        if self._mission_edit is not None:
            self._mission_edit(m)
        path = self.workdir / "mission.yaml"
        path.write_text(yaml.safe_dump(m, sort_keys=False))
        certs = path.parent / "certs"  # the mission's default bus.certs: real drones need them
        if not (certs / "ca.pem").exists():
            from flightstack.comms.certs import create_mission_certs, participants

            zenoh = (m.get("bus") or {}).get("zenoh")
            ids = [int(d["id"]) for d in m["drones"]]
            create_mission_certs(str(m["name"]), participants(ids, zenoh and zenoh["endpoints"]), certs)
        return path

    def mission(self) -> Any:
        """The mission as flightstack loads it."""
        from flightstack.config.mission import load_mission

        return load_mission(self.mission_path)

    # ---- observing the emulators -----------------------------------------------------------------------
    def wait_for_pursuit(self, timeout_s: float = 40.0, n_rc: int = 10) -> float | None:
        """Wait until every Tello emulator is flying and has received `n_rc` rc commands while flying (the
        control loop runs); the time.monotonic() when it did, or None after timeout_s (s)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(
                e.phase == "flying" and len(rc_times(e, after=_phase_start(e, "flying"))) >= n_rc
                for e in self.tellos.values()
            ):
                return time.monotonic()
            time.sleep(0.01)
        return None

    def log(self) -> dict[str, Any]:
        """Every emulator's records, times in s since the lab started (JSON-ready)."""
        t0 = self.t_start

        def rel(t: float) -> float:
            return round(t - t0, 4)

        out: dict[str, Any] = {"t0_monotonic": t0, "network": self.network.name}
        if self.link_specs:
            out["links"] = {k: v.model_dump() for k, v in self.link_specs.items()}
            out["link_counts"] = self.link_counts()
        if self.radios:
            out["network_counts"] = self.network_counts()
            out["blackouts"] = {
                n: [(rel(a), rel(b)) for a, b in r.blackouts[:10]] for n, r in self.radios.items()
            }
        for i, e in self.tellos.items():
            out[DroneIdentity(i).label] = {
                "ip": e.ip,
                "commands": [(rel(t), c) for t, c in list(e.commands)],
                "phase_log": [(rel(t), p) for t, p in list(e.phase_log)],
                "replies_sent": [(rel(t), r, k) for t, r, k in list(e.replies_sent)],
                "refused": [(rel(t), ph, c, r) for t, ph, c, r in list(e.refused)],
                "errors": list(e.errors),
                "landed_by_timeout": e.landed_by_timeout,
                "state_packets_sent": e.state_packets_sent,
                "video_frames_sent": e.video_frames_sent,
                "video_capture_to_send_s_p50": _p50([ts - tc for _, tc, ts in list(e.video_capture_log)]),
            }
        if self.rover is not None:
            out["rover"] = {"armed": bool(self.rover.armed), "setpoints": len(self.rover.setpoint_records())}
        return out

    def write_log(self, path: Path) -> None:
        """Save `log()` as JSON (best effort: a failure to write is not the row's finding)."""
        with suppress(OSError):
            Path(path).write_text(json.dumps(self.log(), indent=1, default=str) + "\n")


# ---- measurements on emulator records ----------------------------------------------------------------------
def _p50(values: list[float]) -> float | None:
    """The median of values (s, rounded to 0.1 ms), None when empty."""
    return round(float(np.median(values)), 4) if values else None


def _phase_start(emu: Any, phase: str) -> float:
    """The latest time the emulator entered `phase` (s), -inf if never."""
    times = [t for t, p in list(emu.phase_log) if p == phase]
    return times[-1] if times else -math.inf


def command_times(emu: Any, text: str, after: float = -math.inf, before: float = math.inf) -> list[float]:
    """Receive times (s) of every datagram equal to `text` at the emulator within (after, before]."""
    return [t for t, c in list(emu.commands) if c == text and after < t <= before]


def rc_times(
    emu: Any,
    after: float = -math.inf,
    before: float = math.inf,
    value: tuple[int, int, int, int] | None = None,
    nonzero: bool = False,
) -> list[float]:
    """Receive times (s) of the rc commands within (after, before]: all, those equal to `value`, or (nonzero)
    those with any stick off centre."""
    out = []
    for t, rc in list(emu.rc_history):
        if not after < t <= before:
            continue
        if value is not None and tuple(rc) != tuple(value):
            continue
        if nonzero and not any(rc):
            continue
        out.append(t)
    return out


def phase_times(emu: Any, phase: str, after: float = -math.inf) -> list[float]:
    """Times (s) at which the emulator entered `phase` ("landed", "takeoff", "flying", "landing") after
    `after`."""
    return [t for t, p in list(emu.phase_log) if p == phase and t > after]


def first(times: Iterable[float]) -> float | None:
    """The earliest of `times`, None if empty."""
    ts = sorted(times)
    return ts[0] if ts else None


def max_gap(times: Iterable[float], t0: float, t1: float) -> float:
    """The longest interval (s) within [t0, t1] without any of `times` (t1 - t0 when there is none)."""
    ts = sorted(t for t in times if t0 <= t <= t1)
    edges = [t0, *ts, t1]
    return max(b - a for a, b in itertools.pairwise(edges))


def ms(seconds: float | None) -> float | None:
    """Seconds as milliseconds rounded to 0.1 ms (None stays None, for faults.json)."""
    return None if seconds is None or not math.isfinite(seconds) else round(1e3 * seconds, 1)


TRUTH_INDEX_STEP = 8
"""Largest step (frames) between the bar-coded indices of two frames decoded one after the other that
`_truth_of` believes: more is a bar code concealment smeared, not frames lost on the way."""


def max_frame_age_s(video: LinkSpec | None) -> float:
    """The emulated lab's `hardware.max_frame_age_s` (s) for the video link its emulators apply (None: a
    perfect one): the lab's default (0.5 s, chosen on loopback, where a frame is decoded within tens of ms
    of its capture) after the link's longest delay (latency_s + jitter_s), as docs/links.md asks a real lab
    to set it above its measured frame age. With the `tello` links (0.3 s + U(0, 0.1 s)) the default alone
    left 0.1 s, three frames: on `lab-wifi` a short burst of loss made 7-19 ticks per 30 s mode "stale"
    whose frames were 0.5-0.7 s old and, carried over their delay by the compensation, still usable."""
    from flightstack.config.hardware import HardwareSpec

    delay = 0.0 if video is None else video.latency_s + video.jitter_s
    return float(HardwareSpec.model_fields["max_frame_age_s"].default) + delay


def _truth_of(cam: Any) -> FrameTruth:
    """How to know the truth of a live camera's decoded frame: its bar-coded frame index (tello_frames)
    looked up in the camera's capture records (VideoProcess.truth_px). None when it cannot be trusted:
    the code's check row disagrees with its index (tello_frames.read_checked_frame_index; a code below
    the picture has one), the index is not there, or it does not follow the previous frame's by 1 to
    TRUTH_INDEX_STEP (a bar code concealed after a loss reads as an older frame's index, or as noise: the
    truth would then be another frame's, and a detection would be judged against a place the target
    never was). In the EDU's downward layout the code is below the picture (tello_view.index_area), in
    the noise that fills most of the stream's datagrams."""
    from flightstack.sim_backend.emulators.tello.frames import read_checked_frame_index, read_frame_index
    from flightstack.sim_backend.emulators.tello.view import index_area, index_is_checked
    from flightstack.vision.camera_file import calibration_from_dict

    cal = calibration_from_dict(cam.spec.calibration, "emulated camera")
    last: list[int] = []  # the previous frame's index, once there is one

    def truth(img: np.ndarray) -> np.ndarray | None:
        area = index_area(cal, img)
        checked = index_is_checked(area, img)
        index = read_checked_frame_index(area) if checked else read_frame_index(area)
        if index is None:  # the check row disagrees: a smeared code, whose frame is unknown
            return None
        follows = not last or 0 < index - last[0] <= TRUTH_INDEX_STEP
        if last and index - last[0] < -TRUTH_INDEX_STEP:  # a new stream counts from 0 again
            follows = index < TRUTH_INDEX_STEP
        last[:] = [index]
        return cam.truth_px.get(index) if follows else None

    return truth


__all__ = [
    "DRONE_STARTS",
    "LAB_IDS",
    "TELLO_PORTS",
    "TRUTH_PERIOD_S",
    "EmulatedLab",
    "LabUnavailableError",
    "TelloPlace",
    "command_times",
    "first",
    "load_emulators",
    "marker_image",
    "max_gap",
    "ms",
    "phase_times",
    "rc_times",
]
