"""Backend registry: mission `backend:` name -> builder, imported lazily (DESIGN §1).

flightstack never imports sim_backend/ or drivers/ at module level, so the simulator runs without
hardware libraries and the hardware runs without the simulator.
"""

from __future__ import annotations

import importlib
from typing import Any

REGISTRY: dict[str, str] = {
    "sim_ideal": "flightstack.sim_backend.build:build_ideal",
    "sim_lab": "flightstack.sim_backend.build_lab:build_lab",
    "tello": "flightstack.drivers.hardware:build_tello",  # real Tellos + motion capture + Scamper
}


def build_backend(mission: Any) -> Any:
    """Build the backend the mission names; ValueError for an unknown name."""
    try:
        target = REGISTRY[mission.backend]
    except KeyError:
        raise ValueError(
            f"unknown backend {mission.backend!r}; known: {', '.join(sorted(REGISTRY))}"
        ) from None
    module_name, func_name = target.split(":")
    return getattr(importlib.import_module(module_name), func_name)(mission)
