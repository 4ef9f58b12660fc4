"""The rig's links as the emulated lab applies them (sim_backend/emulators/device_links.py), on the model:
which links apply (`perfect` changes nothing), seeded decisions (the same seed gives the same decisions,
and the same as the simulated lab's for the same device and link), their statistics, and the delay
line's stream order (a newer sample pushes older ones out ahead of it)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from flightstack.config.links import PROFILES, LinkSpec, LinksSpec
from flightstack.config.mission import load_mission
from flightstack.sim_backend.emulators.device_links import DeviceLinks, LinkStage, emulated_links
from flightstack.sim_backend.emulators.radio import DelayLine

TELLO_VIDEO = PROFILES["tello"]["video"]
LOSSY = LinkSpec(latency_s=0.3, jitter_s=0.1, rate_hz=30.0, loss=0.02)
"""A link losing whole samples (2 %), late as the Tello's video."""


def test_perfect_applies_nothing_and_a_written_link_or_another_profile_applies_as_written() -> None:
    assert emulated_links(LinksSpec()) == {}  # its rc 50 ms is the simulated lab's, not the emulator's
    own = LinkSpec(latency_s=0.1)
    assert emulated_links(LinksSpec(rc=own)) == {"rc": own}
    tello = emulated_links(LinksSpec(profile="tello"))
    assert sorted(tello) == ["mocap", "rc", "robot", "state", "video"]  # the bus is not the emulators'
    assert tello["video"] == TELLO_VIDEO
    assert emulated_links(LinksSpec(profile="tello", rc=LinkSpec()))["video"] == TELLO_VIDEO
    assert "rc" not in emulated_links(LinksSpec(profile="tello", rc=LinkSpec()))
    assert emulated_links(LinksSpec(bus=LinkSpec(latency_s=0.1))) == {}  # between processes: not a device's


def test_an_emulated_lab_on_perfect_links_builds_no_link_stage(tmp_path: Path) -> None:
    from flightstack.sim_backend.emulated_lab import EmulatedLab

    assert EmulatedLab(tmp_path).link_specs == {}
    lab = EmulatedLab(tmp_path, links=LinksSpec(profile="tello"), seed=3)
    assert lab.link_spec("state").rate_hz == 10.0 and lab.link_spec("bus").perfect


def _decisions(stage: LinkStage, n: int) -> list[float | None]:
    return [stage.decide(0.0) for _ in range(n)]


def test_the_same_seed_device_and_link_give_the_same_decisions() -> None:
    a = _decisions(LinkStage(LOSSY, 7, "video", 1), 500)
    b = _decisions(LinkStage(LOSSY, 7, "video", 1), 500)
    assert a == b
    assert a != _decisions(LinkStage(LOSSY, 7, "video", 2), 500)  # another drone
    assert a != _decisions(LinkStage(LOSSY, 8, "video", 1), 500)  # another seed
    assert a != _decisions(LinkStage(LOSSY, 7, "state", 1), 500)  # another link


def test_the_emulated_lab_decides_as_the_simulated_lab_for_the_same_seed() -> None:
    """Drone 1's rc link on lab-sim (its TelloSim) and on the emulated lab (a LinkStage of "tello1")
    lose the same commands and delay the others alike."""
    from flightstack.sim_backend.build_lab import LabSimBackend

    mission = load_mission(
        "paper_experiment",
        {"duration_s": 1.0, "compare_modes": ["none"], "links": {"profile": "tello"}, "seed": 5},
        rig="lab-sim",
    )
    sim = LabSimBackend(mission).drone(1).rc_link
    stage = LinkStage(mission.links.link("rc"), 5, "rc", 1)
    for _ in range(300):
        due = stage.decide(10.0)
        assert (due is None) == sim.lost()
        if due is not None:
            assert due - 10.0 == pytest.approx(sim.delay(), abs=1e-12)


