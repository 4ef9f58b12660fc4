"""The impairment model (flightstack.netem): seeded determinism and its statistics against closed forms."""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import pytest

from flightstack.netem import (
    LINKS,
    PROFILES,
    BlackoutPlan,
    LinkModel,
    LinkProfile,
    StreamModel,
    blackout_windows,
    profile,
)

pytestmark = pytest.mark.unit


def _run(model: LinkModel, n: int, period: float = 0.01, size: int = 100) -> list[list[float]]:
    return [model.decide(k * period, size) for k in range(n)]


def test_same_seed_same_decisions_per_link() -> None:
    prof = PROFILES["crowded"].link("rc")
    a = _run(LinkModel(prof, 7, "tello1", "state"), 3000)
    b = _run(LinkModel(prof, 7, "tello1", "state"), 3000)
    assert a == b
    other_link = _run(LinkModel(prof, 7, "tello1", "reply"), 3000)
    other_seed = _run(LinkModel(prof, 8, "tello1", "state"), 3000)
    assert a != other_link and a != other_seed


def test_decisions_do_not_depend_on_timing() -> None:
    """The n-th packet meets the same loss decision whatever the times (fixed draws per packet)."""
    prof = LinkProfile.bursty(0.1, 3.0)
    a = [bool(x) for x in _run(LinkModel(prof, 3, "d", "l"), 2000, period=0.01)]
    b = [bool(x) for x in _run(LinkModel(prof, 3, "d", "l"), 2000, period=0.37)]
    assert a == b


@pytest.mark.parametrize(("loss", "burst"), [(0.02, 2.0), (0.05, 5.0), (0.2, 1.5)])
def test_gilbert_elliott_loss_rate_and_burst_length(loss: float, burst: float) -> None:
    """Stationary loss p/(p+r) and mean burst 1/r of the simple Gilbert model, within 4 standard errors."""
    prof = LinkProfile.bursty(loss, burst)
    assert prof.stationary_loss() == pytest.approx(loss)
    assert prof.mean_burst() == pytest.approx(burst)
    n = 200_000
    lost = [not x for x in _run(LinkModel(prof, 11, "d", "l"), n)]
    rate = sum(lost) / n
    bursts = [len(list(g)) for k, g in itertools.groupby(lost) if k]
    mean_burst = sum(bursts) / len(bursts)
    # bursty losses are correlated: the rate's standard error grows by ~sqrt((1+ρ)/(1-ρ)), ρ = 1 - p - r
    rho = 1.0 - prof.loss_p - prof.loss_r
    se_rate = math.sqrt(loss * (1 - loss) / n * (1 + rho) / (1 - rho))
    assert abs(rate - loss) < 4 * se_rate, (rate, loss, se_rate)
    # burst lengths are geometric with mean 1/r: variance (1-r)/r²
    se_burst = math.sqrt((1 - prof.loss_r) / prof.loss_r**2 / len(bursts))
    assert abs(mean_burst - burst) < 4 * se_burst, (mean_burst, burst, se_burst)


def test_jitter_mean_and_order() -> None:
    prof = LinkProfile(latency_s=0.003, jitter_s=0.010)
    model = LinkModel(prof, 1, "d", "l")
    n = 50_000
    out = [model.decide(k * 0.5, 100) for k in range(n)]  # far apart: the order never holds one back
    delays = [x[0] - k * 0.5 for k, x in enumerate(out)]
    mean = sum(delays) / n
    assert abs(mean - 0.013) < 4 * 0.010 / math.sqrt(n)
    dense = LinkModel(prof, 1, "d", "l")
    due = [dense.decide(k * 0.001, 100)[0] for k in range(5000)]
    assert all(b >= a for a, b in itertools.pairwise(due))  # in order: 802.11 delivers in order


def test_reordering_and_duplication_rates() -> None:
    prof = LinkProfile(reorder=0.1, reorder_s=0.05, duplicate=0.05)
    model = LinkModel(prof, 5, "d", "l")
    n = 40_000
    out = [model.decide(k * 0.001, 100) for k in range(n)]
    dup = sum(len(x) == 2 for x in out) / n
    assert abs(dup - 0.05) < 4 * math.sqrt(0.05 * 0.95 / n)
    assert abs(model.counts["reordered"] / n - 0.1) < 4 * math.sqrt(0.1 * 0.9 / n)
    firsts = [x[0] for x in out]
    overtaken = sum(b < a for a, b in itertools.pairwise(firsts))
    assert overtaken > 0.05 * n  # a held packet is overtaken by the ones behind it


