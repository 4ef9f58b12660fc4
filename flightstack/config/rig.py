"""Experiment and rig files: what the paper specifies, apart from how it is flown.

An **experiment** file holds what the paper specifies: drones and their desired poses g_d, the graph,
the gains, the GP, the target's motion law, the duration and control period, the compared modes, and the
name of the rig it is flown on by default (`rig:`). A **rig** file holds how it is flown: the backend
(what is simulated and the clock), the simulated physics, the camera calibrations, the believed rc gains,
the safety limits (`safety.enabled: false` only on the ideal rig), the bus and, for a real lab, its
devices (`hardware:`: drone IPs, motion capture, robot). One lab file per lab, shared by every
experiment. `compose(experiment, rig)` merges the two into one `Mission` (flightstack.config.mission), the
resolved object every other layer consumes and every run writes (`mission_resolved.yaml`).

Built-in names (package data under `flightstack.mission_configs`, found from any directory): experiments
`paper_sim`, `paper_experiment`, `scaling_11`, `scaling_31` (paper_sim for 11 and 31 drones,
flightstack.config.generate); rigs `ideal`, `lab-sim`, `emulated-lab`, and `lab` (the real-lab
template). A name that is not built in is read as a path.

A file with both `backend:` and `rig:` is a resolved mission written by a run; it loads as it is.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from flightstack.config.links import network_in_links
from flightstack.config.rigs import EMULATED, RIGS, backends, no_emulators, rig_for
from flightstack.hal import TARGET_BODY, DroneIdentity
from flightstack.safe_yaml import LoadError, load_yaml

PACKAGE = "flightstack.mission_configs"
MISSION_CONFIGS = Path(str(resources.files(PACKAGE)))
"""Where the built-in experiments, rigs (rigs/) and camera files (cameras/) are: package data."""

EXPERIMENT_KEYS = frozenset(
    {
        "name", "description", "seed", "duration_s", "dt_s", "compare_modes", "target", "camera",
        "drones", "graph", "gains", "gp", "gain_analysis", "rig",
    }
)  # fmt: skip
"""Top-level keys of an experiment file (everything the paper specifies, plus its default rig)."""
EXPERIMENT_DRONE_KEYS = frozenset(
    {"id", "desired_pose", "initial_offset", "initial_estimate_error", "sees_target", "camera"}
)
EXPERIMENT_CAMERA_KEYS = frozenset({"mount", "offset"})
RIG_KEYS = frozenset(
    {"rig", "description", "backend", "cameras", "drones", "rc_gains", "robot", "sim", "safety", "bus",
     "hardware", "emulated", "links", "network", "compensation"}
)  # fmt: skip
"""Top-level keys of a rig file."""
RIG_DRONE_KEYS = frozenset({"id", "camera", "rc_gains"})


class RigError(ValueError):
    """An experiment or rig file that cannot be used; the message names the file, the key and why."""


def problem_list(what: str, problems: list[str]) -> str:
    """One line `what: problem` for one problem; else `what (N problems):` and one indented line each."""
    if len(problems) == 1:
        return f"{what}: {problems[0]}"
    return f"{what} ({len(problems)} problems):\n  " + "\n  ".join(problems)


@dataclass(frozen=True)
class Source:
    """A parsed YAML document and the file it came from (`path` is None for a built-in name's data)."""

    data: dict[str, Any]
    path: Path
    where: Any = None

    @property
    def base(self) -> Path:
        return self.path.resolve().parent


def builtin_names(kind: str) -> list[str]:
    """The built-in experiments (`kind` 'experiment') or rigs ('rig'): the package's files, by name."""
    root = MISSION_CONFIGS if kind == "experiment" else MISSION_CONFIGS / "rigs"
    return sorted(p.stem for p in root.glob("*.yaml"))


def builtin_path(name: str, kind: str) -> Path | None:
    """The package-data file of a built-in experiment (`kind` 'experiment') or rig ('rig'), or None."""
    p = MISSION_CONFIGS / (f"{name}.yaml" if kind == "experiment" else f"rigs/{name}.yaml")
    return p if name in builtin_names(kind) else None


def find(name_or_path: str | Path, kind: str) -> Path:
    """A built-in name or a file path -> the file (RigError naming what is known when neither)."""
    text = str(name_or_path)
    builtin = builtin_path(text, kind)
    if builtin is not None and not Path(text).exists():
        return builtin
    p = Path(text)
    if p.is_file() or p.suffix in (".yaml", ".yml", ".json") or "/" in text:
        return p
    names = ", ".join(builtin_names(kind))
    raise RigError(f"{text}: no such file and not a built-in {kind} (built-in: {names})")


def read(path: Path, what: str) -> Source:
    """Load one YAML mapping through the hardened loader (RigError with the loader's reason)."""
    try:
        data, where = load_yaml(path, what)
    except LoadError as exc:
        raise RigError(str(exc)) from None
    if not isinstance(data, dict):
        raise RigError(f"{path}: (top level): a {what} must be a mapping of keys")
    return Source(data, path, where)


def kind_of(data: dict[str, Any]) -> str:
    """'resolved' (a run's mission_resolved.yaml), 'mixed' (experiment and backend in one file, without the
    rig name of a resolved mission: not accepted), 'rig' or 'experiment'."""
    # an experiment has `name` and no `backend`; a rig has `backend` and no `name` (`rig:` is its name)
    if "backend" in data and "name" in data:
        return "resolved" if isinstance(data.get("rig"), str) and data.get("rig") else "mixed"
    if "backend" in data:
        return "rig"
    return "experiment"


def check_experiment(src: Source) -> None:
    """Structure of an experiment file: only experiment keys (rig keys are named as such)."""
    d = src.data
    problems = []
    for k in d:
        if k not in EXPERIMENT_KEYS:
            hint = " (belongs in the rig file)" if k in RIG_KEYS else ""
            problems.append(f"{src.path}: {k}: unknown key{hint}")
    target = d.get("target")
    if isinstance(target, dict) and "robot" in target:
        problems.append(f"{src.path}: target.robot: belongs in the rig file (`robot:`)")
    drones = d.get("drones")
    if isinstance(drones, list):
        for n, dr in enumerate(drones):
            if not isinstance(dr, dict):
                continue
            for k in dr:
                if k not in EXPERIMENT_DRONE_KEYS:
                    hint = " (belongs in the rig file)" if k in RIG_DRONE_KEYS else ""
                    problems.append(f"{src.path}: drones.{n}.{k}: unknown key{hint}")
            cam = dr.get("camera")
            if isinstance(cam, dict):
                for k in cam:
                    if k not in EXPERIMENT_CAMERA_KEYS:
                        hint = " (the calibration belongs in the rig file)" if k == "calibration" else ""
                        problems.append(f"{src.path}: drones.{n}.camera.{k}: unknown key{hint}")
    rig = d.get("rig")
    if rig is not None and not isinstance(rig, str):
        problems.append(f"{src.path}: rig: must be a rig name or a path")
    if problems:
        raise RigError(problem_list("invalid experiment", problems))


def check_rig(src: Source) -> None:
    """Structure of a rig file: only rig keys, a known backend, per-drone entries with ids."""
    d = src.data
    problems = [
        f"{src.path}: {k}: unknown key"
        + (" (belongs in the experiment file)" if k in EXPERIMENT_KEYS else "")
        for k in d
        if k not in RIG_KEYS
    ]
    if not isinstance(d.get("rig"), str) or not d.get("rig"):
        problems.append(f"{src.path}: rig: required, the rig's name")
    if not isinstance(d.get("backend"), str) or d["backend"] not in RIGS:
        problems.append(
            f"{src.path}: backend: must be one of {', '.join(backends())}, got {d.get('backend')!r}"
        )
    elif "emulated" in d and d["backend"] not in EMULATED:
        problems.append(f"{src.path}: emulated: {no_emulators(d['backend'])}")
    cams = d.get("cameras", {})
    if not isinstance(cams, dict) or any(not isinstance(v, str) for v in cams.values()):
        problems.append(f"{src.path}: cameras: a mapping mount -> calibration file")
    drones = d.get("drones", [])
    if not isinstance(drones, list):
        problems.append(f"{src.path}: drones: a list of per-drone device settings")
    else:
        for n, dr in enumerate(drones):
            if (
                not isinstance(dr, dict)
                or not isinstance(dr.get("id"), int)
                or isinstance(dr.get("id"), bool)
            ):
                problems.append(f"{src.path}: drones.{n}.id: each entry needs an integer id")
                continue
            for k in dr:
                if k not in RIG_DRONE_KEYS:
                    problems.append(f"{src.path}: drones.{n}.{k}: unknown key")
            if "camera" in dr and not isinstance(dr["camera"], str):
                problems.append(f"{src.path}: drones.{n}.camera: a calibration file's path")
    if problems:
        raise RigError(problem_list("invalid rig", problems))


def _rel(path_text: str, base: Path) -> str:
    """A file named in a rig, made absolute against the rig file's directory."""
    p = Path(path_text)
    return str(p if p.is_absolute() else (base / p).resolve())


LINKS_FILE_KEYS = frozenset({"links", "measured"})
"""Top-level keys of a links file (`flightstack calibrate latency` writes one): `links:` the measured
links, `measured:` how they were measured (kept for the reader, not applied)."""


def links_with_include(links: Any, base: Path, rig_path: Path) -> Any:
    """A rig's `links:` with `include: FILE` (relative to the rig's directory) replaced by the links of
    FILE's `links:`; a link the rig writes out beside `include` replaces the file's."""
    if not isinstance(links, dict) or "include" not in links:
        return copy.deepcopy(links)
    own = {k: copy.deepcopy(v) for k, v in links.items() if k != "include"}
    name = links["include"]
    if not isinstance(name, str) or not name:
        raise RigError(f"{rig_path}: links.include: a links file's path, got {name!r}")
    src = read(Path(_rel(name, base)), "links file")
    unknown = sorted(set(src.data) - LINKS_FILE_KEYS)
    included = src.data.get("links")
    if unknown or not isinstance(included, dict) or "include" in included:
        raise RigError(
            f"{src.path}: included by {rig_path} (links.include): a links file has `links:` (a mapping, "
            f"without its own include) and optionally `measured:`"
            + (f"; unknown key(s): {', '.join(unknown)}" if unknown else "")
        )
    return {**copy.deepcopy(included), **own}


def compose(experiment: Source, rig: Source) -> dict[str, Any]:
    """The resolved mission document: the experiment, the rig's devices and settings, `rig:` = its name.

    Per drone, the camera calibration is the rig's `drones[id].camera`, else `cameras[<mount>]` for the
    experiment's mount; the believed rc gains are `drones[id].rc_gains`, else the rig's `rc_gains`."""
    check_experiment(experiment)
    check_rig(rig)
    e = copy.deepcopy(experiment.data)
    r = rig.data
    rig_type = rig_for(r["backend"], "emulated" in r)
    e.pop("rig", None)
    out: dict[str, Any] = {"name": e.pop("name", None), "rig": r["rig"], "backend": r["backend"]}
    out.update(e)
    for key in ("sim", "safety", "bus", "hardware", "links", "network", "compensation"):
        if key in r:
            out[key] = copy.deepcopy(r[key])
    if "links" in r:  # a measured links file is included here: the resolved mission holds its values
        out["links"] = links_with_include(r["links"], rig.base, rig.path)
    try:  # a rig file's `network:`, the key before the radio joined `links:`
        out = network_in_links(out, str(rig.path))
    except ValueError as exc:
        raise RigError(str(exc)) from None
    if "emulated" in r:
        out["start_emulators"] = True
    # a `drones:` that is not a list (a number, null) is left for the schema to name, with its line
    drones = out["drones"] if isinstance(out.get("drones"), list) else []
    if "emulated" in r and "hardware" not in r and drones:
        ids = [dr.get("id") for dr in drones if isinstance(dr, dict)]
        out["hardware"] = emulated_hardware([i for i in ids if isinstance(i, int)])
    if "robot" in r and isinstance(out.get("target"), dict):
        out["target"]["robot"] = copy.deepcopy(r["robot"])
    per_drone = {dr["id"]: dr for dr in r.get("drones", [])}
    cams: dict[str, str] = r.get("cameras", {})
    for dr in drones:
        if not isinstance(dr, dict):
            continue
        ident = dr.get("id")
        own = per_drone.get(ident, {}) if isinstance(ident, int) else {}
        cam = dr.get("camera")
        mount = cam.get("mount", "down") if isinstance(cam, dict) else None
        if isinstance(cam, dict) and isinstance(mount, str):  # else the schema names the bad value
            cal = own.get("camera", cams.get(mount))
            if cal is None and rig_type.drones_need_cameras:
                raise RigError(
                    f"{rig.path}: cameras.{mount}: drone {dr.get('id')} of {experiment.path} has a {mount} "
                    f"camera and this rig has no calibration for it (add `cameras: {{{mount}: FILE}}` or "
                    f"`drones: [{{id: {dr.get('id')}, camera: FILE}}]`)"
                )
            if cal is not None:
                cam["calibration"] = _rel(str(cal), rig.base)
        rc = own.get("rc_gains", r.get("rc_gains"))
        if rc is not None:
            dr["rc_gains"] = copy.deepcopy(rc)
    if rig_type.drones_need_cameras and any(
        isinstance(dr, dict) and dr.get("camera") is None for dr in drones
    ):
        raise RigError(
            f"{rig.path}: rig {r['rig']!r} flies drones with cameras; every drone of {experiment.path} needs "
            "`camera: {mount: down|forward}` (the paper's simulation has none: fly it on the ideal rig)"
        )
    return out


def emulated_tello_ip(k: int) -> str:
    """The loopback address of the emulated lab's k-th Tello (0-based): 127.0.0.(6 + k). Its emulator
    binds a free port there, so two labs on the same addresses can fly at once."""
    return f"127.0.0.{6 + k}"


def emulated_hardware(drone_ids: list[int], ports: dict[str, Any] | None = None) -> dict[str, Any]:
    """The `hardware:` section of the emulated-lab rig: station topology on loopback, drone k (0-based) at
    `emulated_tello_ip(k)`. `ports` (from the running emulators: flightstack.sim_backend.emulated_lab)
    fills in the real ports, the NatNet settings and the rover URL; without it the section holds
    placeholders, which is what `flightstack validate` checks before any emulator runs."""
    ports = ports or {}
    drones = []
    for k, i in enumerate(drone_ids):
        own = ports.get("drones", {}).get(i, {})
        drones.append(
            {
                "id": i,
                "ip": emulated_tello_ip(k),
                "control_port": own.get("control_port", 8889),
                "video_port": own.get("video_port", 11111 + k),
                "connect_timeout_s": 2.0,
                "command_timeout_s": 1.0,
                "frame_timeout_s": 5.0,
            }
        )
    return {
        "topology": "station",
        "state_port": ports.get("state_port", 8890),
        "drones": drones,
        "mocap": {
            "system": "optitrack",
            "settings": ports.get("natnet", {"hostname": "127.0.0.1"}),
            "bodies": {DroneIdentity(i).name: f"tello_{i}" for i in drone_ids} | {TARGET_BODY: "scamper"},
            "connect_timeout_s": 1.0,
        },
        "target": {"url": ports.get("rover_url", "udpin:127.0.0.1:14550"), "heartbeat_timeout_s": 3.0},
    }


def load_composed(
    experiment: str | Path, rig: str | Path | None = None
) -> tuple[dict[str, Any], Path, Any, str]:
    """(resolved document, the file to resolve relative paths against, key→line map or None, label).

    `experiment` may also be a resolved mission (a run's mission_resolved.yaml), which is returned as is
    (`rig` must then be None)."""
    exp_path = find(experiment, "experiment")
    src = read(exp_path, "mission file")
    kind = kind_of(src.data)
    if kind == "mixed":
        raise RigError(
            f"{exp_path}: backend: belongs in a rig file; an experiment names its rig with `rig:` "
            "(docs/experiments.md)"
        )
    if kind == "resolved":
        if rig is not None:
            raise RigError(f"{exp_path}: this file names its own backend; --rig needs an experiment file")
        return src.data, exp_path, src.where, str(exp_path)
    if kind == "rig":
        raise RigError(f"{exp_path}: this is a rig file; give an experiment (and this rig with --rig)")
    rig_ref = rig if rig is not None else src.data.get("rig")
    if rig_ref is None:
        raise RigError(f"{exp_path}: rig: no rig given (set `rig:` in the experiment or pass --rig)")
    rig_path = find(rig_ref, "rig")
    if rig is None and not rig_path.is_absolute() and builtin_path(str(rig_ref), "rig") is None:
        rig_path = exp_path.resolve().parent / rig_path  # a rig named by the experiment: relative to it
    rig_src = read(rig_path, "rig file")
    if kind_of(rig_src.data) != "rig":
        raise RigError(f"{rig_path}: not a rig file (a rig has `rig:` and `backend:` and no experiment keys)")
    doc = compose(src, rig_src)
    # lines of the experiment's keys (the rig's sections are validated under the same key paths, and a
    # rig key never appears in an experiment file, so a line number always points into the experiment)
    return doc, exp_path, src.where, f"{exp_path} on rig {rig_src.data['rig']!r} ({rig_path})"


def resolved_document(experiment: str | Path, rig: str | Path | None = None) -> dict[str, Any]:
    """The resolved mission document of `experiment` on `rig` (what `load_mission` validates): for code
    and tests that edit a mission before writing it (a resolved file loads without a warning)."""
    return load_composed(experiment, rig)[0]
