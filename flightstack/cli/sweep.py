"""`flightstack sweep EXPERIMENT --seeds N [--rig RIG] [--set KEY=V1,V2,...]... [--jobs J]
[--scheduler ADDRESS] [--keep-runs] [--force] --out DIR`: the experiment for seeds 0 .. N-1 × every point
of the --set grid, in worker processes (or on a Dask cluster), resumable; statistics over the seeds.

DIR/sweep.json records the plan (seeds, grid, resolved base mission) and the last invocation (command
line, versions, start/end, wall time; earlier invocations under `history`); DIR/runs/<id>.json each
finished combination; DIR/summary.{json,csv}, errors.png, ratios.png the statistics (flightstack.sweep).
Exit codes: 0 every combination succeeded, 1 some failed, 2 bad input (nothing ran), 130 interrupted.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import platform
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightstack import threads
from flightstack.sweep.plan import SweepError

if TYPE_CHECKING:
    from flightstack.sweep.plan import Combination, Plan


def register(sub: Any) -> None:
    """Add the `sweep` subcommand to the CLI's subparsers."""
    p = sub.add_parser("sweep")
    p.add_argument(
        "experiment", help="experiment: a built-in name (paper_sim, paper_experiment) or a YAML file"
    )
    p.add_argument(
        "--seeds", type=_positive_int, required=True, metavar="N", help="seeds 0 .. N-1 per grid point"
    )
    p.add_argument("--rig", default=None, help="simulated rig: ideal or lab-sim (default: the experiment's)")
    p.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="dotted mission key and its values (YAML), e.g. gains.k_s=10,70 or compare_modes=[none,dgp]; "
        "repeatable: the grid is the cartesian product",
    )
    p.add_argument(
        "--jobs",
        type=_positive_int,
        default=None,
        metavar="J",
        help="worker processes (default: the CPUs this process may use)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run on the Dask cluster at ADDRESS (needs flightstack[dask])",
    )
    p.add_argument(
        "--out", required=True, metavar="DIR", help="sweep directory (created; a rerun resumes it)"
    )
    p.add_argument(
        "--keep-runs", action="store_true", help="also write each run's directory to DIR/runs/<id>/"
    )
    p.add_argument("--force", action="store_true", help="accept a plan that differs from DIR/sweep.json's")
    p.set_defaults(func=cmd_sweep)


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: must be at least 1")
    return v


