"""The default layout of the viewer: one tab per mode with its 3-D scene (bodies, trails, cameras, expert
regions, training inputs), its error and GP plots and its event log."""

from __future__ import annotations

from collections.abc import Sequence
from types import ModuleType
from typing import Any

from flightstack.viewer import layout


def build(rr: ModuleType, modes: Sequence[str]) -> Any:
    """A rerun.blueprint.Blueprint with a tab per mode of `modes`, the time panel on `mission_time`."""
    rrb = rr.blueprint
    tabs = []
    for m in modes:
        plots = [
            rrb.TimeSeriesView(origin=layout.series(m, name), name=f"{m}: {title}")
            for name, title in (
                ("e_c_norm", "‖e_c‖"),
                ("e_e_norm", "‖e_e‖"),
                ("mu_fused", "fused μ (used)"),
                ("var_own", "own expert's variance"),
            )
        ]
        scene = rrb.Spatial3DView(
            origin="/",
            contents=[f"+ {layout.world(m)}/**", f"+ {layout.MISSION}/**"],
            name=f"{m}: 3-D (Σw)",
        )
        tabs.append(
            rrb.Horizontal(
                scene,
                rrb.Vertical(*plots, rrb.TextLogView(origin=layout.events(m), name=f"{m}: events")),
                column_shares=[3, 2],
                name=m,
            )
        )
    root = rrb.Tabs(*tabs) if tabs else rrb.Spatial3DView(origin="/")
    return rrb.Blueprint(root, rrb.TimePanel(timeline=layout.TIMELINE))
