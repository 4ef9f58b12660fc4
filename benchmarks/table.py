"""The benchmark table: targets, PASS/MISS per row, the terminal and markdown renderings, machine facts;
the generated blocks of the docs pages.

Used by benchmarks/run.py (which measures); kept apart so that the measuring code reads on its own."""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = REPO / "docs"
BENCH_PAGE = DOCS / "performance.md"
"""The docs page that holds the benchmark table (block `bench`)."""

#: performance targets (value, unit, "max" = measured must be ≤ target, "min" = ≥ target)
TARGETS = {
    "tick_us_M10": (30.0, "µs per agent tick, M = 10", "max"),
    "tick_us_M1000_shared": (500.0, "µs per agent tick, M = 1000, one kernel for the outputs", "max"),
    "sim_per_wall": (200.0, "paper simulation's flown modes, sim s per wall s", "min"),
    "sim_per_wall_31": (10.0, "31 drones, sim s per wall s", "min"),
    "process_quiet_s": (3.5, "s for the whole `flightstack run paper_sim` process, warm, quiet", "max"),
    "process_loaded_s": (8.0, "s for the whole process beside two CPU-bound processes", "max"),
    "train_loaded_s": (1.0, "s of GP training, each warm run beside two CPU-bound processes", "max"),
    "sweep_20_s": (60.0, "s for a 20-seed sweep of the paper simulation", "max"),
    "lab_sweep_20_s": (60.0, "s for a 20-seed sweep of the paper's experiment on the simulated lab", "max"),
    "vision_fps": (300.0, "frames/s at 960×720", "min"),
    "zenoh_p50_ms": (0.3, "ms Zenoh hop p50", "max"),
}


def _pct_ms(d: dict, q: str) -> float | None:
    """p50/p99 in ms from a latency dict whatever its unit suffix (p50_ms, p50_us, p50_s, p50)."""
    for key, scale in ((f"{q}_ms", 1.0), (f"{q}_us", 1e-3), (f"{q}_ns", 1e-6), (f"{q}_s", 1e3), (q, 1e3)):
        if key in d and d[key] is not None:
            return float(d[key]) * scale
    return None


def _status(key: str, measured: float | None) -> tuple[str, str, str]:
    """(target text, measured/target ratio text, PASS/MISS) for one of TARGETS."""
    target, _unit, kind = TARGETS[key]
    if measured is None:
        return (f"{'≤' if kind == 'max' else '≥'} {target:g}", "n/a", "N/A")
    ok = measured <= target if kind == "max" else measured >= target
    ratio = measured / target
    return (
        f"{'≤' if kind == 'max' else '≥'} {target:g}",
        f"{ratio:.3g}× of target",
        "PASS" if ok else "MISS",
    )