def versions() -> dict[str, str]:
    """flightstack, python, numpy, scipy, numba and the platform, for sweep.json."""
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("flightstack", "numpy", "scipy", "numba"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def cmd_sweep(args: argparse.Namespace) -> int:
    """Plan (validate every grid point), check DIR against its recorded plan, run what is not finished,
    summarise. Bad input exits 2 before anything runs."""
    try:
        return _sweep(args)
    except SweepError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _sweep(args: argparse.Namespace) -> int:
    import json

    import yaml

    from flightstack.config.mission import load_mission
    from flightstack.recording.files import atomic_write_json
    from flightstack.runtime.flight import resolved_mission_yaml
    from flightstack.sweep.execute import (
        RUNS_DIR,
        job_of,
        load_finished,
        open_executor,
        run_all,
        write_result,
    )
    from flightstack.sweep.plan import build_plan, parse_grid, plan_differences

    grid = parse_grid(args.sets)
    if args.scheduler is not None and importlib.util.find_spec("distributed") is None:
        raise SweepError("--scheduler needs Dask's distributed package: pip install 'flightstack[dask]'")
    base_mission = load_mission(args.experiment, rig=args.rig)  # MissionError: exit 2 (cli.app)
    base = yaml.safe_load(resolved_mission_yaml(base_mission))  # absolute file paths
    base_dir = base_mission.resolve(".")
    plan = build_plan(base, grid, args.seeds, base_dir)
    out = Path(args.out)
    sweep_json = out / "sweep.json"
    previous: dict[str, Any] = {}
    if sweep_json.exists():
        try:
            previous = json.loads(sweep_json.read_text())
        except (OSError, ValueError):
            previous = {}
        diff = plan_differences(previous.get("plan"), plan)
        if diff and not args.force:
            raise SweepError(
                f"--out {out}: holds a sweep with another plan (differs in: {', '.join(diff)}); "
                "use another --out, or --force to run this plan there (finished runs of it are kept)"
            )
    try:
        (out / RUNS_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SweepError(f"--out {out}: cannot create it: {exc.strerror or exc}") from None
    done = load_finished(out, plan.combinations)
    todo = [c for c in plan.combinations if c.id not in done]
    jobs = args.jobs or threads.usable_cpus()
    limits = threads.apply(threads.limits_for(jobs))  # the run's rule, for `jobs` flights at once
    started, wall0 = time.time(), time.perf_counter()
    record: dict[str, Any] = {
        "command": ["flightstack", "sweep", *_argv(args)],
        "arguments": {k: v for k, v in vars(args).items() if k not in ("func", "command")},
        "versions": versions(),
        "threads": limits.as_dict(),
        "experiment": args.experiment,
        "rig": base_mission.rig,
        "plan": plan.record(),
        "combinations": len(plan.combinations),
        "started": _stamp(started),
        "finished": None,
        "wall_seconds": None,
        "history": [
            *previous.get("history", []),
            *(
                [{k: previous.get(k) for k in ("command", "started", "finished", "wall_seconds", "ran")}]
                if previous
                else []
            ),
        ],
    }
    atomic_write_json(sweep_json, record, strict=False)
    tty = sys.stdout.isatty()
    print(
        f"sweep {plan.base['name']}: {len(plan.combinations)} combinations ({len(plan.points)} grid points x "
        f"{args.seeds} seeds); {len(done)} finished already, skipped; {len(todo)} to run",
        flush=True,
    )
    ran, failed, labels = 0, 0, plan.labels()

    def on_result(c: Combination, result: dict[str, Any]) -> None:
        nonlocal ran
        done[c.id] = write_result(out, c, result)
        ran += 1
        if tty:
            print(_progress_line(len(done), len(plan.combinations), done[c.id], labels[c.point]), flush=True)

    def on_failure(c: Combination, exc: BaseException) -> None:
        nonlocal failed
        failed += 1
        print(
            f"error: {c.id} ({c.values or 'base'}, seed {c.seed}): {type(exc).__name__}: {exc}",
            file=sys.stderr,
        )

    interrupted = False
    if todo:
        keep = (out / RUNS_DIR).resolve() if args.keep_runs else None  # workers may have another cwd
        try:
            with open_executor(min(jobs, len(todo)), args.scheduler) as (ex, how, in_flight):
                print(f"running on {how}; {limits.line()}", flush=True)
                job = functools.partial(job_of, base_dir=base_dir, keep_dir=keep)
                interrupted = run_all(ex, todo, job, on_result, on_failure, in_flight)
        except KeyboardInterrupt:
            interrupted = True
    return _finish(args, out, plan, done, record, wall0, ran, failed, interrupted)


def _finish(
    args: argparse.Namespace,
    out: Path,
    plan: Plan,
    done: dict[str, dict[str, Any]],
    record: dict[str, Any],
    wall0: float,
    ran: int,
    failed: int,
    interrupted: bool,
) -> int:
    """Summary files, plots, sweep.json's end, the table; the exit code."""
    from flightstack.recording.files import atomic_write_json
    from flightstack.sweep.report import format_table, write_plots, write_summary
    from flightstack.sweep.stats import succeeded, summarise

    records = [done[c.id] for c in plan.combinations if c.id in done]
    summary = summarise(plan.points, records, plan.labels())
    meta = {
        "experiment": args.experiment,
        "rig": record["rig"],
        "seeds": plan.seeds,
        "grid": plan.record()["grid"],
    }
    meta.update(complete=len(records) == len(plan.combinations), finished_runs=len(records))
    write_summary(out, summary, [k for k, _ in plan.grid], meta)
    try:
        write_plots(out, summary, records)
    except (OSError, ValueError) as exc:
        print(f"warning: plots not written: {exc}", file=sys.stderr)
    record.update(finished=_stamp(time.time()), wall_seconds=time.perf_counter() - wall0, ran=ran)
    record["interrupted"] = interrupted
    atomic_write_json(out / "sweep.json", record, strict=False)
    print(format_table(summary))
    bad = sum(not succeeded(r) for r in records)
    missing = len(plan.combinations) - len(records)
    print(
        f"{len(records)}/{len(plan.combinations)} combinations finished ({ran} ran now, {bad} with an error, "
        f"{missing} missing); summary: {out / 'summary.csv'}, {out / 'summary.json'}"
    )
    if interrupted:
        print("warning: interrupted: finished runs kept; rerun the same command to resume", file=sys.stderr)
        return 130
    return 1 if bad or missing or failed else 0


def _progress_line(k: int, total: int, r: dict[str, Any], label: str) -> str:
    """`[ 3/40] s0001-ab12cd34ef seed 1 gains.k_s=10: none 6.5e-04 dgp 1.2e-04 (12.3 s)`."""
    m = r.get("metrics") or {}
    errs = " ".join(
        f"{mode} {mm.get('mean_sq_error', float('nan')):.2e}" for mode, mm in m.get("modes", {}).items()
    )
    tail = f" ERROR {r['error']}" if r.get("error") else ""
    wall = r.get("wall_seconds") or 0.0
    head = f"[{k:{len(str(total))}d}/{total}] {r['id']} seed {r['seed']} {label}"
    return f"{head}: {errs} ({wall:.1f} s){tail}"


def _argv(args: argparse.Namespace) -> list[str]:
    """The command line (as given to this process when it is the flightstack CLI, else rebuilt)."""
    if len(sys.argv) > 1 and "sweep" in sys.argv[1:]:
        return sys.argv[sys.argv.index("sweep") + 1 :]
    out = [args.experiment, "--seeds", str(args.seeds), "--out", str(args.out)]
    out += ["--rig", args.rig] if args.rig else []
    for s in args.sets:
        out += ["--set", s]
    return out


def _stamp(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(t))
