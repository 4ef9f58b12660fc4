"""`flightstack validate RIG.yaml`: a rig or lab file checked on its own, before any experiment is flown on
it. Every section is validated by the same schema models a composed mission uses (flightstack.config),
and every camera calibration it names must exist and parse. Raises RigError naming the file, the key
and the reason; returns a short summary of what the rig provides."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from flightstack.config.bus import BusSpec
from flightstack.config.hardware import HardwareSpec
from flightstack.config.mission import SafetySpec
from flightstack.config.rig import RigError, Source, problem_list
from flightstack.config.rig_rules import safety_off_problem
from flightstack.config.rigs import rig_for
from flightstack.config.sim_specs import RcGainsSpec, RobotSpec, SimSpec

SECTIONS: dict[str, type[BaseModel]] = {
    "safety": SafetySpec,
    "bus": BusSpec,
    "hardware": HardwareSpec,
    "sim": SimSpec,
    "robot": RobotSpec,
    "rc_gains": RcGainsSpec,
}


def validate_rig(src: Source) -> dict[str, Any]:
    """Validate every section of a rig file (structure already checked by config.rig.check_rig)."""
    problems: list[str] = []
    for key, model in SECTIONS.items():
        if key in src.data:
            _validate(model, src.data[key], key, src, problems)
    for n, dr in enumerate(src.data.get("drones", [])):
        if "rc_gains" in dr:
            _validate(RcGainsSpec, dr["rc_gains"], f"drones.{n}.rc_gains", src, problems)
    cameras = dict(src.data.get("cameras", {}))
    cameras.update(
        {
            f"drones.{n}.camera": dr["camera"]
            for n, dr in enumerate(src.data.get("drones", []))
            if "camera" in dr
        }
    )
    from flightstack.vision.camera_file import load_calibration

    for where, rel in cameras.items():
        path = Path(rel) if Path(rel).is_absolute() else (src.base / rel).resolve()
        if not path.is_file():
            problems.append(f"{src.path}: {where}: file not found: {path}")
            continue
        try:
            load_calibration(path)
        except ValueError as exc:
            problems.append(f"{src.path}: {where}: {exc}")
    backend = src.data.get("backend")
    rig = rig_for(str(backend), "emulated" in src.data)  # config.rig.check_rig has checked both
    if rig.has_devices and "hardware" not in src.data and not rig.starts_emulators:
        problems.append(
            f"{src.path}: hardware: a rig with backend {backend} needs its devices (or `emulated:`)"
        )
    safety = src.data.get("safety", {})
    off = safety_off_problem(rig, safety.get("enabled") if isinstance(safety, dict) else None)
    if off is not None:
        problems.append(f"{src.path}: {off}")
    if problems:
        raise RigError(problem_list("invalid rig", problems))
    return {
        "rig": src.data["rig"],
        "backend": backend,
        "sections": sorted(k for k in src.data if k in SECTIONS),
        "cameras": sorted(cameras),
        "drones": [dr["id"] for dr in src.data.get("drones", [])],
    }


def _validate(model: type[BaseModel], value: Any, key: str, src: Source, problems: list[str]) -> None:
    try:
        model.model_validate(value)
    except ValidationError as err:
        for e in err.errors():
            path = ".".join(str(p) for p in (key, *e["loc"]))
            msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
            problems.append(f"{src.path}: {path}: {msg}")