def build_rows(r: dict) -> list[tuple[str, str, str, str, str]]:
    """(benchmark, measured, compared with, ratio, target/status) rows shared by console and docs page."""
    rows: list[tuple[str, str, str, str, str]] = []
    for M, g in r["gp_predict_one"].items():
        rows.append(
            (
                f"GP predict_one (mean + var, 1 point), M = {M}",
                f"{g['ours_us']:.1f} µs",
                f"sklearn {g['sklearn_us']:.0f} µs",
                f"{g['speedup']:.1f}× faster",
                "",
            )
        )
    for t in r["gp_train"]:
        cap = "to tolerance" if t["maxiter"] is None else f"≤ {t['maxiter']} L-BFGS-B iterations"
        n = t["N"]
        rows.append(
            (
                f"GP LML+grad eval, pooled N = {n} vs 3 experts × {n // 3}",
                f"{t['eval_3_experts_s'] * 1e3:.1f} ms",
                f"pooled {t['eval_pooled_s'] * 1e3:.1f} ms",
                f"{t['eval_ratio_pooled_over_experts']:.1f}× (pooled / experts)",
                "",
            )
        )
        rows.append(
            (
                f"GP fit (1 output, 1 restart, {cap}), N = {n}: 3 experts vs pooled",
                f"{t['fit_3_experts_s']:.2f} s",
                f"pooled {t['fit_pooled_s']:.2f} s",
                f"{t['fit_ratio_pooled_over_experts']:.1f}× (pooled / experts)",
                "",
            )
        )
        rows.append(
            (
                f"GP fit pooled N = {n}: ours vs sklearn (same start/bounds/optimiser)",
                f"{t['fit_pooled_s']:.2f} s, LML {t['lml_ours_pooled']:.2f}",
                f"sklearn {t['fit_sklearn_s']:.2f} s, LML {t['lml_sklearn_pooled']:.2f}",
                f"{t['fit_ratio_sklearn_over_ours']:.2f}× faster, "
                f"ΔLML {t['lml_ours_minus_sklearn']:+.2g} nats",
                "",
            )
        )
    rows += _sim_rows(r)
    v = r["vision"]
    tgt, ratio, st = _status("vision_fps", v["fps"])
    rows.append(
        (
            "marker extraction, 960×720, 4 markers in view",
            f"{v['ms_per_frame']:.2f} ms ({v['fps']:.0f} fps)",
            f"render {v['render_ms_per_frame']:.2f} ms",
            f"{v['fps'] / 30:.1f}× a 30 fps camera; {ratio}",
            f"{tgt} fps: {st}",
        )
    )
    b = r["bus"]
    ip = b["inproc"]
    rows.append(
        (
            "bus hop in-process (encode → publish → latest)",
            f"p50 {ip['p50_ms'] * 1e3:.1f} µs, p99 {ip['p99_ms'] * 1e3:.1f} µs",
            "dt = 2 ms",
            f"{2.0 / ip['p50_ms']:.0f}× inside one tick (p50)",
            "",
        )
    )
    z = b.get("zenoh")
    if z:
        p50, p99 = _pct_ms(z, "p50"), _pct_ms(z, "p99")
        tgt, ratio, st = _status("zenoh_p50_ms", p50)
        rows.append(
            (
                "bus hop Zenoh (benchmarks/zenoh_hop.py)",
                f"p50 {p50:.3f} ms, p99 {p99:.3f} ms" if p50 is not None and p99 is not None else str(z),
                f"in-process p50 {ip['p50_ms']:.4f} ms",
                (f"{p50 / ip['p50_ms']:.0f}× in-process; {ratio}" if p50 is not None else ratio),
                f"{tgt} ms: {st}",
            )
        )
    else:
        tgt, _, _ = _status("zenoh_p50_ms", None)
        rows.append(("bus hop Zenoh", str(b["zenoh_status"]), "", "", f"{tgt} ms: N/A"))
    return rows


