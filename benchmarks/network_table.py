"""The emulated lab under each network profile: does the flight hold, and what does the radio cost?

    python benchmarks/network_table.py                      # every profile, 30 s per mode (~10 min)
    python benchmarks/network_table.py --profiles clean,outage --duration 20
    python benchmarks/network_table.py --links perfect      # the radio alone, without the Tello's delays
    python benchmarks/network_table.py --update-docs        # also rewrite docs/links.md's table

Per profile (docs/links.md) it flies `flightstack run paper_experiment --rig emulated-lab --network P
--links L` (L: the rig's links profile, default `tello`: a Tello's own video, state and rc delays)
(the data run, training, then modes none, local and dgp, each for --duration s of pursuit; the
experiment's seed),
through the real drivers, decoders and safety layer on the wall clock, and reads back the run directory:

- loop: whether the loop kept dt (analysis.loop_health: ≤ 1 % overruns, compute p99 < dt) and its
  overrun fraction;
- failsafe events (FAILSAFE_KINDS, and command_timeout while the loop should command): on a profile
  without blackouts every one of them is false;
- frames: per mode, summed over the drones, the frames the receivers published, the distinct frames the
  loop looked at, the damaged frames dropped and the resynchronisations (recording `video_counts`), and
  the ticks whose frame was older than `max_frame_age_s` ("stale frame" rejections);
- frame age (from capture, as stamped) p50/p99 over the drones; pursuit error: the mean position error
  (m); dgp against local: the ratio of their errors;
- outages: for every blackout of a drone's radio that began while a mode flew, the time from its start to
  the safety layer's `link_lost` for that drone and to the drone's own landing (the emulator's phase).

Not a test (it flies in real time, minutes per profile); one seed per profile, so an error difference
between profiles smaller than about 0.02 m is noise (docs/experiments.md gives the seed spread).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.table import DOCS, write_block  # noqa: E402

PROFILES = ("clean", "lab-wifi", "crowded", "outage")
MODES = ("none", "local", "dgp")
FAILSAFE_KINDS = (
    "link_lost", "pose_stale_hover", "pose_stale_land", "target_lost_hover", "target_lost_land", "land_all",
    "landed_by_drone", "loop_lost_land", "takeoff_failed", "land_failed",
)  # fmt: skip
"""Safety reactions (events.jsonl kinds) that a network without blackouts must never cause."""
MISSION_END = "mission complete"
"""The detail of the `land_all` that ends every mode: not a reaction."""


def results_file(links: str) -> Path:
    """Where a run of the table with the rig's links `links` keeps its results."""
    return REPO / "benchmarks" / f"network_table_{links}.json"


PAGE = DOCS / "links.md"


def fly(profile: str, links: str, duration_s: float, out: Path, seed: int | None = None) -> tuple[int, float]:
    """One run of paper_experiment on the emulated lab under network `profile` and links `links` (seed:
    the experiment's when None): (exit code, wall s)."""
    t0 = time.monotonic()
    experiment = "paper_experiment"
    if seed is not None:  # `run` takes no seed (a sweep's): the experiment's file with its seed replaced
        text = (REPO / "mission_configs" / "paper_experiment.yaml").read_text()
        seeded = re.sub(r"(?m)^seed: \d+", f"seed: {int(seed)}", text, count=1)
        if seeded == text and seed != 0:
            raise RuntimeError("paper_experiment.yaml has no top-level `seed:` line to replace")
        out.parent.mkdir(parents=True, exist_ok=True)
        experiment = str(out.parent / f"paper_experiment_seed{seed}.yaml")
        Path(experiment).write_text(seeded)
    cmd = [
        sys.executable, "-m", "flightstack", "run", experiment, "--rig", "emulated-lab",
        "--network", profile, "--links", links, "--duration", str(duration_s), "--out", str(out),
        "--no-progress",
    ]  # fmt: skip
    with open(out.parent / f"{profile}.log", "w") as log:
        r = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, timeout=40 * duration_s + 600)
    return r.returncode, time.monotonic() - t0


def _events(run: Path) -> list[dict[str, Any]]:
    p = run / "events.jsonl"
    if not p.exists():
        return []
    out = []
    for line in p.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def _mode_spans(events: list[dict[str, Any]]) -> dict[str, tuple[float, float]]:
    """Mode → (first, last) event time (s, mission clock): when each mode flew, roughly."""
    spans: dict[str, tuple[float, float]] = {}
    for e in events:
        m, t = e.get("mode"), e.get("t")
        if not isinstance(m, str) or not isinstance(t, int | float):
            continue
        a, b = spans.get(m, (t, t))
        spans[m] = (min(a, t), max(b, t))
    return spans


