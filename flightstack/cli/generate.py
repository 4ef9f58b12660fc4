"""`flightstack generate-mission --drones N`: the paper's simulation for N drones.

Writes the experiment YAML (flightstack.config.generate.n_drone_mission) to --out, or to stdout without
it; an existing file is kept unless --force. The file loads with `flightstack validate FILE` and flies
with `flightstack run FILE`. Exit codes: 0 written, 1 the file could not be written, 2 refused (bad
arguments, an unstable gain, an existing file).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
from pathlib import Path
from typing import Any

from flightstack.config.generate import GRAPHS, MAX_DRONES, GenerateError, generate, mission_yaml


def _drones(text: str) -> int:
    """argparse type of --drones: an integer 2..MAX_DRONES."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of drones") from None
    if not 2 <= n <= MAX_DRONES:
        raise argparse.ArgumentTypeError(f"{text!r}: between 2 and {MAX_DRONES} drones")
    return n


def command_line(args: argparse.Namespace) -> str:
    """The command that reproduces the file (without --out/--force: where it went does not change it)."""
    parts = ["flightstack", "generate-mission", "--drones", str(args.drones), "--graph", args.graph]
    parts += ["--base", str(args.base)]
    if args.radius is not None:
        parts += ["--radius", f"{args.radius:g}"]
    if args.k_s is not None:
        parts += ["--k-s", f"{args.k_s:g}"]
    if args.reduce_k_s:
        parts.append("--reduce-k-s")
    if args.name is not None:
        parts += ["--name", args.name]
    return shlex.join(parts)


def _write_new(out: Path, text: str, force: bool) -> None:
    """Write `text` to `out` atomically (a temporary file renamed over it); FileExistsError when `out`
    exists and not `force`."""
    if out.exists() and not force:
        raise FileExistsError(out)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", dir=out.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        if force:
            os.replace(tmp, out)
        else:
            os.link(tmp, out)  # fails if `out` appeared meanwhile: never overwrites without --force
            os.unlink(tmp)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def cmd_generate_mission(args: argparse.Namespace) -> int:
    try:
        g = generate(
            args.drones,
            base=args.base,
            graph=args.graph,
            radius_m=args.radius,
            k_s=args.k_s,
            name=args.name,
            reduce_k_s=args.reduce_k_s,
        )
    except GenerateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = mission_yaml(g, command_line(args))
    for note in g.notes:
        print(f"note: {note}", file=sys.stderr)
    if args.out is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.out)
    try:
        _write_new(out, text, args.force)
    except FileExistsError:
        print(f"error: {out}: exists; pass --force to overwrite it", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(
        f"{out}: {g.n} drones, {g.graph} graph, k_s = {g.k_s:.6g}, bands over {g.axis} "
        f"[{g.band_range_m[0]}, {g.band_range_m[1]}] m (`flightstack validate {out}`)",
        file=sys.stderr,
    )
    return 0


def register(sub: Any) -> None:
    g = sub.add_parser("generate-mission")
    g.add_argument("--drones", type=_drones, required=True, help=f"number of drones (2..{MAX_DRONES})")
    g.add_argument(
        "--graph", choices=GRAPHS, default="complete", help="communication graph (default complete)"
    )
    g.add_argument("--base", default="paper_sim", help="experiment to scale (default paper_sim)")
    g.add_argument(
        "--radius", type=float, default=None, help="circle of desired poses, m (default the base's)"
    )
    g.add_argument(
        "--k-s", type=float, default=None, help="consensus gain, 1/s (default the base's scaled by λ_max)"
    )
    g.add_argument(
        "--reduce-k-s",
        action="store_true",
        help="lower k_s to the stability bound instead of refusing a mission that exceeds it",
    )
    g.add_argument("--name", default=None, help="the mission's name (default <base>_<graph>_<N>)")
    g.add_argument("--out", default=None, help="YAML file to write (default: stdout)")
    g.add_argument("--force", action="store_true", help="overwrite an existing --out file")
    g.set_defaults(func=cmd_generate_mission)
