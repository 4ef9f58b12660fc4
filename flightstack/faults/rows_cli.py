"""The rows of `flightstack faults` that exercise the command line in a subprocess: a malformed mission
file and SIGINT mid-flight. Each is a FaultRow: (mission file, work directory) -> FaultResult.

The subprocess is `python -m flightstack.cli.app` run from the repository root with it on PYTHONPATH, so the
rows test the code of this checkout even when another copy is installed.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from flightstack.config.mission import load_mission
from flightstack.config.rig import resolved_document
from flightstack.faults.result import Checks, FaultResult, FaultRow
from flightstack.recording.timeseries import Recording
from flightstack.runtime.runner import safety_limits
from flightstack.safety import outside_hard_fence

CLI_TIMEOUT_S = 60.0
SIGINT_AFTER_S = 1.5
"""Wall seconds between the first tick counted on `flightstack sim`'s progress bar and SIGINT (the drones
are then in pursuit: takeoff takes 2 s of simulated time, about 0.3 s of wall time)."""
_BAR_COUNT = re.compile(r"mode none\s*:[^|\r\n]*\|[^|\r\n]*\|\s*([\d.]+)([kMG]?)/")
"""The tick count of a `mode none` progress bar line (tqdm: `mode none  :  1%|▏  | 150/12.0k [...]`)."""


def bar_ticks(text: str) -> float:
    """The largest tick count the `mode none` progress bars in `text` show (0 if none does)."""
    scale = {"": 1.0, "k": 1e3, "M": 1e6, "G": 1e9}
    return max((float(n) * scale[u] for n, u in _BAR_COUNT.findall(text)), default=0.0)


def cli_command(*args: str) -> list[str]:
    """`flightstack ARGS` run by this interpreter (the installed package: no checkout needed)."""
    return [sys.executable, "-m", "flightstack", *args]


def cli_env() -> dict[str, str]:
    """The child's environment: this process's."""
    return dict(os.environ)


def run_cli(*args: str, timeout: float = CLI_TIMEOUT_S) -> subprocess.CompletedProcess[str]:
    """`flightstack ARGS` in a subprocess (bounded by `timeout` s)."""
    return subprocess.run(cli_command(*args), capture_output=True, text=True, timeout=timeout, env=cli_env())


# ---- malformed mission file --------------------------------------------------------------------------------
def malformed_variants(mission_path: Path) -> dict[str, tuple[str, str]]:
    """name -> (file text, the text stderr must contain): one defect each, on a copy of the mission."""
    text = Path(mission_path).read_text(encoding="utf-8")
    base = Path(mission_path).resolve().parent

    def variant(edit: Any) -> str:
        data = resolved_document(mission_path)  # the experiment on its rig, calibrations absolute
        edit(data)
        return yaml.safe_dump(data, sort_keys=False)

    def unknown_key(d: dict[str, Any]) -> None:
        d["drones"][0]["speed"] = 3.0

    def bad_value(d: dict[str, Any]) -> None:
        d["dt_s"] = -0.05

    def missing_file(d: dict[str, Any]) -> None:
        d["drones"][-1]["camera"]["calibration"] = str(base / "cameras" / "no_such_calibration.yaml")

    last = len(resolved_document(mission_path)["drones"]) - 1
    return {
        "yaml_syntax": (text + "\nextra: [unclosed\n", "not valid YAML"),
        "unknown_key": (variant(unknown_key), "drones.0.speed: unknown key"),
        "bad_value": (variant(bad_value), "dt_s: Input should be greater than or equal to 0.0001"),
        "missing_file": (variant(missing_file), f"drones.{last}.camera.calibration: file not found"),
    }


def malformed_mission(mission_path: Path, workdir: Path) -> FaultResult:
    """`flightstack validate` on four broken copies of the mission, `flightstack sim` on one."""
    wall0 = time.perf_counter()
    expected = "validate and sim exit 2 naming the key path and the reason; nothing flies, nothing is written"
    root = workdir / "malformed_mission"
    root.mkdir(parents=True, exist_ok=True)
    c, crash, notes = Checks(), Checks(), []
    out_dirs = []
    for name, (body, token) in malformed_variants(mission_path).items():
        path = root / f"{name}.yaml"
        path.write_text(body, encoding="utf-8")
        commands: list[tuple[str, ...]] = [("validate", str(path))]
        if name == "unknown_key":
            out = root / f"out_{name}"
            out_dirs.append(out)
            commands.append(("sim", str(path), "--out", str(out), "--no-progress"))
        for cmd in commands:
            try:
                r = run_cli(*cmd)
            except subprocess.TimeoutExpired:
                crash.check(False, f"{cmd[0]} {name}: no answer in {CLI_TIMEOUT_S:g} s")
                continue
            crash.check("Traceback" not in r.stderr, f"{cmd[0]} {name}: traceback: {r.stderr[-500:]}")
            c.check(r.returncode == 2, f"{cmd[0]} {name}: exit {r.returncode}")
            c.check(token in r.stderr, f"{cmd[0]} {name}: stderr lacks {token!r}: {r.stderr[-300:]}")
            named = f" '{token}'" if token in r.stderr else ""
            notes.append(f"{cmd[0]} {name}: exit {r.returncode}{named}")
    written = [str(o) for o in out_dirs if o.exists()]
    problems = [f"reaction: {p}" for p in c.failed] + [f"crashed: {p}" for p in crash.failed]
    if written:
        problems.append(f"recording: run directory written for a bad mission: {written}")
    return FaultResult(
        name="malformed_mission",
        expected=expected,
        observed="; ".join(notes) + ("; nothing written" if not written else f"; WROTE {written}"),
        all_safe=not written,  # nothing may take off: sim must stop before creating the run directory
        recording_complete=not written,  # no partial run directory
        crashed=not crash.ok,
        seconds=time.perf_counter() - wall0,
        reaction_ok=c.ok,
        problems=problems,
    )


# ---- SIGINT mid-flight -------------------------------------------------------------------------------------
def interrupt_sim(mission_path: Path, out: Path, after_s: float = SIGINT_AFTER_S) -> tuple[int | None, str]:
    """Start `flightstack sim MISSION --out OUT --duration 600`, wait until its progress bar counts a tick
    (the bar is drawn before the fleet is assembled, which a busy computer can take seconds for), let it
    fly `after_s` wall seconds, send SIGINT; (exit code or None if it had to be killed, stderr)."""
    proc = subprocess.Popen(
        # --progress: its stderr is a pipe, and a bar that counts ticks is the sign that the drones fly
        cli_command("sim", str(mission_path), "--out", str(out), "--duration", "600", "--progress"),
        env=cli_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    buf = ""
    try:
        deadline = time.monotonic() + CLI_TIMEOUT_S
        counted = False
        while not counted and time.monotonic() < deadline and proc.poll() is None:
            ch = proc.stderr.read(1) if proc.stderr else ""
            buf += ch
            counted = ch == "]" and bar_ticks(buf[-400:]) > 0  # tqdm ends each bar with "]"
        time.sleep(after_s)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=CLI_TIMEOUT_S)
        return proc.returncode, buf + err
    except subprocess.TimeoutExpired:
        return None, buf
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def sigint_mid_flight(mission_path: Path, workdir: Path) -> FaultResult:
    """SIGINT to `flightstack sim` while the drones pursue the target."""
    wall0 = time.perf_counter()
    expected = (
        "every drone lands (land_all from the signal handler: signal SIGINT), the partial recording and "
        "metrics are written, exit 130"
    )
    out = workdir / "sigint" / "run"
    code, stderr = interrupt_sim(mission_path, out)
    mission = load_mission(mission_path)
    ids = [d.id for d in mission.drones]
    react, safe, rec_c = Checks(), Checks(), Checks()
    crashed = code is None or "Traceback" in stderr
    react.check(code == 130, f"exit code {code}")
    events: list[dict[str, Any]] = []
    if rec_c.check((out / "events.jsonl").is_file(), "events.jsonl not written"):
        events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    ends = [e for e in events if e.get("event") == "end"]
    react.check(len(ends) == 1 and ends[0].get("reason") == "interrupted", f"end events {ends}")
    land_all = [e for e in events if e.get("kind") == "land_all"]
    react.check(bool(land_all) and "signal SIGINT" in str(land_all[0]["detail"]), f"land_all {land_all}")
    for i in ids:
        fate = [e for e in events if e.get("drone") == i and e.get("event") in ("landed", "NOT LANDED")]
        ok = len(fate) == 1 and fate[0]["event"] == "landed" and float(fate[0]["height_m"]) <= 0.01
        safe.check(ok, f"drone {i}: {fate}")
    ticks = 0
    if rec_c.check((out / "metrics.json").is_file(), "metrics.json not written"):
        m = json.loads((out / "metrics.json").read_text())
        react.check(m.get("interrupted") is True, "metrics: interrupted is not true")
        ticks = int(m.get("modes", {}).get("none", {}).get("ticks", -1))
    npz = out / "timeseries_none.npz"
    t_last = float("nan")
    if rec_c.check(npz.is_file(), "timeseries_none.npz not written"):
        rec = Recording.load(str(npz))
        k = rec.ticks_done
        t_last = float(rec.t[-1]) if k else t_last
        react.check(k > 0, "interrupted before pursuit (no tick recorded)")
        rec_c.check(k == ticks, f"{k} ticks saved, metrics say {ticks}")
        for f in ("t", "g_w0", "g_wi", "g_bar_w", "e_c", "e_e", "V_cmd"):
            rec_c.check(bool(np.all(np.isfinite(getattr(rec, f)))), f"{f} not finite")
        if k > 1:
            rec_c.check(bool(np.allclose(np.diff(rec.t), mission.dt_s, rtol=1e-6)), "ticks not every dt")
        limits = safety_limits(mission)
        beyond = sum(1 for p in rec.g_wi.reshape(-1, 4)[:, :3] if outside_hard_fence(p, limits, False))
        safe.check(beyond == 0, f"beyond the hard fence on {beyond} drone-ticks")
    problems = [f"reaction: {p}" for p in react.failed] + [f"safety: {p}" for p in safe.failed]
    problems += [f"recording: {p}" for p in rec_c.failed]
    if crashed:
        problems.insert(0, f"crashed: exit {code}: {stderr[-800:]}")
    landed = [e["drone"] for e in events if e.get("event") == "landed"]
    observed = (
        f"exit {code}; SIGINT @{ends[0]['t'] if ends else float('nan'):.2f} after {ticks} ticks (last "
        f"t={t_last:.2f}); land_all: {land_all[0]['detail'] if land_all else 'none'}; landed {landed}"
    )
    return FaultResult(
        name="sigint",
        expected=expected,
        observed=observed,
        all_safe=safe.ok,
        recording_complete=rec_c.ok,
        crashed=crashed,
        seconds=time.perf_counter() - wall0,
        reaction_ok=react.ok,
        problems=problems,
        details={"run_dir": str(out)},
    )


ROWS: dict[str, FaultRow] = {
    "malformed_mission": malformed_mission,
    "sigint": sigint_mid_flight,
}
"""The command-line rows, in table order."""
