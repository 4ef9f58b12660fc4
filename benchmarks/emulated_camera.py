"""CPU per emulated camera stream: render + encode (the camera's child process) and decode (the driver's
receiver in this process), at 30 fps, for each simulated calibration (docs/performance.md).

    python benchmarks/emulated_camera.py [--seconds 10] [--floor plain|tiles]

A Tello emulator on 127.0.0.13 flies nothing: it hovers 0.85 m above the target after `takeoff`, so every
frame shows the four markers. CPU is measured as CPU seconds per wall second (1.0 = one core): the child's
from /proc/<pid>/stat (utime + stime), this process's from time.process_time() (the decoder thread plus
the emulator's light feeding threads). Prints one line per calibration and a JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import time
from pathlib import Path

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.config.rig import MISSION_CONFIGS
from flightstack.drivers.tello.camera import VideoReceiver
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.net import wait_until
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from flightstack.sim_backend.emulators.tello.video_process import SharedTarget, VideoProcess
from flightstack.sim_backend.emulators.tello.view import CameraSpec
from flightstack.vision.camera_file import load_calibration

IP = "127.0.0.13"
P0 = ((0.1, 0.1, 0.15), (-0.1, 0.1, 0.15), (-0.1, -0.1, 0.15), (0.1, -0.1, 0.15))


def cpu_s(pid: int) -> float:
    """utime + stime (s) of process pid."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(cal_file: str, seconds: float, floor: str = "plain") -> dict[str, float]:
    """CPU (cores) of one stream of `cal_file` over `seconds` of streaming, the floor `floor`; a calibration
    with a stream layout (the EDU's downward camera) streams with `downvision 1`."""
    target = SharedTarget()
    target.write(0.0, 0.0, 0.0)
    port = free_udp_port()
    spec = CameraSpec(
        calibration=load_calibration(MISSION_CONFIGS / "cameras" / cal_file).to_dict(),
        R_ic=tuple(tuple(r) for r in CAMERA_MOUNTS["down"].tolist()),
        t_ic=(0.0, 0.0, 0.0),
        feature_points=P0,
        start=(0.0, 0.0, 0.0, 0.0),
        floor=floor,
    )
    down = spec.calibration.get("stream") is not None
    cam = VideoProcess(spec, IP, ("127.0.0.1", port), target, fps=30.0)
    emu = TelloEmulator(IP, state_port=free_udp_port(), video_port=port, video_size=cam.size, fps=30.0)
    emu.use_remote_video(cam)
    rx = VideoReceiver(port, "127.0.0.1")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        cam.start()
        cam.wait_ready()
        emu.start()
        for text in ("command", *(("downvision 1",) if down else ()), "takeoff", "streamon"):
            sock.sendto(text.encode(), emu.address)
        assert rx.wait_first_frame(10.0), emu.errors
        wait_until(lambda: emu.phase == "flying", 5.0)
        time.sleep(1.0)
        pid = cam.process.pid
        assert pid is not None
        t0, c0, p0, f0 = time.monotonic(), cpu_s(pid), time.process_time(), rx.counts["frames"]
        time.sleep(seconds)
        wall = time.monotonic() - t0
        child = (cpu_s(pid) - c0) / wall
        parent = (time.process_time() - p0) / wall
        fps = (rx.counts["frames"] - f0) / wall
    finally:
        sock.close()
        rx.close()
        emu.close()
        cam.close()
    w, h = spec.stream_size(down)
    return {"width": w, "height": h, "fps_decoded": fps, "render_encode": child, "decode": parent}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--floor", choices=("plain", "tiles"), default="plain")
    args = ap.parse_args()
    out = {}
    for cal in ("tello_down_sim.yaml", "tello_down_edu_sim.yaml", "tello_front_sim.yaml"):
        r = measure(cal, args.seconds, args.floor)
        out[cal] = r
        print(
            f"{r['width']}x{r['height']} at {r['fps_decoded']:.1f} fps decoded: render+encode "
            f"{100 * r['render_encode']:.1f} % of a core (child), decode {100 * r['decode']:.1f} % (parent), "
            f"total {100 * (r['render_encode'] + r['decode']):.1f} %"
        )
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
