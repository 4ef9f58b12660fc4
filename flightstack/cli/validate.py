"""`flightstack validate EXPERIMENT|RIG|MISSION [--rig RIG] [--json]`: check a file before anything flies.

A valid file prints a short summary (what will fly, on what, for how long, with which gains, GP options,
safety and devices) ending in `valid`; `--json` prints the full resolved mission instead (for a rig or
lab file on its own: its summary as JSON). An invalid one exits 2 naming the key and the reason (the
MissionError/RigError is reported by `flightstack.cli.app.main`), also when the recording would not fit
in this computer's memory (flightstack.runtime.resources)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from flightstack.config.mission import Mission, load_mission, mission_to_dict


def _num(x: float) -> str:
    """A number as short as it reads (0.05, 60, 1e-05)."""
    return f"{x:g}"


def _nums(xs: list[float] | tuple[float, ...]) -> str:
    """Numbers as a list, or its first and last value when it is long (the region edges of 31 drones)."""
    if len(xs) > 4:
        return f"[{_num(xs[0])} .. {_num(xs[-1])}]"
    return "[" + ", ".join(_num(x) for x in xs) + "]"


def id_ranges(ids: list[int]) -> str:
    """Drone ids with runs of three or more consecutive ids joined: [1, 2, 3, 5, 6] -> "1-3, 5, 6"."""
    runs: list[list[int]] = []
    for i in ids:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 2 else ", ".join(map(str, r)) for r in runs)


def mission_summary(m: Mission) -> list[str]:
    """A few lines describing a resolved, valid mission (without the final `valid`)."""
    if m.simulated:
        where = "simulated"
    else:
        where = "real drivers, loopback emulators" if m.start_emulators else "real hardware"
    rig = f"rig {m.rig}" if m.rig else "no rig"
    lines = [f"mission {m.name}: {rig}, backend {m.backend} ({where})"]
    blind = [d.id for d in m.drones if not d.sees_target]
    n_edges = m.edge_count()
    graph = "complete graph" if m.graph.kind == "complete" else f"graph of {n_edges} edge(s)"
    lines.append(
        f"drones: {len(m.drones)} (ids {id_ranges([d.id for d in m.drones])}); {graph}"
        + (f"; not seeing the target: {id_ranges(blind)}" if blind else "")
    )
    ticks = m.n_ticks
    lines.append(
        f"duration {_num(m.duration_s)} s, dt {_num(m.dt_s)} s ({ticks} ticks per mode); "
        f"modes {', '.join(m.compare_modes)}; seed {m.seed}; target {m.target.motion}"
    )
    g = m.gains
    lines.append(f"gains: k_c {_nums(g.k_c)}, k_e {_nums(g.k_e)}, k_s {_num(g.k_s)}")
    gp = m.gp
    experts = f"experts {gp.experts_file}" if gp.experts_file else "experts trained on the `none` run"
    regions = f"{len(gp.regions.edges) + 1} regions along {gp.regions.axis}"
    if gp.regions.edges:
        regions += f" split at {_nums(gp.regions.edges)}"
    lines.append(f"gp: {experts}; {regions}; {gp.samples_per_region} samples per region")
    lines.append(
        f"    noise_var {_num(gp.noise_var)}, hyperparameters {gp.hyperparameters}, "
        f"output kernel {gp.output_kernel}, fusion {gp.fusion}, {gp.restarts} restarts"
    )
    bus: str = m.bus.kind
    if m.bus.kind == "zenoh" and m.bus.zenoh is not None:
        bus += f" ({m.bus.zenoh.security})"
    lines.append(f"safety: {'on' if m.safety.enabled else 'off'}; bus {bus}")
    hw = m.hardware
    if hw is not None:
        robot = f"robot at {hw.target.url}" if hw.target is not None else "no robot driven (target: null)"
        lines.append(f"hardware ({hw.topology}): mocap {hw.mocap.system}; {robot}")
        tellos = ", ".join(
            f"{d.id} at {d.ip}:{d.control_port}{'' if d.interface is None else ' via ' + d.interface}"
            f" (video {d.video_port}" + "".join(f", `{v.command}`" for v in hw.video_settings(d.id)) + ")"
            for d in hw.drones
        )
        lines.append(f"    tellos {tellos}")
    return lines


def rig_summary(summary: dict[str, Any]) -> list[str]:
    """A few lines describing a valid rig or lab file (flightstack.config.rig_check.validate_rig's dict)."""
    drones = summary.get("drones") or []
    return [
        f"rig {summary['rig']}: backend {summary['backend']}",
        f"drones: {len(drones)}" + (f" (ids {id_ranges(drones)})" if drones else ""),
        f"sections: {', '.join(summary['sections']) or 'none'}",
        f"camera calibrations: {', '.join(summary['cameras']) or 'none'}",
    ]


def cmd_validate(args: argparse.Namespace) -> int:
    """Validate an experiment (on its rig or --rig), a rig or lab file on its own, or a resolved mission;
    print a short summary and `valid` (`--json`: the resolved mission as JSON). Exit 2 naming the key and
    the reason when invalid (raised here, reported by main)."""
    from flightstack.config.rig import check_rig, find, kind_of, read

    as_json = bool(getattr(args, "json", False))
    path = find(args.mission, "experiment") if args.rig is None else None
    if path is not None and path.is_file():
        src = read(path, "mission file")
        if kind_of(src.data) == "rig":  # a rig or lab file on its own: structure and every section
            check_rig(src)
            from flightstack.config.rig_check import validate_rig

            summary = validate_rig(src)
            print(json.dumps(summary, indent=2) if as_json else "\n".join([*rig_summary(summary), "valid"]))
            return 0
    m = load_mission(args.mission, rig=args.rig)
    from flightstack.runtime.resources import check_recording_fits

    check_recording_fits(m)  # on the computer that validates; `run` checks again before takeoff
    print(json.dumps(mission_to_dict(m), indent=2) if as_json else "\n".join([*mission_summary(m), "valid"]))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `validate` to the top-level subcommands."""
    v = sub.add_parser("validate")
    v.add_argument("mission", help="experiment name or file, rig or lab file, or resolved mission")
    v.add_argument("--rig", default=None, help="validate the experiment on this rig")
    v.add_argument(
        "--json", action="store_true", help="print the full resolved mission as JSON instead of a summary"
    )
    v.set_defaults(func=cmd_validate)
