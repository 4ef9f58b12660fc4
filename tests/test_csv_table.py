"""The per-run CSV (flightstack/recording/csv_table.py): written by the recorder once a mode's npz is on
disk, it loads in pandas with exactly the columns docs/logs.md names (read from the page), and every value
equals the recording's at the rows written (rounded as the page says); `export --csv` writes the same rows
for every mode of a run directory."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from flightstack.recording import csv_table as ct
from flightstack.recording.run_dir import RunWriter
from flightstack.recording.timeseries import Recording
from tests.conftest import REPO, random_recording

LOGS = REPO / "docs" / "logs.md"


def page_columns() -> list[str]:
    """The column names of docs/logs.md's CSV table, in order."""
    text = LOGS.read_text(encoding="utf-8")
    block = text.split("<!-- generated: csv-columns -->", 1)[1].split("<!-- /generated", 1)[0]
    return re.findall(r"^\| `([^`]+)` \|", block, re.MULTILINE)


def page_rule() -> tuple[float, int]:
    """(period s, decimals) as the page states the row and rounding rules."""
    text = LOGS.read_text(encoding="utf-8")
    period = re.search(r"⌊([0-9.]+) s / dt⌋", text)
    decimals = re.search(r"rounded to (\d+) decimals", text)
    assert period and decimals, "docs/logs.md no longer states the CSV's rules"
    return float(period[1]), int(decimals[1])


def expected(rec: Recording, k: np.ndarray) -> dict[str, np.ndarray]:
    """Each column's values at ticks k (rows: tick-major, drones in recording order), from the recording."""
    n = len(rec.drone_ids)

    def per_drone(a: np.ndarray) -> np.ndarray:
        return a[k].reshape(len(k) * n)

    def per_tick(a: np.ndarray) -> np.ndarray:
        return np.repeat(a[k], n)

    out = {"tick": np.repeat(k, n), "t": per_tick(rec.t), "drone": np.tile(rec.drone_ids, len(k))}
    for c, name in enumerate(("x", "y", "z", "theta")):
        out[name] = per_drone(rec.g_wi[..., c])
        out[f"target_{name}"] = per_tick(rec.g_w0[:, c])
        out[f"est_{name}"] = per_drone(rec.g_bar_w[..., c])
    out["e_c_norm"] = per_drone(np.linalg.norm(rec.e_c, axis=2))
    out["e_e_norm"] = per_drone(np.linalg.norm(rec.e_e, axis=2))
    for c, name in enumerate(("vx", "vy", "vz", "omega")):
        out[f"mu_{name}"] = per_drone(rec.mu_used[..., c])
        out[f"cmd_{name}"] = per_drone(rec.V_cmd[..., c])
    out["visible"] = per_drone(rec.visible).astype(int)
    out["n_fused"] = per_drone(rec.n_fused)
    return out


def check_csv(df: pd.DataFrame, rec: Recording) -> None:
    """df (the CSV of rec alone) has the page's columns and rec's values at the rows written."""
    period, decimals = page_rule()
    assert list(df.columns) == page_columns()
    dt = float(rec.t[1] - rec.t[0])
    k = np.arange(0, rec.ticks_done, max(1, int(np.floor(period / dt + 1e-9))))
    assert len(df) == len(k) * len(rec.drone_ids)
    assert (df["mode"] == rec.mode).all()
    want = expected(rec, k)
    assert set(want) == set(df.columns) - {"mode"}
    for name, values in want.items():
        got = df[name].to_numpy(dtype=float)
        finite = np.isfinite(values)
        assert np.array_equal(np.isnan(got), ~finite), name  # not finite: an empty field
        scale = 10.0**decimals
        assert np.array_equal(np.rint(got[finite] * scale), np.rint(values[finite] * scale)), name


def _recording(mode: str, n_ticks: int, dt: float, seed: int) -> Recording:
    rec = random_recording(mode, [1, 2, 5], n_ticks, seed)
    rec.t[:] = np.arange(n_ticks) * dt
    rec.g_wi *= 3.0
    rec.g_wi[0, 0, 0] = -1234.5  # several integer digits, a sign
    rec.V_cmd[1, 1, 2] = np.nan  # not finite: an empty field
    rec.mu_used[2, 2, 0] = 1e-10  # below the rounding: 0
    return rec


