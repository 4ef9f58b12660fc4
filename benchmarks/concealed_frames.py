"""What the fiducial detector makes of frames decoded through lost datagrams, against the true corners.

    python benchmarks/concealed_frames.py [--seconds 30] [--seeds 0,1,2] [--losses 0.002,0.02]

Offline and deterministic (no sockets, no clock): drone 1's grey downward camera of paper_experiment on the
emulated lab (mission_configs/cameras/tello_down_edu_sim.yaml, the EDU's 320 × 720 layout, the tiled floor)
renders a pursuit: the target drives a square (0.15 m/s, turning in place at 0.5 rad/s at each corner, as
paper_experiment's robot does), the drone follows 0.85 m above it through a first-order lag (0.6 s) with a
hover's wobble. Each frame is stamped with its index's checked bar code below the picture, encoded as the
Tello emulator encodes (libx264, 3 Mbit/s, the recorded 67-frame keyframe interval), split into 1460-byte
datagrams, and datagrams are lost by the simple Gilbert chain the `tello` video link uses
(flightstack.netem.LinkProfile.bursty: `loss`, bursts of 3). The receiver's own path decodes them
(FFmpeg's h264 with err_detect aggressive, drivers/tello/video_check.StreamCheck tagging `damaged`), the
driver cuts the picture (vision/picture.py) and `detect_fiducial` runs on every frame whose bar code reads.

Per loss rate and seed, for frames tagged clean and tagged damaged: how many had the fiducial found, how many
found were more than 1, 3 and 10 px from the true corners (max over the four), and of the damaged frames in
which it was not found, how many still show the marker's outline intact (its sides, measured from the true
corners, give them back within 1 px: `refine_by_edges`) against those in which concealment broke an edge.
Of the damaged frames' detections: how many the detection gate mends for their shape (flightstack.vision.gate;
the true corners stand for the prediction, which on a level camera differs from them by a similarity only;
σ_shape 0) and how many are then more than 3 and 10 px off (the JSON also counts the boards off their shape
that are kept as detected, and how far each kind was before and after).
Prints a Markdown table and a JSON summary (docs/links.md, "What the detector makes of concealed frames").
"""

from __future__ import annotations

import argparse
import json
import math
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.config.rig import MISSION_CONFIGS
from flightstack.drivers.tello.video_decode import StreamDecoder
from flightstack.netem import LinkProfile
from flightstack.paper.geometry import Pose
from flightstack.sim_backend.emulators.tello.frames import read_checked_frame_index, stamp_frame_index
from flightstack.sim_backend.emulators.tello.recorded import KEYFRAME_INTERVAL_FRAMES
from flightstack.sim_backend.emulators.tello.video import frame_datagrams, make_encoder
from flightstack.sim_backend.emulators.tello.view import CameraSpec, CameraView, index_area
from flightstack.vision.camera_file import CameraCalibration, load_calibration
from flightstack.vision.fiducial import detect_fiducial, distorted_pixels, marker_cells, refine_by_edges
from flightstack.vision.gate import (
    DEFAULT_NOISE_PX,
    GateSpec,
    mend_board,
    shape_gate_px,
    similarity_basis,
    similarity_fit,
)
from flightstack.vision.picture import picture

CALIBRATION = MISSION_CONFIGS / "cameras" / "tello_down_edu_sim.yaml"
P0 = ((0.1, 0.1, 0.15), (-0.1, 0.1, 0.15), (-0.1, -0.1, 0.15), (0.1, -0.1, 0.15))
FPS = 30.0
SPEED_MPS, TURN_RADPS, SIDE_M = 0.15, 0.5, 1.0
"""The target's square: its speed along a side, its turn rate in place at a corner, the side."""
FOLLOW_S, HEIGHT_M, WOBBLE_M = 0.6, 0.85, 0.01
"""The drone's lag behind the target (s), its height (m), the amplitude of its hover wobble (m)."""
BURST = 3.0
"""Mean length of a burst of lost datagrams (the `tello` video link's datagram_burst)."""