def test_rate_cap_throughput_and_tail_drop() -> None:
    prof = LinkProfile(rate_bps=1e6, queue_s=0.1)
    model = LinkModel(prof, 0, "d", "v")
    # 2 Mbit/s offered for 2 s: half of it fits, the rest is tail-dropped once the queue holds 0.1 s
    out = [model.decide(k * 0.005, 1250) for k in range(400)]
    delivered = [x[0] for x in out if x]
    assert len(delivered) == pytest.approx(200, abs=25)
    assert model.counts["queue"] == 400 - len(delivered)
    span = delivered[-1] - delivered[0]
    assert 8 * 1250 * (len(delivered) - 1) / span == pytest.approx(1e6, rel=0.01)
    assert max(d - k * 0.005 for k, x in enumerate(out) if x for d in x) <= 0.1 + 0.01 + 1e-9


def test_blackouts_drop_both_directions_in_their_windows() -> None:
    plan = BlackoutPlan(first_s=6.0, every_s=12.0, min_s=1.0, max_s=3.0)
    windows = blackout_windows(plan, 4, "tello1", horizon_s=60.0)
    assert [a for a, _ in windows] == [6.0, 18.0, 30.0, 42.0, 54.0]
    assert all(1.0 <= b - a <= 3.0 for a, b in windows)
    assert windows == blackout_windows(plan, 4, "tello1", horizon_s=60.0)
    assert windows != blackout_windows(plan, 4, "tello2", horizon_s=60.0)
    up = LinkModel(LinkProfile(), 4, "tello1", "command", epoch=100.0, blackouts=windows)
    down = LinkModel(LinkProfile(), 4, "tello1", "state", epoch=100.0, blackouts=windows)
    a, b = windows[0]
    for model in (up, down):
        assert model.decide(100.0 + a - 0.01, 10) and model.decide(100.0 + b + 0.01, 10)
        assert model.decide(100.0 + (a + b) / 2, 10) == []
        assert model.counts["blackout"] == 1


def test_profiles() -> None:
    assert PROFILES["clean"].clean
    assert all(PROFILES["clean"].link(k).clean for k in LINKS)
    wifi = profile("lab-wifi").link("rc")
    assert 0.01 <= wifi.stationary_loss() <= 0.05 and 0.01 <= wifi.jitter_s <= 0.05
    crowded = profile("crowded")
    assert crowded.link("video").rate_bps is not None and crowded.link("rc").reorder > 0
    assert crowded.link("rc").spike_s[0] >= 0.1 and crowded.link("rc").mean_burst() > 2
    outage = profile("outage").blackouts
    assert outage is not None and (outage.min_s, outage.max_s) == (1.0, 3.0)
    with pytest.raises(ValueError, match="unknown network profile"):
        profile("nope")
    with pytest.raises(ValueError, match="probability"):
        LinkProfile(loss_p=1.5)
    assert "gemodel" in wifi.netem() and "rate 2500kbit" in crowded.link("video").netem()


def test_stream_model_delivers_everything_in_order() -> None:
    prof = LinkProfile.bursty(0.05, 2.0, latency_s=0.002, jitter_s=0.005, rate_bps=8e6)
    m = StreamModel(prof, 2, "bus", "0:up", epoch=10.0, blackouts=[(1.0, 2.5)])
    t = [10.0 + 0.01 * k for k in range(400)]
    due = [m.decide(x, 1000) for x in t]
    assert all(b >= a for a, b in itertools.pairwise(due)) and all(d > x for d, x in zip(due, t, strict=True))
    held = [d for x, d in zip(t, due, strict=True) if 11.0 <= x < 12.5]
    assert held and min(held) >= 12.5 + 0.002  # a blackout holds the bytes, then their latency
    assert m.counts["held"] == len(held) and m.counts["chunks"] == 400
    assert m.counts["retransmitted"] > 0  # a loss costs a retransmission, never the bytes
    late = [d - x for x, d in zip(t, due, strict=True) if not 11.0 <= x < 12.7]
    assert min(late) >= 0.002 + 8 * 1000 / 8e6 - 1e-12