def outage_reactions(run: Path, events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per blackout of a drone's radio that began while a mode flew: its length, the delay to the
    safety layer's link_lost for that drone, and to the drone's landing phase (emulator), s."""
    logp = next(iter(run.rglob("network_log.json")), None)
    if logp is None:
        return []
    log = json.loads(logp.read_text())
    t0 = float(log["t0_monotonic"])
    spans = _mode_spans(events)
    out = []
    for dev, windows in (log.get("blackouts") or {}).items():
        if not dev.startswith("tello"):
            continue
        drone = int(dev[5:])
        phases = [(t0 + t, p) for t, p in log.get(dev, {}).get("phase_log", [])]
        for a_rel, b_rel in windows:
            a, b = t0 + a_rel, t0 + b_rel
            flying = [p for t, p in phases if t <= a]
            if not flying or flying[-1] != "flying":
                continue  # the drone was not flying when its radio went out
            mode = next((m for m, (s, e) in spans.items() if s <= a <= e), None)
            lost = [e["t"] for e in events if e.get("kind") == "link_lost" and e.get("drone") == drone
                    and a <= e["t"] <= a + 10.0]  # fmt: skip
            landing = [t for t, p in phases if t >= a and p in ("landing", "landed")]
            out.append({
                "drone": drone, "mode": mode, "blackout_s": b - a,
                "link_lost_after_s": (min(lost) - a) if lost else None,
                "landing_after_s": (landing[0] - a) if landing else None,
                "landing_after_return_s": (landing[0] - b) if landing else None,
            })  # fmt: skip
    return out


def summarise(profile: str, run: Path, code: int | None, wall_s: float) -> dict[str, Any]:
    """What the table shows for one profile's run (module docstring)."""
    mp = run / "metrics.json"
    metrics = json.loads(mp.read_text()) if mp.exists() else {}
    events = _events(run)
    rows: dict[str, Any] = {}
    for mode in MODES:
        m = (metrics.get("modes") or {}).get(mode)
        if not m:
            continue
        h = m.get("loop_health") or {}
        video = m.get("video_counts") or {}

        def total(key: str, video: dict[str, Any] = video) -> int:
            return int(sum(c.get(key, 0) for c in video.values()))

        stale = sum(int(r.get("stale frame", 0)) for r in (m.get("vision_rejections") or {}).values())
        mine = [e for e in events if e.get("mode") == mode and isinstance(e.get("t"), int | float)]
        took_off = [e["t"] for e in mine if e.get("kind") == "takeoff"]
        landed = [e["t"] for e in mine if e.get("kind") == "land"]
        # the loop's silence counts while it should command: after the start-up's own timeouts (3 s
        # after takeoff), before the mode's landing
        a, b = (max(took_off) + 3.0 if took_off else np.inf), (min(landed) if landed else np.inf)
        failsafe = [
            e for e in mine
            if (e.get("kind") in FAILSAFE_KINDS and not str(e.get("detail", "")).startswith(MISSION_END))
            or (e.get("kind") == "command_timeout" and a < e["t"] < b)
        ]  # fmt: skip
        fa = h.get("frame_age_s") or {}
        rows[mode] = {
            "keeps_dt": h.get("keeps_dt"),
            "overrun_fraction": h.get("overrun_fraction"),
            "failsafe_events": sorted({str(e.get("kind")) for e in failsafe}),
            "n_failsafe_events": len(failsafe),
            "frames_published": total("frames"),
            "frames_seen": total("frames_seen"),
            "frames_concealed": total("concealed"),
            "gate": _gate_totals(m.get("vision_gate") or {}),
            "resyncs": total("resync"),
            "stale_frame_ticks": stale,
            "frame_age_p50_s": fa.get("p50"),
            "frame_age_p99_s": fa.get("p99"),
            "mean_position_error_m": m.get("mean_position_error_m"),
            "visible_fraction": m.get("visible_fraction"),
            "sim_seconds": m.get("sim_seconds"),
            "error": m.get("error"),
        }
    local, dgp = rows.get("local", {}), rows.get("dgp", {})
    ratio = None
    if local.get("mean_position_error_m") and dgp.get("mean_position_error_m") is not None:
        ratio = dgp["mean_position_error_m"] / local["mean_position_error_m"]
    return {
        "profile": profile, "exit_code": code, "wall_s": wall_s, "modes": rows, "dgp_over_local": ratio,
        "outages": outage_reactions(run, events), "run_error": metrics.get("error"),
    }  # fmt: skip


def _gate_totals(per_drone: dict[str, dict[str, int]]) -> dict[str, int]:
    """The detection gate's counts (runtime.tick_record.GATE_COUNTS) summed over the drones."""
    out: dict[str, int] = {}
    for c in per_drone.values():
        for k, v in c.items():
            out[k] = out.get(k, 0) + int(v)
    return out


def _gate_cell(g: dict[str, int]) -> str:
    """accepted / rejected; accepted from damaged frames more than 3 / 10 px from the truth."""
    if not g:
        return "–"
    return (f"{g.get('accepted', 0)} / {g.get('rejected', 0)}; {g.get('accepted_damaged_over_3px', 0)} / "
            f"{g.get('accepted_damaged_over_10px', 0)} of {g.get('accepted_damaged', 0)}")  # fmt: skip


def _ms(v: float | None) -> str:
    return "–" if v is None else f"{1e3 * v:.0f}"


def markdown(results: list[dict[str, Any]], duration_s: float, links: str) -> str:
    """The table of docs/links.md (one row per profile × mode) and the outage reactions."""
    lines = [
        f"Measured by `python benchmarks/network_table.py --links {links} --duration {duration_s:g}` "
        f"({time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores; one seed per profile).",
        "",
        "| profile | mode | keeps dt (overruns) | false failsafe events | frames published / seen / "
        "concealed / resyncs | stale-frame ticks | detections accepted / rejected; accepted from damaged "
        "frames > 3 / > 10 px off | frame age p50 / p99 (ms) | mean position error (m) | seen (drone 1) "
        "| dgp / local |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for mode, row in r["modes"].items():
            keeps = {True: "yes", False: "**no**", None: "–"}[row["keeps_dt"]]
            over = row["overrun_fraction"]
            keeps += "" if over is None else f" ({100 * over:.1f} %)"
            if r["profile"] == "outage":
                false = f"(outage: {row['n_failsafe_events']} reactions)"
            else:
                false = str(row["n_failsafe_events"]) + (
                    f" ({', '.join(row['failsafe_events'])})" if row["failsafe_events"] else ""
                )
            frames = (f"{row['frames_published']} / {row['frames_seen']} / {row['frames_concealed']} / "
                      f"{row['resyncs']}")  # fmt: skip
            seen = (row.get("visible_fraction") or {}).get("1")
            err = row["mean_position_error_m"]
            ratio = r["dgp_over_local"] if mode == "dgp" and r["dgp_over_local"] is not None else None
            lines.append(
                f"| {r['profile']} | {mode} | {keeps} | {false} | {frames} | {row['stale_frame_ticks']} | "
                f"{_gate_cell(row['gate'])} | {_ms(row['frame_age_p50_s'])} / "
                f"{_ms(row['frame_age_p99_s'])} | {'–' if err is None else f'{err:.3f}'} | "
                f"{'–' if seen is None else f'{100 * seen:.1f} %'} | "
                f"{'' if ratio is None else f'{ratio:.2f}'} |"
            )
    for r in results:
        if r["run_error"] or r["exit_code"]:
            code = "" if r["exit_code"] is None else f"exit {r['exit_code']}: "
            lines.append(f"\n`{r['profile']}`: {code}{r['run_error'] or 'see its log'}")
    outages = [o for r in results for o in r["outages"]]
    if outages:
        lost = [o["link_lost_after_s"] for o in outages if o["link_lost_after_s"] is not None]
        back = [o["landing_after_return_s"] for o in outages if o["landing_after_return_s"] is not None]
        lines += [
            "",
            f"Outages (profile `outage`): {len(outages)} blackouts of a flying drone's radio "
            f"({min(o['blackout_s'] for o in outages):.1f}–{max(o['blackout_s'] for o in outages):.1f} s); "
            f"`link_lost` {len(lost)} times, "
            + (f"{np.median(lost):.2f} s after the blackout began (max {max(lost):.2f} s); " if lost else "")
            + (f"the drone landing {np.median(back):.2f} s after its radio returned (max {max(back):.2f} s)."
               if back else "no landing seen."),
        ]  # fmt: skip
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profiles", default=",".join(PROFILES))
    ap.add_argument("--duration", type=float, default=30.0, help="s of pursuit per mode")
    ap.add_argument("--links", choices=("perfect", "tello"), default="tello", help="the rig's links profile")
    ap.add_argument("--out", type=Path, default=None, help="keep the run directories here")
    ap.add_argument("--seed", type=int, default=None, help="the experiment's seed (default: its own)")
    ap.add_argument("--update-docs", action="store_true")
    ap.add_argument(
        "--read", type=Path, default=None, help="tabulate the run directories of an earlier --out DIR again"
    )
    args = ap.parse_args()
    profiles = [p for p in args.profiles.split(",") if p]
    unknown = sorted(set(profiles) - set(PROFILES))
    if unknown:
        print(f"error: unknown profiles {unknown}; known: {', '.join(PROFILES)}", file=sys.stderr)
        return 2
    root = args.read or args.out or Path(tempfile.mkdtemp(prefix="network_table-"))
    root.mkdir(parents=True, exist_ok=True)
    results = []
    for p in profiles:
        code: int | None
        if args.read is not None:
            if not (root / p).is_dir():
                continue
            code, wall = None, float("nan")  # the exit code was not kept; metrics.json says the error
        else:
            code, wall = fly(p, args.links, args.duration, root / p, args.seed)
        r = summarise(p, root / p, code, wall)
        results.append(r)
        print(f"{p}: exit {code}, {wall:.0f} s; " + "; ".join(
            f"{m}: err {row['mean_position_error_m']}, keeps dt {row['keeps_dt']}, "
            f"failsafe {row['n_failsafe_events']}" for m, row in r["modes"].items()), flush=True)  # fmt: skip
    table = markdown(results, args.duration, args.links)
    print(table)
    if args.read is None:  # a re-read keeps the file of the run itself (its exit codes, wall times)
        results_file(args.links).write_text(
            json.dumps({"duration_s": args.duration, "links": args.links, "results": results}, indent=1)
            + "\n"
        )
    if args.update_docs:
        write_block(PAGE, f"network-table:{args.links}", table)
    print(f"run directories: {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