def test_the_tello_video_loses_datagrams_in_bursts_not_frames() -> None:
    """The `tello` profile's video: no frame lost whole; 0.2 % of the datagrams lost in bursts of 3 on
    average (the simple Gilbert chain, one step per datagram), the same decisions for the same seed and
    drone, others for another drone."""
    assert TELLO_VIDEO.loss == 0 and TELLO_VIDEO.datagram_loss == 0.002 and TELLO_VIDEO.datagram_burst == 3.0

    def kept(drone: int, n: int) -> np.ndarray:
        stage = LinkStage(TELLO_VIDEO, 11, "video", drone)
        out = np.array([stage.keeps(k / 270.0, 1460) for k in range(n)])
        row = stage.row()
        assert row["datagrams"] == n and row["datagrams_lost"] == (~out).sum() and row["samples"] == 0
        return out

    n = 400_000
    a = kept(1, n)
    assert np.array_equal(a, kept(1, n)) and not np.array_equal(a, kept(2, n))
    lost = ~a
    starts = lost[1:] & ~lost[:-1]
    bursts = int(starts.sum()) + int(lost[0])
    mean_burst = lost.sum() / bursts
    # bursts are geometric with mean 3: about n·0.002/3 = 267 of them; their count is Poisson-like, the
    # lost fraction then within 5 sigma of the count's spread (each burst worth ~3 datagrams)
    sigma_bursts = np.sqrt(n * 0.002 / 3.0)
    assert abs(bursts - n * 0.002 / 3.0) < 5 * sigma_bursts, bursts
    assert 2.3 < mean_burst < 3.9, mean_burst  # geometric(1/3): sd ≈ 2.45 / sqrt(267) ≈ 0.15 per burst
    assert abs(lost.mean() - 0.002) < 5 * 3.0 * sigma_bursts / n * 1.5, lost.mean()


def test_datagram_loss_is_the_video_links_alone() -> None:
    """A datagram loss on a link other than video is refused with the reason (the others are one sample
    per datagram: their `loss` says it)."""
    with pytest.raises(ValueError, match=r"state\.datagram_loss: only the video link"):
        LinksSpec(state=LinkSpec(datagram_loss=0.01))
    video = LinksSpec(video=LinkSpec(datagram_loss=0.01, datagram_burst=2.0)).link("video")
    assert video.datagram_burst == 2.0


def test_delays_and_losses_follow_the_link() -> None:
    """latency_s + U(0, jitter_s) late, `loss` of the samples lost (binomial bounds, 5 sigma)."""
    stage = LinkStage(LOSSY, 0, "video", 1)
    n = 20000
    got = _decisions(stage, n)
    delays = np.array([d for d in got if d is not None])
    lost = n - delays.size
    sd = (n * 0.02 * 0.98) ** 0.5
    assert abs(lost - 0.02 * n) < 5 * sd, lost
    assert delays.min() >= 0.3 and delays.max() <= 0.4
    assert delays.mean() == pytest.approx(0.35, abs=0.003)
    row = stage.row()
    assert (row["samples"], row["lost"], row["delivered"]) == (n, lost, delays.size)
    assert row["delay_mean_ms"] == pytest.approx(1e3 * delays.mean(), abs=1e-3)


def test_a_link_that_is_not_applied_passes_everything_at_once() -> None:
    links = DeviceLinks({"rc": LinkSpec(latency_s=0.1), "state": LinkSpec()}, 0, 1, "t")
    assert links.applies("rc") and not links.applies("state") and not links.applies("video")
    assert links.decide("video", 4.0) == 4.0
    assert links.spec("state").perfect

    class Raw:
        def gettimeout(self) -> float | None:
            return None

    raw = Raw()
    assert links.socket(raw, recv="state") is raw  # nothing to wrap
    links.close()


class _Recorder:
    """A sender that records (time.monotonic(), data) of every datagram."""

    def __init__(self) -> None:
        self.log: list[tuple[float, bytes]] = []

    def sendto(self, data: bytes, addr: tuple[str, int]) -> int:
        self.log.append((time.monotonic(), data))
        return len(data)


def test_a_newer_sample_of_a_stream_pushes_older_ones_out_ahead_of_it() -> None:
    """Due at +0.30, +0.10, +0.20 s (in that order of scheduling): the first leaves with the second at
    +0.10, before it; the third at +0.20; another stream and unnamed datagrams keep their own times."""
    line, out = DelayLine("test"), _Recorder()
    t0 = time.monotonic()
    addr = ("127.0.0.1", 9)
    line.schedule(t0 + 0.30, out, b"a", addr, stream="video")
    line.schedule(t0 + 0.35, out, b"other", addr, stream="state")
    line.schedule(t0 + 0.40, out, b"radio", addr)
    line.schedule(t0 + 0.10, out, b"b", addr, stream="video")
    line.schedule(t0 + 0.20, out, b"c", addr, stream="video")
    deadline = time.monotonic() + 3.0
    while len(out.log) < 5 and time.monotonic() < deadline:
        time.sleep(0.01)
    line.close()
    order = [d for _, d in out.log]
    at = {d: t - t0 for t, d in out.log}
    assert order == [b"a", b"b", b"c", b"other", b"radio"], order
    assert 0.10 <= at[b"a"] <= at[b"b"] < 0.2, at  # pushed out ahead of the newer one (not before it)
    assert at[b"c"] >= 0.2 and at[b"other"] >= 0.35 and at[b"radio"] >= 0.4, at
