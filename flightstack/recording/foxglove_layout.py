"""The Foxglove / Lichtblick layout shipped with the docs (docs/foxglove/flightstack-<mode>.json), one per
mode, made from the run's topics (flightstack.recording.mcap_writer), so it names no topic a run does not
write: `python -m flightstack.recording.foxglove_layout DIR` writes them, and a test checks that the
committed files are what this module makes.

The layout (the layout-file format both apps import, *Layouts → Import from file*: `configById`,
`layout`): a 3D panel in `world` (z up) with the target's pose, the drones' poses, their estimates and the
scene (fence, markers); the camera images of drones 1 and 2 (empty on the ideal rig, which has no
cameras); a plot of drones 1 and 2's control error e_c in x and y; the mode's events in a Log panel.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from flightstack.config.types import Mode
from flightstack.recording.mcap_scene import WORLD_FRAME
from flightstack.recording.mcap_writer import drone_topic, image_topic, topic

LAYOUT_DRONES = (1, 2)
"""The drones whose images and errors the layout shows (every rig's experiment has them)."""
_TITLE_KEYS = ("foxglovePanelTitle", "lichtblickPanelTitle")  # each app reads its own


def layout_name(mode: str) -> str:
    """The shipped file of `mode`'s layout."""
    return f"flightstack-{mode}.json"


def _titled(title: str, config: dict[str, Any]) -> dict[str, Any]:
    return {**dict.fromkeys(_TITLE_KEYS, title), **config}


def layout(mode: str) -> dict[str, Any]:
    """The layout of `mode` (module docstring) as the layout file's JSON document."""
    three_d = {
        "followTf": WORLD_FRAME,
        "followMode": "follow-none",
        "cameraState": {
            "distance": 7.0,
            "perspective": True,
            "phi": 60.0,
            "thetaOffset": 45.0,
            "target": [0.0, 0.0, 0.0],
            "targetOffset": [0.0, 0.0, 0.5],
            "targetOrientation": [0.0, 0.0, 0.0, 1.0],
            "fovy": 45.0,
            "near": 0.01,
            "far": 500.0,
        },
        "scene": {"transforms": {"showLabel": True, "labelSize": 0.08, "axisScale": 0.25}},
        "transforms": {},
        "topics": {
            topic(mode, "pose/target"): {"visible": True, "type": "arrow", "color": "#ffb000ff"},
            topic(mode, "pose/drones"): {"visible": True, "type": "arrow"},
            topic(mode, "pose/estimates"): {"visible": True, "type": "axis", "axisScale": 0.15},
            topic(mode, "scene"): {"visible": True},
        },
        "layers": {
            "grid": {
                "layerId": "foxglove.Grid",
                "instanceId": "grid",
                "label": "floor (world, z = 0)",
                "visible": True,
                "frameId": WORLD_FRAME,
                "size": 6,
                "divisions": 12,
                "lineWidth": 1,
                "color": "#248eff80",
                "position": [0, 0, 0],
                "rotation": [0, 0, 0],
                "order": 1,
            }
        },
        "imageMode": {},
    }
    config: dict[str, Any] = {"3D!flightstack": _titled(f"{mode}: poses in world (z up)", three_d)}
    for i in LAYOUT_DRONES:
        config[f"Image!drone{i}"] = _titled(
            f"{mode}: drone {i}'s camera", {"imageMode": {"imageTopic": image_topic(mode, i)}}
        )
    paths = [
        {
            "value": f"{drone_topic(mode, i)}.e_c[{k}]",
            "enabled": True,
            "timestampMethod": "receiveTime",
            "label": f"drone {i} e_c {axis} (m)",
        }
        for i in LAYOUT_DRONES
        for k, axis in enumerate("xy")
    ]
    config["Plot!errors"] = _titled(
        f"{mode}: control error e_c",
        {
            "paths": paths,
            "showLegend": True,
            "legendDisplay": "floating",
            "showPlotValuesInLegend": False,
            "showXAxisLabels": True,
            "showYAxisLabels": True,
            "isSynced": True,
            "xAxisVal": "timestamp",
            "sidebarDimension": 240,
        },
    )
    config["RosOut!events"] = _titled(
        f"{mode}: events", {"searchTerms": [], "minLogLevel": 2, "topicToRender": topic(mode, "events")}
    )
    images = {"first": "Image!drone1", "second": "Image!drone2", "direction": "row", "splitPercentage": 50}
    right = {
        "first": images,
        "second": {"first": "Plot!errors", "second": "RosOut!events", "direction": "column"},
        "direction": "column",
        "splitPercentage": 45,
    }
    return {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {"first": "3D!flightstack", "second": right, "direction": "row", "splitPercentage": 55},
    }


def layout_json(mode: str) -> str:
    """The shipped file's text of `mode`'s layout."""
    return json.dumps(layout(mode), indent=2) + "\n"


def layout_topics(doc: dict[str, Any]) -> set[str]:
    """Every topic a layout document names: 3D panels' topics, Image panels' imageTopic, Plot paths' topic
    (before the message path), Log panels' topicToRender."""
    out: set[str] = set()
    for panel, cfg in doc["configById"].items():
        kind = panel.split("!", 1)[0]
        if kind == "3D":
            out |= set(cfg.get("topics", {}))
        elif kind == "Image":
            out.add(cfg["imageMode"]["imageTopic"])
        elif kind == "Plot":
            out |= {p["value"].split(".", 1)[0] for p in cfg["paths"]}
        elif kind == "RosOut":
            out.add(cfg["topicToRender"])
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m flightstack.recording.foxglove_layout DIR", file=sys.stderr)
        return 2
    out = Path(args[0])
    out.mkdir(parents=True, exist_ok=True)
    for mode in Mode:
        (out / layout_name(mode.value)).write_text(layout_json(mode.value))
    return 0


__all__ = ["LAYOUT_DRONES", "layout", "layout_json", "layout_name", "layout_topics"]


if __name__ == "__main__":
    sys.exit(main())