def target_pose(t: float) -> Pose:
    """The target at t (s): a side at SPEED_MPS, then a quarter turn in place at TURN_RADPS, repeated."""
    side_s, turn_s = SIDE_M / SPEED_MPS, (math.pi / 2) / TURN_RADPS
    laps, s = divmod(t, side_s + turn_s)
    n = int(laps) % 4  # whole sides driven, from the square's start corner
    x = sum(SIDE_M * math.cos(k * math.pi / 2) for k in range(n))
    y = sum(SIDE_M * math.sin(k * math.pi / 2) for k in range(n))
    yaw = n * math.pi / 2
    if s < side_s:
        x, y = x + SPEED_MPS * s * math.cos(yaw), y + SPEED_MPS * s * math.sin(yaw)
    else:
        x, y = x + SIDE_M * math.cos(yaw), y + SIDE_M * math.sin(yaw)
        yaw += TURN_RADPS * (s - side_s)
    return Pose.make([x, y, 0.0], yaw)


def drone_poses(seconds: float, rng: np.random.Generator) -> list[Pose]:
    """The drone over the target at each frame: its position a first-order lag (FOLLOW_S) of the target's,
    its yaw the target's lagged the same way, plus a wobble of WOBBLE_M (a random phase per axis)."""
    dt = 1.0 / FPS
    g0 = target_pose(0.0)
    p, yaw = np.array([g0.p[0], g0.p[1]]), float(g0.theta)
    phase = rng.uniform(0, 2 * math.pi, 3)
    out = []
    for k in range(int(seconds * FPS)):
        g = target_pose(k * dt)
        a = dt / FOLLOW_S
        p = p + a * (np.asarray(g.p[:2]) - p)
        yaw += a * math.remainder(float(g.theta) - yaw, 2 * math.pi)
        w = WOBBLE_M * np.sin(2 * math.pi * 0.3 * k * dt + phase)
        out.append(Pose.make([p[0] + w[0], p[1] + w[1], HEIGHT_M + w[2]], yaw))
    return out


def outline_intact(grey: np.ndarray, corners_aruco: np.ndarray, cal: CameraCalibration) -> bool:
    """Whether the marker's four sides, measured from the true corners (4, 2 px, ArUco order), give back
    corners within 1 px of them (`refine_by_edges`): False when concealment broke an edge."""
    refined = refine_by_edges(grey, corners_aruco, cal, int(marker_cells(cal.fiducial).shape[0]))  # type: ignore[arg-type]
    return refined is not None and float(np.linalg.norm(refined - corners_aruco, axis=1).max()) <= 1.0


def run(loss: float, seed: int, seconds: float) -> dict[str, int]:
    """One stream (module docstring): the counts by tag."""
    cal = load_calibration(CALIBRATION)
    spec = CameraSpec(
        calibration=cal.to_dict(), R_ic=tuple(tuple(float(v) for v in r) for r in CAMERA_MOUNTS["down"]),
        t_ic=(0.0, 0.0, 0.0), feature_points=P0, start=(0.0, 0.0, 0.0, 0.0), seed=seed, floor="tiles",
    )  # fmt: skip
    view = CameraView(spec)
    rng = np.random.default_rng(seed)
    poses = drone_poses(seconds, rng)
    link = LinkProfile.bursty(loss, BURST)
    encoder = make_encoder(spec.stream_size(True), FPS, KEYFRAME_INTERVAL_FRAMES)
    counts: Counter[str] = Counter()
    decoder = StreamDecoder(Counter(), lambda exc: None)  # a rejected frame: the next keyframe resynchronises
    truth: dict[int, np.ndarray] = {}
    bad = False
    order = list(cal.fiducial.corners)  # type: ignore[union-attr]
    for k, g_wi in enumerate(poses):
        g_w0 = target_pose(k / FPS)
        frame = view.frame(g_wi, g_w0, True)
        truth[k] = view.true_pixels(g_wi, g_w0)
        stamp_frame_index(index_area(cal, frame), k, checked=True)
        for datagram in frame_datagrams(encoder, frame, k):
            bad = rng.random() < (1.0 - link.loss_r if bad else link.loss_p)
            counts["datagrams"] += 1
            if bad:
                counts["datagrams_lost"] += 1
                continue
            for img, damaged, _ in decoder.feed(datagram):
                index = read_checked_frame_index(index_area(cal, img))
                tag = "damaged" if damaged else "clean"
                if index is None or index not in truth:
                    counts[f"{tag}_unknown"] += 1
                    continue
                grey = picture(img, cal)
                counts[f"{tag}_frames"] += 1
                det = detect_fiducial(grey, cal)
                if det.pixels is None:
                    counts[f"{tag}_missed"] += 1
                    if tag == "damaged":
                        quad = np.empty((4, 2))
                        quad[order] = truth[index]
                        edge = "intact" if outline_intact(grey, quad, cal) else "broken"
                        counts[f"damaged_missed_outline_{edge}"] += 1
                    continue
                err = float(np.linalg.norm(det.pixels - truth[index], axis=1).max())
                counts[f"{tag}_found"] += 1
                for px in (1, 3, 10):
                    counts[f"{tag}_over_{px}px"] += err > px
                if tag == "damaged":
                    off_shape, mended = mended_pixels(np.asarray(det.normalized), truth[index], cal)
                    used = det.pixels if mended is None else mended
                    err_used = float(np.linalg.norm(used - truth[index], axis=1).max())
                    kind = "mended" if mended is not None else "off_shape_kept" if off_shape else None
                    if kind is not None:
                        counts[f"damaged_{kind}"] += 1
                        counts[f"damaged_{kind}_over_1px_before"] += err > 1
                        counts[f"damaged_{kind}_over_3px_before"] += err > 3
                        counts[f"damaged_{kind}_over_3px_after"] += err_used > 3
                    for px in (3, 10):
                        counts[f"damaged_as_gated_over_{px}px"] += err_used > px
    return dict(counts)


