"""The frame tree and the static scene of a run's Foxglove topics (flightstack.recording.mcap_writer), from
the mission alone.

**Frames.** `world` is the display frame: right-handed, z up, what a 3-D panel assumes. `sigma_w` is the
recording's world frame Σw, in which every pose of the recording is given, a child of `world`:

- on the lab rigs (`lab-sim`, `emulated-lab`, `lab`) Σw is the motion-capture frame, z up, and
  `world` → `sigma_w` is the identity;
- on the ideal rig (backend `sim_ideal`, the paper's simulation) Σw's z is the cameras' optical axis, which
  looks down at the target (paper_sim: drones at z = −1.5 m, the target at z = 0), and `world` → `sigma_w`
  is a half turn about x (x kept, y and z reversed), so the drones appear above the target.

The bodies `<mode>/target`, `<mode>/drone<i>` and `<mode>/drone<i>/estimate` are children of `sigma_w`
(translation p, rotation θ about Σw's z); a drone with a camera has `<mode>/drone<i>/camera` (x right, y
down, z the optical axis: foxglove.CompressedImage's convention) as its child, by the mount extrinsic
p_i = R_ic p_c + t_ic (flightstack.config.mission.CAMERA_MOUNTS, offset in m).

**Scene** (`Scene.update`): the safety fence (rigs with safety on): the soft box [fence_lo, fence_hi] in
amber and the hard box (grown by hard_margin) in red, in `sigma_w`; the target's markers (its feature
points, in `<mode>/target`, frame-locked, so they move with it), numbered in the order of f.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from foxglove.messages import (
    Color,
    FrameTransform,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

WORLD_FRAME = "world"
"""The display frame: right-handed, z up (the root of the frame tree)."""
SIGMA_W_FRAME = "sigma_w"
"""The recording's world frame Σw, a child of WORLD_FRAME (module docstring)."""
HALF_TURN_X = (1.0, 0.0, 0.0, 0.0)
"""Quaternion (x, y, z, w) of a half turn about x: `world` → `sigma_w` on a rig whose Σw looks down
(RigFacts.world_z_down)."""
IDENTITY = (0.0, 0.0, 0.0, 1.0)
"""Quaternion (x, y, z, w) of no rotation."""
MARKER_DIAMETER_M = 0.04
"""Diameter of the sphere drawn at each marker (m)."""
FENCE_LINE_M = 0.01
"""Thickness of the fence's edges (m)."""
_SOFT = Color(r=1.0, g=0.65, b=0.0, a=0.8)
_HARD = Color(r=0.9, g=0.1, b=0.1, a=0.8)
_MARKER = Color(r=0.1, g=0.8, b=0.9, a=1.0)
_LABEL = Color(r=1.0, g=1.0, b=1.0, a=1.0)
_BOX_EDGES = ((0, 1), (1, 3), (3, 2), (2, 0), (4, 5), (5, 7), (7, 6), (6, 4), (0, 4), (1, 5), (2, 6), (3, 7))


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a rotation matrix R (3, 3), w ≥ 0."""
    R = np.asarray(R, dtype=float).reshape(3, 3)
    w = math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return (x / n, y / n, z / n, w / n)


def stamp(ns: int) -> Timestamp:
    """A foxglove Timestamp of a log time (ns)."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Timestamp(sec, nsec)


