"""Tests of flightstack.drivers.mocap: quaternion reduction against scipy, and the threaded pose source.

The pose source is exercised with an injected fake `motioncapture` object (deterministic, 200 Hz) and, when
the `motioncapture` package is installed, with its real `mock` backend.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from flightstack.drivers.mocap import MocapConfig, MocapError, MocapPoseSource, quaternion_to_planar
from flightstack.hal import PoseSource
from tests.conftest import Bound


def _wxyz(rot: Rotation) -> tuple[float, float, float, float]:
    x, y, z, w = rot.as_quat()  # scipy is scalar-last
    return float(w), float(x), float(y), float(z)


# ---- quaternion_to_planar ----------------------------------------------------------------------------------
@pytest.mark.parametrize("yaw", [0.0, 0.3, -1.2, 2.9, -3.1, math.pi])
def test_pure_yaw(yaw: float) -> None:
    pose, tilt = quaternion_to_planar(np.array([1, 2, 3], np.float32), *_wxyz(Rotation.from_euler("z", yaw)))
    assert math.isclose(math.cos(pose.theta), math.cos(yaw), abs_tol=1e-9)
    assert math.isclose(math.sin(pose.theta), math.sin(yaw), abs_tol=1e-9)
    assert tilt == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(pose.p, [1, 2, 3])
    assert pose.p.dtype == np.float64


@pytest.mark.parametrize("axis", ["x", "y"])
@pytest.mark.parametrize("angle", [0.1, -0.35, 1.0, -2.5])
def test_pure_roll_pitch_tilt(axis: str, angle: float) -> None:
    _, tilt = quaternion_to_planar(np.zeros(3), *_wxyz(Rotation.from_euler(axis, angle)))
    assert tilt == pytest.approx(abs(angle), abs=1e-9)


def test_invalid_quaternion() -> None:
    with pytest.raises(ValueError):
        quaternion_to_planar(np.zeros(3), 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        quaternion_to_planar(np.zeros(3), math.nan, 0.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        quaternion_to_planar(np.array([0.0, math.inf, 0.0]), 1.0, 0.0, 0.0, 0.0)


unit = st.floats(-1.0, 1.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(q=st.tuples(unit, unit, unit, unit), scale=st.floats(0.2, 5.0), sign=st.sampled_from([1.0, -1.0]))
def test_random_rotations_match_scipy(q: tuple[float, ...], scale: float, sign: float) -> None:
    qa = np.array(q)
    assume(np.linalg.norm(qa) > 1e-2)
    rot = Rotation.from_quat(qa[[1, 2, 3, 0]])  # (w,x,y,z) -> scipy (x,y,z,w), normalised by scipy
    w, x, y, z = (sign * scale * qa).tolist()  # q and -q, and any scale, are the same rotation
    pose, tilt = quaternion_to_planar([0.5, -1.0, 2.0], w, x, y, z)
    R = rot.as_matrix()
    assert tilt == pytest.approx(math.acos(np.clip(R[2, 2], -1.0, 1.0)), abs=1e-6)
    if tilt < 1.3:  # far from the Z-Y-X gimbal lock (|pitch| <= tilt)
        yaw = rot.as_euler("ZYX")[0]
        assert abs(math.remainder(pose.theta - yaw, 2 * math.pi)) < 1e-6


# ---- fake motioncapture ------------------------------------------------------------------------------------
def _body(p: tuple[float, float, float], rot: Rotation) -> SimpleNamespace:
    w, x, y, z = _wxyz(rot)
    return SimpleNamespace(position=np.array(p, np.float32), rotation=SimpleNamespace(w=w, x=x, y=y, z=z))


class FakeMocap:
    """motioncapture-like object publishing a mutable body dict at 1/period Hz (deadline-paced)."""

    def __init__(self, period: float = 0.005) -> None:
        self.period = period
        self.bodies: dict[str, SimpleNamespace] = {}
        self.block = threading.Event()  # while set, waitForNextFrame blocks until release is set
        self.release = threading.Event()
        self._next = time.monotonic()
        self._lock = threading.Lock()

    def waitForNextFrame(self) -> None:
        if self.block.is_set():
            self.release.wait()
        self._next += self.period
        time.sleep(max(0.0, self._next - time.monotonic()))

    @property
    def rigidBodies(self) -> dict[str, SimpleNamespace]:
        with self._lock:
            return dict(self.bodies)

    def set(self, name: str, body: SimpleNamespace | None) -> None:
        with self._lock:
            if body is None:
                self.bodies.pop(name, None)
            else:
                self.bodies[name] = body


def _wait_for(pred: Callable[[], bool], timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.002)
    return pred()


@pytest.fixture
def fake() -> Iterator[FakeMocap]:
    f = FakeMocap()
    f.set("cf1", _body((1.0, 2.0, 0.5), Rotation.from_euler("z", 0.7)))
    yield f
    f.release.set()


def _source(fake: FakeMocap, **kw: Any) -> tuple[MocapPoseSource, list[tuple[str, dict[str, str]]]]:
    calls: list[tuple[str, dict[str, str]]] = []

    def connect(system: str, cfg: dict[str, str]) -> FakeMocap:
        calls.append((system, cfg))
        return fake

    return MocapPoseSource(MocapConfig(system="fake", settings={"hostname": "h"}, **kw), connect), calls


def test_is_pose_source_and_receive_stamps(fake: FakeMocap) -> None:
    src, calls = _source(fake)
    assert isinstance(src, PoseSource)
    assert src.latest("cf1") is None  # never seen (not started)
    t0 = time.monotonic()
    src.start()
    try:
        assert calls == [("fake", {"hostname": "h"})]
        assert _wait_for(lambda: src.latest("cf1") is not None)
        sp = src.latest("cf1")
        assert sp is not None
        assert t0 <= sp.stamp <= time.monotonic()
        assert time.monotonic() - sp.stamp <= src.cfg.stale_after_s
        np.testing.assert_allclose(sp.pose.p, [1.0, 2.0, 0.5], atol=1e-6)
        assert sp.pose.theta == pytest.approx(0.7, abs=1e-6)
        assert src.latest("nobody") is None
        assert src.tilt("nobody") is None
        assert src.tilt("cf1") == pytest.approx(0.0, abs=1e-6)
        time.sleep(0.05)
        sp2 = src.latest("cf1")
        assert sp2 is not None and sp2.stamp > sp.stamp  # stamps advance with received frames
        assert "cf1" in [e.detail for e in src.events if e.kind == "body_found"]
    finally:
        src.close()


def test_stamps_use_injected_clock(fake: FakeMocap) -> None:
    offset = 1000.0
    src = MocapPoseSource(
        MocapConfig(system="fake"), lambda s, c: fake, clock=lambda: time.monotonic() + offset
    )
    src.start()
    try:
        assert _wait_for(lambda: src.latest("cf1") is not None)
        sp = src.latest("cf1")
        assert sp is not None and sp.stamp > offset
    finally:
        src.close()


def test_stale_after_body_disappears(fake: FakeMocap, safety_bound: Bound) -> None:
    src, _ = _source(fake, stale_after_s=0.1)
    src.start()
    try:
        assert _wait_for(lambda: src.latest("cf1") is not None)
        fake.set("cf1", None)
        t_removed = time.monotonic()
        assert _wait_for(lambda: any((e.kind, e.detail) == ("body_lost", "cf1") for e in src.events))
        last: list[float] = []  # the receive stamp of the newest pose seen (a loaded reader may lag)

        def stale() -> bool:
            sp = src.latest("cf1")
            if sp is not None:
                last.append(sp.stamp)
            return sp is None

        assert _wait_for(stale, timeout=1.0)
        t_stale = time.monotonic()
        if last:  # not refused before stale_after_s after the newest pose's receipt
            assert t_stale - max(last) >= src.cfg.stale_after_s
        safety_bound(
            "mocap: a vanished body's pose refused (stale_after_s 0.1 s)", 1e3 * (t_stale - t_removed), 500
        )
        assert src.rate_hz("cf1") == 0.0
        assert src.tilt("cf1") is not None  # last tilt stays known
        fake.set("cf1", _body((0.0, 0.0, 1.0), Rotation.identity()))
        assert _wait_for(lambda: src.latest("cf1") is not None)
        assert any((e.kind, e.detail) == ("body_regained", "cf1") for e in src.events)
    finally:
        src.close()


def test_stale_when_frames_stop(fake: FakeMocap) -> None:
    """A frozen stream (no frames at all) also makes bodies stale."""
    src, _ = _source(fake, stale_after_s=0.1)
    src.start()
    try:
        assert _wait_for(lambda: src.latest("cf1") is not None)
        fake.block.set()
        assert _wait_for(lambda: src.latest("cf1") is None, timeout=1.0)
        assert src.stats()["last_frame_age_s"] > 0.09
    finally:
        fake.release.set()
        src.close()


def test_tilt_refusal(fake: FakeMocap) -> None:
    src, _ = _source(fake, max_tilt_rad=0.35)
    src.start()
    try:
        assert _wait_for(lambda: src.latest("cf1") is not None)
        fake.set("cf1", _body((1.0, 2.0, 0.5), Rotation.from_euler("ZYX", [0.7, 0.0, 0.5])))
        assert _wait_for(lambda: src.latest("cf1") is None)
        assert src.tilt("cf1") == pytest.approx(0.5, abs=1e-6)
        assert any((e.kind, e.detail) == ("tilt_refused", "cf1") for e in src.events)
        time.sleep(0.05)
        assert src.latest("cf1") is None  # refused while tilted, although fresh
        assert [e.kind for e in src.events].count("tilt_refused") == 1  # one event per episode
        fake.set("cf1", _body((1.0, 2.0, 0.5), Rotation.from_euler("ZYX", [0.7, 0.2, 0.0])))
        assert _wait_for(lambda: src.latest("cf1") is not None)
        assert any((e.kind, e.detail) == ("tilt_ok", "cf1") for e in src.events)
    finally:
        src.close()


def test_invalid_run_counts_the_samples_since_the_last_valid_one(fake: FakeMocap) -> None:
    """A body whose samples turn non-finite counts them (`invalid_run`, what preflight reports as
    "streams non-finite poses"); a valid sample resets it; a body never streamed counts 0."""
    src, _ = _source(fake)
    src.start()
    try:
        assert _wait_for(lambda: src.latest("cf1") is not None)
        assert src.invalid_run("cf1") == 0 and src.invalid_run("nobody") == 0
        fake.set("cf1", _body((math.nan, 2.0, 0.5), Rotation.from_euler("z", 0.7)))
        assert _wait_for(lambda: src.invalid_run("cf1") >= 3)
        assert any((e.kind, e.detail) == ("bad_sample", "cf1") for e in src.events)
        fake.set("cf1", _body((1.0, 2.0, 0.5), Rotation.from_euler("z", 0.7)))
        assert _wait_for(lambda: src.invalid_run("cf1") == 0)
        assert src.latest("cf1") is not None
    finally:
        src.close()


def test_rate_hz(fake: FakeMocap) -> None:
    src, _ = _source(fake)
    src.start()
    try:
        time.sleep(1.0)
        assert src.rate_hz("cf1") == pytest.approx(200.0, rel=0.3)
        st_ = src.stats()
        assert st_["bodies"]["cf1"]["rate_hz"] == pytest.approx(200.0, rel=0.3)
        assert st_["connected"] and st_["reader_alive"] and st_["frames"] > 100
        assert src.rate_hz("nobody") == 0.0
    finally:
        src.close()


def test_close_joins_quickly(fake: FakeMocap) -> None:
    src, _ = _source(fake)
    src.start()
    assert _wait_for(lambda: src.latest("cf1") is not None)
    t0 = time.monotonic()
    src.close()
    print(f"closed in {1e3 * (time.monotonic() - t0):.0f} ms")
    assert not src.stats()["reader_alive"]


def test_close_is_bounded_when_reader_blocked(fake: FakeMocap) -> None:
    src, _ = _source(fake)
    src.start()
    assert _wait_for(lambda: src.latest("cf1") is not None)
    fake.block.set()
    time.sleep(0.05)
    t0 = time.monotonic()
    src.close(join_timeout_s=0.2)
    assert time.monotonic() - t0 < 0.2 + 2.0  # gave up on the join (2 s: scheduling on a busy machine)
    assert any(e.kind == "reader_join_timeout" for e in src.events)
    fake.release.set()  # the reader then sees the stop flag and exits
    assert _wait_for(lambda: not src.stats()["reader_alive"])


def test_connect_timeout_names_system() -> None:
    never = threading.Event()

    def blocking_connect(system: str, cfg: dict[str, str]) -> Any:
        never.wait(10.0)
        return FakeMocap()

    src = MocapPoseSource(
        MocapConfig(system="optitrack", settings={"hostname": "127.0.0.9"}, connect_timeout_s=0.3),
        blocking_connect,
    )
    t0 = time.monotonic()
    with pytest.raises(MocapError, match=r"no optitrack server answered within 0\.3 s.*127\.0\.0\.9"):
        src.start()
    assert 0.29 <= time.monotonic() - t0 < 0.3 + 2.0  # its connect timeout (2 s: scheduling)
    never.set()  # late connect: the thread must exit without reading
    assert _wait_for(lambda: not src.stats()["reader_alive"])
    assert src.stats()["frames"] == 0


def test_connect_error_is_wrapped() -> None:
    def bad_connect(system: str, cfg: dict[str, str]) -> Any:
        raise RuntimeError("Unknown motion capture type!")

    src = MocapPoseSource(MocapConfig(system="nosuch"), bad_connect)
    with pytest.raises(MocapError, match=r"nosuch.*Unknown motion capture type"):
        src.start()


def test_reader_error_is_recorded(fake: FakeMocap) -> None:
    src, _ = _source(fake)
    src.start()
    try:
        assert _wait_for(lambda: src.latest("cf1") is not None)

        def boom() -> None:
            raise RuntimeError("link down")

        fake.waitForNextFrame = boom  # type: ignore[method-assign]
        assert _wait_for(lambda: src.stats()["reader_failing"]) and src.stats()["reader_alive"]
        assert "link down" in (src.stats()["reader_error"] or "")
        assert _wait_for(lambda: src.latest("cf1") is None, timeout=1.0)
    finally:
        src.close()


# ---- real motioncapture mock backend -----------------------------------------------------------------------
def test_real_mock_backend() -> None:
    pytest.importorskip("motioncapture")
    w, x, y, z = _wxyz(Rotation.from_euler("z", -0.8))
    cfg = MocapConfig(
        system="mock",
        settings={
            "rigid_bodies": f"cf1(1.5,-2.0,0.75,{w},{x},{y},{z});cf2(0,0,0,1,0,0,0)",
            "frequency": "200",
        },
        connect_timeout_s=2.0,
    )
    with MocapPoseSource(cfg) as src:
        assert _wait_for(lambda: src.latest("cf1") is not None and src.latest("cf2") is not None)
        sp = src.latest("cf1")
        assert sp is not None
        np.testing.assert_allclose(sp.pose.p, [1.5, -2.0, 0.75], atol=1e-6)
        assert sp.pose.theta == pytest.approx(-0.8, abs=1e-5)
        assert src.tilt("cf1") == pytest.approx(0.0, abs=1e-3)
        time.sleep(0.6)
        assert src.rate_hz("cf1") == pytest.approx(200.0, rel=0.3)
    assert not src.stats()["reader_alive"]