def mended_pixels(
    normalized: np.ndarray, truth_px: np.ndarray, cal: CameraCalibration
) -> tuple[bool, np.ndarray | None]:
    """(whether the detection's shape is beyond the gate, its corners (4, 2) (distorted px) as the
    detection gate mends them: None when it does not), the true corners standing for the prediction."""
    K, dist = np.asarray(cal.camera_matrix, dtype=float), np.asarray(cal.dist_coeffs, dtype=float)
    fx = float(K[0, 0])
    p = cv2.undistortPoints(np.asarray(truth_px, dtype=float).reshape(-1, 1, 2), K, dist).reshape(-1, 2) * fx
    d = normalized.reshape(-1, 2) * fx - p
    M = similarity_basis(p)
    _, shape2 = similarity_fit(d, M)
    spec = GateSpec(noise_px=cal.rms_px or DEFAULT_NOISE_PX)
    if float(np.sqrt(shape2.max())) <= shape_gate_px(4, spec.sigmas, spec.noise_px):
        return False, None
    one = mend_board(d, M, shape_gate_px(3, spec.sigmas, spec.noise_px))
    return True, None if one is None else distorted_pixels((p + (M @ one[0]).reshape(-1, 2)) / fx, cal)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--losses", default="0.002,0.02")
    ap.add_argument("--json", type=Path, default=None, help="write the summary here too")
    a = ap.parse_args()
    results = []
    print(
        "| datagrams lost | seed | frames clean / damaged | found in clean | clean > 1 / 3 / 10 px | found "
        "in damaged | damaged > 1 / 3 / 10 px | damaged, not found: outline intact / broken | "
        "damaged: mended; then > 3 / 10 px |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for loss in (float(v) for v in a.losses.split(",")):
        for seed in (int(v) for v in a.seeds.split(",")):
            c = Counter(run(loss, seed, a.seconds))
            results.append({"loss": loss, "seed": seed, **c})
            nc, nd = c["clean_frames"], c["damaged_frames"]
            print(
                f"| {100 * c['datagrams_lost'] / max(1, c['datagrams']):.2f} % | {seed} | {nc} / {nd} | "
                f"{100 * c['clean_found'] / max(1, nc):.1f} % | {c['clean_over_1px']} / "
                f"{c['clean_over_3px']} / {c['clean_over_10px']} | "
                f"{100 * c['damaged_found'] / max(1, nd):.1f} % | "
                f"{c['damaged_over_1px']} / {c['damaged_over_3px']} / {c['damaged_over_10px']} | "
                f"{c['damaged_missed_outline_intact']} / {c['damaged_missed_outline_broken']} | "
                f"{c['damaged_mended']}; {c['damaged_as_gated_over_3px']} / "
                f"{c['damaged_as_gated_over_10px']} |",
                flush=True,
            )
    print(json.dumps(results))
    if a.json is not None:
        a.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