def _sim_rows(r: dict) -> list[tuple[str, str, str, str, str]]:
    """Agent tick, paper simulation, drones and sweep rows (benchmarks/sim_speed.py)."""
    tk, rows = r["agent_tick"], []
    t10 = tk["M10"]["per_agent_us"]
    tgt, ratio, st = _status("tick_us_M10", t10)
    rows.append(
        (
            "agent tick (observer, predict, publish, fuse, control), M = 10, 2 neighbours",
            f"{t10:.1f} µs",
            "dt = 2 ms",
            f"{tk['M10']['dt_over_tick']:.0f}× real time; {ratio}",
            f"{tgt} µs: {st}",
        )
    )
    for key, label in (("M100", "M = 100"), ("M1000", "M = 1000")):
        rows.append(
            (
                f"agent tick, {label} (one kernel per output, the paper's model)",
                f"{tk[key]['per_agent_us']:.0f} µs",
                f"M = 10: {t10:.1f} µs",
                f"{tk[key]['per_agent_us'] / t10:.1f}× slower; {tk[key]['dt_over_tick']:.1f}× real time",
                "",
            )
        )
    sh, acc = tk["M1000_shared"]["per_agent_us"], r["shared_kernel"]
    tgt, ratio, st = _status("tick_us_M1000_shared", sh)
    rows.append(
        (
            "agent tick, M = 1000, gp.output_kernel: shared",
            f"{sh:.0f} µs",
            f"per output: {tk['M1000']['per_agent_us']:.0f} µs",
            f"{tk['M1000']['per_agent_us'] / sh:.1f}× faster; {ratio}",
            f"{tgt} µs: {st}",
        )
    )
    rows.append(
        (
            "accuracy of gp.output_kernel: shared, M = 1000 (RMS error of μ vs the true field)",
            f"{acc['rmse_shared']:.4f} m/s",
            f"per output {acc['rmse_exact']:.4f} m/s",
            f"RMS difference {acc['rms_difference']:.4f} m/s; var ratio {acc['median_var_ratio']:.2f}",
            "",
        )
    )
    for n in (10, 30):
        key = f"n{n + 1}"
        rows.append(
            (
                f"agent tick, M = 10, {n} neighbours ({n + 1} drones)",
                f"{tk[key]['per_agent_us']:.1f} µs",
                f"2 neighbours: {t10:.1f} µs",
                f"{tk[key]['per_agent_us'] / t10:.2f}×",
                "",
            )
        )
    ps = r["paper_sim"]
    tgt, ratio, st = _status("sim_per_wall", ps["loop_sim_per_wall"])
    rows.append(
        (
            "paper simulation, flown modes none + local + dgp (3 × 40 s), compiled loop",
            " / ".join(f"{ps['modes'][k]['wall_s']:.2f}" for k in ("none", "local", "dgp")) + " s",
            "real time 40 s each",
            f"{ps['loop_sim_per_wall']:.0f}× real time; {ratio}",
            f"{tgt}×: {st}",
        )
    )
    rows.append(
        (
            "`flightstack run paper_sim`, whole command (warm cache, training, plots)",
            f"{ps['command_s']:.1f} s",
            "120 s simulated",
            f"{ps['command_sim_per_wall']:.0f}× real time",
            "",
        )
    )
    wp = r.get("whole_process") or {}
    for case, key, what in (
        ("quiet", "process_quiet_s", "as the machine is"),
        ("quiet_no_live_mcap", "process_quiet_s", "as the machine is, `--no-live-mcap`"),
        ("loaded", "process_loaded_s", "beside two CPU-bound processes"),
    ):
        if case not in wp:
            continue
        c = wp[case]
        tgt, ratio, st = _status(key, c["median_wall_s"])
        rows.append(
            (
                f"`flightstack run paper_sim`, whole process (start to exit, warm), {what}, "
                f"median of {len(c['wall_s'])}",
                f"{c['median_wall_s']:.1f} s ({min(c['wall_s']):.1f}–{max(c['wall_s']):.1f}); "
                f"CPU {c['median_cpu_s']:.1f} s",
                f"load {c['load'][0]:.1f} → {c['load'][1]:.1f}",
                ratio,
                f"{tgt} s: {st}",
            )
        )
    if "train_s" in wp.get("loaded", {}):
        trains = wp["loaded"]["train_s"]
        tgt, ratio, st = _status("train_loaded_s", max(trains))
        rows.append(
            (
                "GP training inside those runs beside two CPU-bound processes (metrics.json "
                f"gp.train_seconds), largest of {len(trains)}",
                f"{max(trains):.2f} s (median {float(np.median(trains)):.2f} s; "
                f"{sum(t <= TARGETS['train_loaded_s'][0] for t in trains)} of {len(trains)} within target)",
                "each run",
                ratio,
                f"{tgt} s each: {st}",
            )
        )
    dr = r["drones"]
    tgt, ratio, st = _status("sim_per_wall_31", dr["31"]["sim_per_wall"])
    rows.append(
        (
            "simulation speed, 3 / 11 / 31 drones (dgp, compiled loop)",
            " / ".join(f"{dr[k]['sim_per_wall']:.0f}" for k in ("3", "11", "31")) + "× real time",
            "3 drones",
            f"31 drones {dr['31']['sim_per_wall'] / dr['3']['sim_per_wall']:.2f}× of 3; {ratio}",
            f"{tgt}× (31): {st}",
        )
    )
    sw = r["sweep"]
    tgt, ratio, st = _status("sweep_20_s", sw["wall_s"])
    rows.append(
        (
            f"`flightstack sweep paper_sim --seeds {sw['seeds']}` (3 modes each), {sw['jobs']} jobs",
            f"{sw['wall_s']:.1f} s",
            f"one run: {ps['command_s']:.1f} s",
            f"{sw['seeds'] * ps['command_s'] / sw['wall_s']:.1f}× faster than {sw['seeds']} single commands "
            f"(a sweep run writes no plots or recordings); {ratio}",
            f"{tgt} s: {st}",
        )
    )
    rows.extend(_lab_rows(r))
    return rows