@pytest.mark.parametrize("spacing_steps", [1.0, 20.0])
def test_time_stepped_chain_against_its_n_step_closed_form(spacing_steps: float) -> None:
    """A chain stepped per 10 ms: packets every 10 ms see the per-packet closed forms; packets every
    200 ms see the 20-step transition: same stationary loss, mean burst 1/(1 − P(bad → bad in n steps))."""
    prof = LinkProfile.bursty(0.05, 5.0, loss_step_s=0.01)
    n = 200_000
    model = LinkModel(prof, 9, "d", "l")
    lost = [not model.decide(k * 0.01 * spacing_steps, 100) for k in range(n)]
    stay = prof.transition(True, spacing_steps)
    if spacing_steps == 1.0:
        assert stay == pytest.approx(1 - prof.loss_r)
    rate = sum(lost) / n
    rho = stay - prof.transition(False, spacing_steps)  # the n-step chain's second eigenvalue
    se_rate = math.sqrt(0.05 * 0.95 / n * (1 + rho) / (1 - rho))
    assert abs(rate - 0.05) < 4 * se_rate, (rate, se_rate)
    bursts = [len(list(g)) for k, g in itertools.groupby(lost) if k]
    expected_burst = 1.0 / (1.0 - stay)
    se_burst = math.sqrt(stay / (1 - stay) ** 2 / len(bursts))
    assert abs(sum(bursts) / len(bursts) - expected_burst) < 4 * se_burst