def _pose(p: Sequence[float] = (0.0, 0.0, 0.0), q: Sequence[float] = IDENTITY) -> Pose:
    return Pose(
        position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def _box(lo: np.ndarray, hi: np.ndarray, color: Color) -> LinePrimitive:
    """The 12 edges of the axis-aligned box [lo, hi] (m) as a line list."""
    corners = [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    points = [
        Point3(x=float(c[0]), y=float(c[1]), z=float(c[2]))
        for a, b in _BOX_EDGES
        for c in (corners[a], corners[b])
    ]
    return LinePrimitive(
        type=LinePrimitiveLineType.LineList,
        pose=_pose(),
        thickness=FENCE_LINE_M,
        scale_invariant=False,
        points=points,
        color=color,
    )


@dataclass(frozen=True)
class Scene:
    """What the Foxglove topics need of the mission (module docstring). `Scene()`: no mission known (a run
    directory without mission_resolved.yaml): Σw taken as z up, no fence, no markers, no cameras."""

    z_down: bool = False
    """Σw's z looks down (the ideal rig): `world` → `sigma_w` is HALF_TURN_X."""
    fence: tuple[np.ndarray, np.ndarray, float] | None = None
    """(fence_lo (3,), fence_hi (3,), hard_margin) in Σw (m); None: safety off, no fence drawn."""
    markers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """The target's feature points (m, 3) in its own frame (m)."""
    cameras: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Drone id → its camera's mount (R_ic (3, 3), t_ic (3,) m) in the drone's frame; drones with a
    `camera:` only."""

    @classmethod
    def of(cls, mission: Mission) -> Scene:
        """The scene of `mission` (its backend, safety fence, target markers and camera mounts)."""
        s = mission.safety
        fence = None
        if s.enabled:
            fence = (
                np.array(s.fence_lo, dtype=float),
                np.array(s.fence_hi, dtype=float),
                float(s.hard_margin),
            )
        cameras = {}
        for k, d in enumerate(mission.drones):
            if d.camera is not None:
                cam = mission.camera_model(k)
                cameras[d.id] = (np.asarray(cam.R_ic, dtype=float), np.asarray(cam.t_ic, dtype=float))
        return cls(
            z_down=mission.rig_type.world_z_down,
            fence=fence,
            markers=np.array(mission.target.feature_points, dtype=float).reshape(-1, 3),
            cameras=cameras,
        )

    def root(self, ts: Timestamp) -> FrameTransform:
        """`world` → `sigma_w` at `ts`."""
        q = HALF_TURN_X if self.z_down else IDENTITY
        return FrameTransform(
            timestamp=ts,
            parent_frame_id=WORLD_FRAME,
            child_frame_id=SIGMA_W_FRAME,
            translation=Vector3(x=0.0, y=0.0, z=0.0),
            rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    def camera_transforms(self, mode: str, ids: Sequence[int], ts: Timestamp) -> list[FrameTransform]:
        """`<mode>/drone<i>` → `<mode>/drone<i>/camera` of each drone of `ids` with a camera."""
        out = []
        for i in ids:
            if i not in self.cameras:
                continue
            R, t = self.cameras[i]
            q = quaternion(R)
            out.append(
                FrameTransform(
                    timestamp=ts,
                    parent_frame_id=drone_frame(mode, i),
                    child_frame_id=camera_frame(mode, i),
                    translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                    rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
                )
            )
        return out

    def update(self, mode: str, ts: Timestamp) -> SceneUpdate:
        """The scene of `mode` at `ts`: entity `fence` (when safety is on) and `markers` (when the target
        has any); each replaces the one before it on the topic."""
        entities = []
        if self.fence is not None:
            lo, hi, margin = self.fence
            entities.append(
                SceneEntity(
                    timestamp=ts,
                    frame_id=SIGMA_W_FRAME,
                    id="fence",
                    frame_locked=False,
                    lines=[_box(lo, hi, _SOFT), _box(lo - margin, hi + margin, _HARD)],
                )
            )
        if len(self.markers):
            d = MARKER_DIAMETER_M
            spheres = [
                SpherePrimitive(pose=_pose(p), size=Vector3(x=d, y=d, z=d), color=_MARKER)
                for p in self.markers
            ]
            texts = [
                TextPrimitive(
                    pose=_pose(p + np.array([0.0, 0.0, d])),
                    billboard=True,
                    font_size=14.0,
                    scale_invariant=True,
                    color=_LABEL,
                    text=str(k + 1),
                )
                for k, p in enumerate(self.markers)
            ]
            entities.append(
                SceneEntity(
                    timestamp=ts,
                    frame_id=target_frame(mode),
                    id="markers",
                    frame_locked=True,
                    spheres=spheres,
                    texts=texts,
                )
            )
        return SceneUpdate(entities=entities)


def target_frame(mode: str) -> str:
    """The target's frame g_w0 of `mode`."""
    return f"{mode}/target"


def drone_frame(mode: str, i: int) -> str:
    """Drone i's frame g_wi of `mode`."""
    return f"{mode}/drone{i}"


def estimate_frame(mode: str, i: int) -> str:
    """Drone i's estimate ḡ_w,i of the target's pose, of `mode`."""
    return f"{mode}/drone{i}/estimate"


def camera_frame(mode: str, i: int) -> str:
    """Drone i's camera frame of `mode` (x right, y down, z the optical axis)."""
    return f"{mode}/drone{i}/camera"


__all__ = [
    "HALF_TURN_X",
    "SIGMA_W_FRAME",
    "WORLD_FRAME",
    "Scene",
    "camera_frame",
    "drone_frame",
    "estimate_frame",
    "quaternion",
    "stamp",
    "target_frame",
]