def _lab_rows(r: dict) -> list[tuple[str, str, str, str, str]]:
    """The simulated lab's rows: one run and the 20-seed sweep, rendered camera against `centres`."""
    rows: list[tuple[str, str, str, str, str]] = []
    run, sweep = r.get("lab_run"), r.get("lab_sweep")
    if run:
        img, fast = run["image"], run["centres"]
        rows.append(
            (
                "`paper_experiment` on lab-sim, one run (3 modes × 80 s, training incl.), sim s per wall s",
                f"{img['sim_per_wall']:.1f} / {fast['sim_per_wall']:.1f}",
                "rendered camera / `sim.render.model: centres`",
                f"centres {fast['sim_per_wall'] / img['sim_per_wall']:.1f}× faster",
                "",
            )
        )
    if sweep:
        img, fast = sweep["image"], sweep["centres"]
        for name, s in (("rendered camera", img), ("`sim.render.model: centres`", fast)):
            tgt, ratio, st = _status("lab_sweep_20_s", s["wall_s"])
            e = s["mean_sq_error"]
            load = ""
            if "cpu_s" in s:  # CPU time and load: what the wall would be on idle cores
                load = (
                    f" (load {s['load_before']:.1f} → {s['load_after']:.1f}); CPU {s['cpu_s']:.0f} s, "
                    f"{s['cpu_s'] / s['seeds']:.1f} s a run; "
                    f"CPU / {s['jobs']} jobs = {s['idle_wall_s']:.0f} s"
                )
            rows.append(
                (
                    f"`flightstack sweep paper_experiment --rig lab-sim --seeds {s['seeds']}`, {name}, "
                    f"{s['jobs']} jobs",
                    f"{s['wall_s']:.1f} s{load}",
                    "mean_sq_error none / local / dgp: "
                    + " / ".join(f"{e[k]['mean']:.2e}" for k in ("none", "local", "dgp")),
                    ratio,
                    f"{tgt} s: {st}",
                )
            )
    return rows


def print_table(rows: list[tuple[str, str, str, str, str]]) -> None:
    head = ("benchmark", "measured", "compared with", "ratio", "target")
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    line = "  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True))
    print(line)
    print("-" * len(line))
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)))


def markdown_table(rows: list[tuple[str, str, str, str, str]], machine: dict) -> str:
    out = [
        "| benchmark | measured | compared with | ratio | target |",
        "|---|---|---|---|---|",
    ]
    out += ["| " + " | ".join(c.replace("|", "/") for c in r) + " |" for r in rows]
    out.append("")
    out.append(
        f"Measured on {machine['cpu_count']} CPUs ({machine['machine']}), Python {machine['python']}, "
        f"numpy {machine['numpy']}; raw numbers in `benchmarks/results.json`."
    )
    again = machine.get("remeasured")
    if again:
        out.append(
            f"Stages {', '.join(again['stages'])} measured again at commit {again['commit']} "
            f"(load {again['load']:.1f}; `--only`), the other rows kept from {again['kept_from']}."
        )
    return "\n".join(out) + "\n"


def block_pattern(key: str) -> re.Pattern[str]:
    """A generated block `key` (bench, sweep:NAME, sweep:NAME:summary, gallery) of a markdown page: the start
    marker line `<!-- KEY:start ... -->`, the block's text, the end marker `<!-- KEY:end -->`."""
    k = re.escape(key)
    return re.compile(rf"(<!-- {k}:start[^\n]*-->\n)(.*?)(<!-- {k}:end -->)", re.DOTALL)


def _where(page: Path) -> str:
    return str(page.relative_to(REPO)) if page.is_relative_to(REPO) else str(page)


def read_block(page: Path, key: str) -> str:
    """The text of `page`'s block `key` (SystemExit naming the page and the markers when it has none)."""
    match = block_pattern(key).search(page.read_text(encoding="utf-8"))
    if match is None:
        raise SystemExit(f"{_where(page)} has no <!-- {key}:start ... --> … <!-- {key}:end --> block")
    return match.group(2)


def has_block(page: Path, key: str) -> bool:
    return block_pattern(key).search(page.read_text(encoding="utf-8")) is not None


def write_block(page: Path, key: str, block: str) -> None:
    """Replace only the text of `page`'s block `key`; the page is read fresh just before the atomic write
    (SystemExit naming the page and the markers when it has none)."""
    text = page.read_text(encoding="utf-8")
    match = block_pattern(key).search(text)
    if match is None:
        raise SystemExit(f"{_where(page)} has no <!-- {key}:start ... --> … <!-- {key}:end --> block")
    tmp = page.with_suffix(".md.tmp")
    tmp.write_text(text[: match.start(2)] + block + text[match.end(2) :], encoding="utf-8")
    os.replace(tmp, page)


def update_bench_page(table_md: str) -> None:
    """The benchmark table into docs/performance.md's bench block."""
    write_block(BENCH_PAGE, "bench", table_md)


def machine_info() -> dict[str, object]:
    import cv2
    import scipy
    import sklearn

    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": usable,
        "machine": platform.machine(),
        "processor": platform.processor(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "sklearn": sklearn.__version__,
        "opencv": cv2.__version__,
    }