def test_network_profiles_are_the_emulated_labs_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--network` reaches the mission on the emulated lab; a simulated rig refuses it (schema) and so does a
    real lab (exit 2, nothing flies: tc netem impairs a real network)."""
    from flightstack.cli.app import main
    from flightstack.config.mission import MissionError, load_mission

    m = load_mission("paper_experiment", {"links.network": "crowded"}, rig="emulated-lab")
    assert m.links.network == "crowded" and m.start_emulators
    assert load_mission("paper_experiment", rig="emulated-lab").links.network == "clean"
    with pytest.raises(MissionError, match=r"links\.network: profile 'lab-wifi' is applied by the emulated"):
        load_mission("paper_experiment", {"links.network": "lab-wifi"}, rig="lab-sim")
    with pytest.raises(MissionError, match="unknown network profile 'wifi'"):
        load_mission("paper_experiment", {"links.network": "wifi"}, rig="emulated-lab")
    out = tmp_path / "run"
    assert main(["run", "paper_experiment", "--rig", "lab", "--network", "outage", "--out", str(out)]) == 2
    assert "tc netem" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"latency_s": 1e300}, "LinkProfile.latency_s"),
        ({"jitter_s": 1e300}, "LinkProfile.jitter_s"),
        ({"queue_s": 1e300}, "LinkProfile.queue_s"),
        ({"reorder_s": math.inf}, "LinkProfile.reorder_s"),
        ({"latency_s": math.nan}, "LinkProfile.latency_s"),
        ({"latency_s": -0.001}, "LinkProfile.latency_s"),
        ({"latency_s": "0.1"}, "LinkProfile.latency_s"),
        ({"rate_bps": 1e-300}, "LinkProfile.rate_bps"),
        ({"rate_bps": 1e300}, "LinkProfile.rate_bps"),
        ({"spike_s": (0.1, 1e300)}, "LinkProfile.spike_s"),
        ({"spike_s": (0.3, 0.1)}, "LinkProfile.spike_s"),
        ({"loss_p": math.nan}, "LinkProfile.loss_p"),
    ],
)
def test_a_link_profile_refuses_values_no_link_has(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        LinkProfile(**kwargs)


def test_link_profile_bounds_admit_the_extremes_of_real_links() -> None:
    from flightstack.netem import MAX_DELAY_S, MAX_RATE_BPS, MIN_RATE_BPS

    LinkProfile(latency_s=MAX_DELAY_S, jitter_s=MAX_DELAY_S, queue_s=MAX_DELAY_S, spike_s=(0.0, MAX_DELAY_S))
    LinkProfile(rate_bps=MIN_RATE_BPS)
    LinkProfile(rate_bps=MAX_RATE_BPS)
    LinkProfile(latency_s=0.6, rate_bps=1e4)  # a geostationary satellite hop on a slow modem


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"first_s": 0.0, "every_s": 1e-9, "min_s": 1e-10, "max_s": 1e-10}, "BlackoutPlan.every_s"),
        ({"first_s": 0.0, "every_s": 1.0, "min_s": 0.001, "max_s": 0.5}, "BlackoutPlan.min_s"),
        ({"first_s": math.inf, "every_s": 15.0, "min_s": 1.0, "max_s": 3.0}, "BlackoutPlan.first_s"),
        ({"first_s": math.nan, "every_s": 15.0, "min_s": 1.0, "max_s": 3.0}, "BlackoutPlan.first_s"),
        ({"first_s": 0.0, "every_s": 1e300, "min_s": 1.0, "max_s": 3.0}, "BlackoutPlan.every_s"),
        ({"first_s": 0.0, "every_s": 15.0, "min_s": 1.0, "max_s": 15.0}, "BlackoutPlan.max_s"),
        ({"first_s": 0.0, "every_s": 15.0, "min_s": 3.0, "max_s": 1.0}, "BlackoutPlan.max_s"),
    ],
)
def test_a_blackout_plan_refuses_values_no_link_has(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        BlackoutPlan(**kwargs)


def test_the_densest_blackout_plan_is_cheap() -> None:
    """The shortest period allowed gives 36,000 windows in an hour: drawn, and looked up per packet, in
    well under a second (BlackoutPlan(every_s=1e-9) ran for more than 10 s before it was refused)."""
    from flightstack.netem import MIN_BLACKOUT_PERIOD_S, MIN_BLACKOUT_S

    plan = BlackoutPlan(0.0, MIN_BLACKOUT_PERIOD_S, MIN_BLACKOUT_S, MIN_BLACKOUT_S)
    t0 = time.perf_counter()
    windows = blackout_windows(plan, 0, "tello1")
    model = LinkModel(LinkProfile(), 0, "tello1", "state", blackouts=windows)
    lost = sum(not model.decide(k * 0.001, 100) for k in range(10_000))
    elapsed = time.perf_counter() - t0
    print(f"{len(windows)} windows drawn and 10,000 packets decided in {1e3 * elapsed:.0f} ms")
    assert 36_000 <= len(windows) <= 36_001  # float steps of 0.1 s up to 3600 s
    assert lost == model.counts["blackout"] and 900 <= lost <= 1100  # 10 ms out of every 100 ms


def test_overlapping_blackout_windows_hold_until_the_last_one_ends() -> None:
    """Windows given by hand may overlap or come unsorted: a packet in any of them is lost (LinkModel), and
    a chunk is held until the union around it ends (StreamModel)."""
    windows = [(5.0, 6.0), (1.0, 3.0), (2.5, 4.0)]
    model = LinkModel(LinkProfile(), 0, "d", "l", epoch=10.0, blackouts=windows)
    assert [bool(model.decide(10.0 + t, 10)) for t in (0.5, 1.0, 2.9, 3.9, 4.0, 5.5, 6.0)] == [
        True, False, False, False, True, False, True,
    ]  # fmt: skip
    stream = StreamModel(LinkProfile(), 0, "d", "l", epoch=10.0, blackouts=windows)
    assert stream.decide(11.5, 10) == pytest.approx(14.0) and stream.counts["held"] == 1


def _rig_with(tmp_path: Path, extra: str) -> Path:
    """A copy of the emulated-lab rig file with `extra` appended (its relative paths kept working)."""
    from flightstack.mission_configs import __file__ as configs

    rigs = Path(configs).parent / "rigs"
    path = tmp_path / "rigs" / "emulated-copy.yaml"
    path.parent.mkdir(parents=True)
    (tmp_path / "cameras").symlink_to(rigs.parent / "cameras")
    path.write_text((rigs / "emulated-lab.yaml").read_text() + extra)
    return path


def test_a_rig_files_old_network_key_is_the_links_network_said_in_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """`network: PROFILE` beside `backend:` (before the radio joined `links:`) still loads, into
    `links.network`, with one line naming the new key; both keys at once is refused naming them."""
    from flightstack.config.mission import MissionError, load_mission

    old = _rig_with(tmp_path, "network: crowded\n")
    with caplog.at_level("WARNING"):
        m = load_mission("paper_experiment", rig=old)
    assert m.links.network == "crowded"
    said = [r.getMessage() for r in caplog.records if "links.network" in r.getMessage()]
    assert said == [f"{old}: `network:` is now `links.network:` (docs/links.md)"], said
    both = _rig_with(tmp_path / "b", "network: crowded\nlinks: {network: outage}\n")
    with pytest.raises(MissionError, match=r"network: and links\.network: both given"):
        load_mission("paper_experiment", rig=both)


def test_links_and_network_flags_set_their_own_part_of_links(tmp_path: Path) -> None:
    """`--links P` replaces the rig's links with a profile and keeps its radio; `--network N` sets the
    radio and keeps the links (load_mission's overrides, as `run` builds them); `--set links.network=N`
    sets it too."""
    from flightstack.config.mission import load_mission

    rig = _rig_with(tmp_path, "links: {network: outage, rc: {latency_s: 0.2}}\n")
    m = load_mission("paper_experiment", {"links": {"profile": "tello"}}, rig=rig)
    assert m.links.network == "outage" and m.links.profile == "tello" and m.links.rc is None
    m = load_mission("paper_experiment", {"links.network": "crowded"}, rig=rig)
    assert m.links.network == "crowded" and m.links.rc is not None and m.links.rc.latency_s == 0.2
    from flightstack.cli.run import with_sets

    assert with_sets(m, ["links.network=lab-wifi"]).links.network == "lab-wifi"  # `--set` reaches it too