def test_the_recorder_writes_a_csv_per_mode_that_pandas_reads(tmp_path: Path) -> None:
    recs = [_recording("none", 500, 0.002, 0), _recording("dgp", 40, 0.05, 1)]
    with RunWriter(tmp_path) as run:
        for rec in recs:
            w = run.mode(rec.mode, rec.drone_ids, rec.ticks_done)
            w.append(rec, rec.ticks_done)
            w.close(rec)
    for rec in recs:
        df = pd.read_csv(tmp_path / f"timeseries_{rec.mode}.csv")
        check_csv(df, rec)
    assert len(pd.read_csv(tmp_path / "timeseries_none.csv")) == 50 * 3  # dt 2 ms: every 10th tick
    assert len(pd.read_csv(tmp_path / "timeseries_dgp.csv")) == 40 * 3  # dt 50 ms: every tick


def test_no_csv_without_a_final_recording(tmp_path: Path) -> None:
    """A mode closed without its recording (a run cut short) keeps its row stream and has no CSV."""
    rec = _recording("none", 20, 0.05, 0)
    with RunWriter(tmp_path) as run:
        w = run.mode("none", rec.drone_ids, 20)
        rec.ticks_done = 10
        assert w.flush(rec)
        w.close()
    assert not (tmp_path / "timeseries_none.csv").exists()
    assert (tmp_path / "timeseries_none.rows").exists()


def test_export_csv_of_a_run_directory(tmp_path: Path) -> None:
    recs = [_recording("none", 60, 0.01, 3), _recording("local", 60, 0.01, 4)]
    run_dir = tmp_path / "run"
    with RunWriter(run_dir) as run:
        for rec in recs:
            run.record(rec)
    out = tmp_path / "all.csv"
    cmd = [sys.executable, "-m", "flightstack.cli.app", "export", str(run_dir), "--csv", str(out)]
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"wrote {out}" in r.stdout and "180 rows of modes none, local" in r.stdout, r.stdout
    df = pd.read_csv(out)
    for rec in recs:
        check_csv(df[df["mode"] == rec.mode].reset_index(drop=True), rec)
    # the same bytes as the run's own files, one header
    own = [(run_dir / f"timeseries_{m}.csv").read_bytes() for m in ("none", "local")]
    assert out.read_bytes() == own[0] + own[1].split(b"\n", 1)[1]
    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert (
        again.returncode == 2
        and again.stderr.strip() == f"error: {out} exists (pass --force to overwrite it)"
    )
    nothing = subprocess.run(cmd[:-2], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert nothing.returncode == 2 and nothing.stderr.startswith("error: nothing to write"), nothing.stderr


@pytest.mark.parametrize(
    ("n_ticks", "n_drones", "dt", "stride"),
    [
        (20_000, 3, 0.002, 10),  # paper_sim: 50 Hz
        (4_000, 3, 0.01, 2),
        (1_000, 3, 0.05, 1),  # slower than 50 Hz: every tick
        (2_000_000, 3, 0.01, 6),  # the spreadsheet's limit: 6,000,000 rows / 1,048,575 → every 6th
        (1, 3, 0.01, 1),
    ],
)
def test_stride_keeps_a_file_within_a_spreadsheet(
    n_ticks: int, n_drones: int, dt: float, stride: int
) -> None:
    rec = SimpleNamespace(ticks_done=n_ticks, drone_ids=list(range(n_drones)), t=np.arange(n_ticks) * dt)
    s = ct.stride(rec)  # type: ignore[arg-type]
    assert s == stride
    assert len(range(0, n_ticks, s)) * n_drones <= ct.MAX_ROWS


def test_numbers_round_and_huge_values_still_read() -> None:
    """Fixed point for the usual values, Python's repr for a diverged one; both read back by pandas."""
    rec = _recording("none", 3, 0.05, 0)
    rec.g_wi[2, 0, 1] = 3.5e15  # beyond the fixed point's range (a diverged flight)
    rec.g_w0[1, 3] = -np.inf
    from io import BytesIO

    df = pd.read_csv(BytesIO(ct.csv_bytes([rec])))
    assert df["y"].iloc[6] == 3.5e15 and np.isnan(df["target_theta"].iloc[3:6]).all()
    check_csv(df, rec)
