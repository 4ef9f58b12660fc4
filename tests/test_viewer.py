"""The Rerun viewer: `flightstack view RUN_DIR` and the live `--viewer` tap.

Each .rrd is read back with rerun 0.41's own reader (rerun.chunk.RrdReader: chunks with their entity path
and row count; the version is pinned in pyproject.toml's `viewer` extra because this API changes between
releases), and the rows per entity are checked against the rate rules of flightstack.viewer.layout.
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

rr = pytest.importorskip(
    "rerun", reason="the viewer tests need rerun-sdk 0.41.0 (the `viewer` extra: pip install -e '.[viewer]')"
)
from rerun.chunk import RrdReader  # noqa: E402

from flightstack.cli.app import main  # noqa: E402
from flightstack.config.mission import load_mission  # noqa: E402
from flightstack.config.rig import resolved_document  # noqa: E402
from flightstack.recording.run_reader import load_run, read_events  # noqa: E402
from flightstack.viewer import layout, sinks  # noqa: E402
from flightstack.viewer.live import RerunTap  # noqa: E402
from flightstack.viewer.rerun_import import INSTALL_HINT  # noqa: E402
from tests.conftest import MISSIONS, fly_mode  # noqa: E402


class Rrd:
    """What an .rrd holds: non-static rows per entity path, the static entity paths, the timelines."""

    def __init__(self, path: Path) -> None:
        reader = RrdReader(path)
        self.recordings = reader.recordings()
        self.rows: Counter[str] = Counter()
        self.static: set[str] = set()
        self.timelines: set[str] = set()
        self.chunks = list(reader.stream())
        for ch in self.chunks:
            if ch.is_static:
                self.static.add(ch.entity_path)
            else:
                self.rows[ch.entity_path] += ch.num_rows
                self.timelines.update(ch.timeline_names)
        reader.store()  # only a finished file has the footer (manifest) this needs

    def column(self, path: str, name: str) -> tuple[np.ndarray, list[Any]]:
        """(mission_time (s), values) of component column `name` of entity `path`, in time order."""
        t: list[float] = []
        v: list[Any] = []
        for ch in self.chunks:
            if ch.entity_path == path and not ch.is_static:
                rb = ch.to_record_batch()
                t += [x.value / 1e9 for x in rb.column(layout.TIMELINE)]
                v += rb.column(name).to_pylist()
        order = np.argsort(t, kind="stable")
        return np.asarray(t)[order], [v[k] for k in order]


def _events_by_mode(run_dir: Path) -> Counter[str]:
    """Events per mode as events.jsonl holds them (an event without a mode: the one before it)."""
    out: Counter[str] = Counter()
    mode = ""
    for ev in read_events(run_dir):
        mode = str(ev.get("mode", mode))
        out[mode] += 1
    return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """paper_sim with its three modes over 12 s (the shortest that trains every expert), one restart of
    the GP fit (fast); about 2 s."""
    tmp = tmp_path_factory.mktemp("viewer")
    doc = resolved_document(MISSIONS / "paper_sim.yaml")
    doc["duration_s"], doc["gp"]["restarts"] = 12.0, 1
    exp = tmp / "paper_sim_12.yaml"
    exp.write_text(yaml.safe_dump(doc))
    out = tmp / "run"
    assert main(["run", str(exp), "--out", str(out), "--force", "--no-progress"]) == 0
    return out


# ---- the rate rules ----------------------------------------------------------------------------------------
def test_rate_rules() -> None:
    assert layout.stride(0.002, 20.0) == 25  # paper_sim: 500 Hz ticks, 3-D at 20 Hz
    assert layout.stride(0.05, 20.0) == 1  # the lab: 20 Hz ticks, every tick
    assert layout.stride(0.002, 10.0, base=layout.stride(0.002, 50.0)) == 50  # live 3-D ⊂ live scalars
    assert layout.stride(0.003, 10.0, base=7) == 35
    assert layout.scalar_stride(10_000) == 1 and layout.scalar_stride(20_000) == 2
    assert list(layout.ticks(7, 3)) == [0, 3, 6]
    assert sinks.viewer_spec("save:x.rrd") == "save:x.rrd" and sinks.viewer_spec("") == sinks.AUTO
    assert sinks.connect_url("10.0.0.2:9876") == "rerun+http://10.0.0.2:9876/proxy"
    with pytest.raises(Exception, match="spawn, connect"):
        sinks.viewer_spec("save:")


def test_viewer_option_on_run_sim_fly_and_agent(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from flightstack.cli.app import build_parser

    p = build_parser()
    for cmd in (
        ["run", "paper_sim"],
        ["sim", "paper_sim"],
        ["fly", "m.yaml"],
        ["agent", "m.yaml", "--id", "1"],
    ):
        assert p.parse_args(cmd).viewer is None
        assert p.parse_args([*cmd, "--viewer"]).viewer == sinks.AUTO
        assert p.parse_args([*cmd, "--viewer", "connect:h:1"]).viewer == "connect:h:1"
    monkeypatch.setattr(sinks, "display_available", lambda: False)  # headless: into the run directory
    assert sinks.resolve(sinks.AUTO, tmp_path / "live.rrd") == sinks.Sink("save", str(tmp_path / "live.rrd"))
    monkeypatch.setattr(sinks, "display_available", lambda: True)
    assert sinks.resolve(sinks.AUTO, tmp_path / "live.rrd") == sinks.Sink("spawn")
    refused = sinks.unreachable(sinks.Sink("connect", sinks.connect_url("127.0.0.1:1")), timeout_s=1.0)
    assert refused is not None and "no Rerun viewer answers at 127.0.0.1:1" in refused


# ---- (a) view: a run directory -> .rrd, read back ----------------------------------------------------------
def test_view_writes_an_rrd_with_every_mode_at_the_stated_rates(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "replay.rrd"
    t0 = time.perf_counter()
    assert main(["view", str(run_dir), "--save", str(out)]) == 0
    assert time.perf_counter() - t0 < 20
    assert "every 25 ticks" in capsys.readouterr().out
    rrd = Rrd(out)
    assert len(rrd.recordings) == 1 and rrd.timelines == {layout.TIMELINE}
    recs = load_run(run_dir)
    events = _events_by_mode(run_dir)
    assert list(recs) == ["none", "local", "dgp"]
    for mode, rec in recs.items():
        n, ids = rec.ticks_done, rec.drone_ids
        assert n == 6000 and ids == [1, 2, 3]
        poses = math.ceil(n / 25)  # dt 0.002 s: every 25th tick is 20 Hz of mission time
        for path in [layout.target(mode), layout.trail(mode, "target")]:
            assert rrd.rows[path] == poses, path
        for i in ids:
            for path in (layout.drone(mode, i), layout.estimate(mode, i), layout.trail(mode, f"drone{i}")):
                assert rrd.rows[path] == poses, path
            for signal in ("e_c", "e_c_norm", "e_e", "e_e_norm", "mu_fused", "var_own", "visible", "n_fused"):
                assert rrd.rows[layout.series(mode, signal, i)] == n, (mode, signal)  # every tick (≤ cap)
            # each expert's own μ where the mode predicts (from experts.npz), not in `none`
            assert rrd.rows[layout.series(mode, "mu_own", i)] == (0 if mode == "none" else n)
            assert {layout.drone(mode, i), layout.camera(mode, i), layout.image(mode, i)} <= rrd.static
        assert rrd.rows[layout.events(mode)] == events[mode] == len(rec.events) > 0
    for i in (1, 2, 3):
        assert {layout.region(i), layout.training(i)} <= rrd.static
    # the values are the recording's: drone 1's translation (m, float32) at its 3-D ticks
    t, tr = rrd.column(layout.drone("dgp", 1), "Transform3D:translation")
    rec = recs["dgp"]
    assert np.allclose(t, rec.t[::25], atol=1e-9)
    assert np.allclose(np.array([v[0] for v in tr]), rec.g_wi[::25, 0, :3], atol=1e-6)


def test_view_without_a_display_saves_run_rrd_and_says_how_to_open_it(
    run_dir: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(sinks, "display_available", lambda: False)
    assert main(["view", str(run_dir), "--mode", "dgp"]) == 0
    path = run_dir / "run.rrd"
    assert f"rerun {path}" in capsys.readouterr().out
    rrd = Rrd(path)
    assert {p.split("/")[1] for p in rrd.rows} == {"dgp"}  # --mode: that mode only


def test_view_of_a_missing_run_or_mode_exits_2(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["view", str(tmp_path / "nothing"), "--save", str(tmp_path / "x.rrd")]) == 2
    assert main(["view", str(run_dir), "--mode", "oracle", "--save", str(tmp_path / "x.rrd")]) == 2
    assert "modes: none, local, dgp" in capsys.readouterr().err


# ---- (b) live: --viewer save:FILE on a run -----------------------------------------------------------------
def test_live_viewer_of_a_run_writes_the_expected_entities(tmp_path: Path) -> None:
    out, rrd_path = tmp_path / "run", tmp_path / "live.rrd"
    args = ["run", "paper_sim", "--out", str(out), "--force", "--duration", "4", "--modes", "none"]
    assert main([*args, "--no-progress", "--viewer", f"save:{rrd_path}"]) == 0
    rrd = Rrd(rrd_path)
    rec = load_run(out)["none"]
    n = rec.ticks_done
    assert n == 2000
    scalars, poses = math.ceil(n / 10), math.ceil(n / 50)  # live: 50 Hz and 10 Hz of mission time
    assert rrd.rows[layout.target("none")] == poses
    for i in rec.drone_ids:
        assert rrd.rows[layout.drone("none", i)] == rrd.rows[layout.estimate("none", i)] == poses
        assert rrd.rows[layout.series("none", "e_c", i)] == scalars
        assert rrd.rows[layout.series("none", "e_e_norm", i)] == scalars
        assert layout.image("none", i) in rrd.static
    assert rrd.rows[layout.events("none")] == len(rec.events)
    assert layout.region(1) in rrd.static
    # live e_c is computed from the poses; it equals the recording's (filled after landing)
    _, ec = rrd.column(layout.series("none", "e_c", 1), "Scalars:scalars")
    assert np.allclose(np.array(ec), rec.e_c[::10, 0], atol=1e-9)


def test_live_viewer_shows_camera_images_and_does_not_change_the_flight(tmp_path: Path) -> None:
    """The simulated lab renders camera images: the tap shows the frames the agents measured (JPEG), and
    the recording is the one flown without a viewer (asking the rendered camera again would draw noise
    from the simulation's generator)."""
    mission = load_mission("paper_experiment", {"duration_s": 1.5, "compare_modes": ["none"]})
    rrd_path = tmp_path / "lab.rrd"
    tap = RerunTap.open(sinks.Sink("save", str(rrd_path)), mission, ["none"], "lab test")
    try:
        seen = fly_mode(mission, "none", taps=[tap])
    finally:
        tap.finish()
    alone = fly_mode(mission, "none")
    for name in ("g_wi", "g_bar_w", "e_e_meas", "V_cmd", "visible"):
        assert np.array_equal(getattr(seen, name), getattr(alone, name)), name
    rrd = Rrd(rrd_path)
    assert rrd.rows[layout.image("none", 1)] >= 1  # at most IMAGE_HZ per wall second
    assert rrd.rows[layout.markers("none", 1)] >= 1  # the markers drone 1's agent detected, over its image
    assert rrd.rows[layout.drone("none", 2)] == math.ceil(seen.ticks_done / 2)  # dt 0.05 s: 10 Hz
    assert tap.dropped == 0 and tap.errors == 0


# ---- (c) the tap never holds the loop; a failing tap never ends the flight ---------------------------------
class _Raising:
    def start(self, f: Any, rec: Any) -> None:
        pass

    def on_tick(self, f: Any, rec: Any, k_end: int) -> None:
        raise RuntimeError("a broken observer")

    def close(self, rec: Any) -> None:
        pass


def test_a_slow_viewer_drops_batches_instead_of_blocking_and_a_raising_tap_does_not_end_the_flight(
    tmp_path: Path,
) -> None:
    mission = load_mission("paper_sim", {"duration_s": 1.0, "compare_modes": ["none"]})
    stream = sinks.open_stream(rr, sinks.Sink("save", str(tmp_path / "slow.rrd")), "slow")
    tap = RerunTap(rr, stream, mission, queue_size=2)
    send = tap._send

    def slow_send(job: Any) -> None:  # a viewer that takes 0.2 s per batch
        time.sleep(0.2)
        send(job)

    tap._send = slow_send  # type: ignore[method-assign]
    longest = [0.0]
    on_tick = tap.on_tick

    def timed(f: Any, rec: Any, k_end: int) -> None:
        t0 = time.perf_counter()
        on_tick(f, rec, k_end)
        longest[0] = max(longest[0], time.perf_counter() - t0)

    tap.on_tick = timed  # type: ignore[method-assign]
    try:
        rec = fly_mode(mission, "none", taps=[_Raising(), tap], compiled=False)  # on_tick every tick
    finally:
        tap.finish()
    assert rec.ticks_done == 500 and rec.error is None and not rec.interrupted  # the flight went on
    assert tap.dropped > 0  # the queue was full: batches dropped...
    assert longest[0] < 0.1  # ...and on_tick never waited for the slow viewer
    assert Rrd(tmp_path / "slow.rrd").rows[layout.events("none")] == len(rec.events)  # events kept


# ---- (d) without rerun-sdk ---------------------------------------------------------------------------------
def test_without_rerun_view_and_viewer_exit_2_with_the_install_hint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    assert main(["view", str(tmp_path)]) == 2
    assert INSTALL_HINT in capsys.readouterr().err
    out = tmp_path / "run"
    args = ["run", "paper_sim", "--out", str(out), "--duration", "1", "--modes", "none", "--no-progress"]
    assert main([*args, "--viewer", "save:x.rrd"]) == 2
    err = capsys.readouterr().err
    assert INSTALL_HINT in err and "nothing took off" in err
    assert not out.exists() or not any(out.iterdir())
