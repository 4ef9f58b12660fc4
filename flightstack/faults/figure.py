"""faults.png: the fault table at a glance.

One lane per row of `flightstack faults`: its name coloured by the verdict (handled or not), and on the
mission clock (s) the safety events of its run (`events.jsonl` in the row's run directory), one marker
shape per family: hover (zero velocity), land, refusal, link, and everything else. Rows without a run
directory (e.g. a mission file that is refused before anything flies) show the verdict only. Drawn from
faults.json and the run directories, so `flightstack faults` and the docs' gallery share it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from flightstack.recording.run_reader import read_events

FAMILIES: tuple[tuple[str, tuple[str, ...], str, str], ...] = (
    # label, substrings of the event kind, marker, colour
    ("refused", ("refuse",), "x", "tab:red"),
    ("land", ("land",), "v", "tab:blue"),
    ("hover / zero velocity", ("hover", "timeout", "stale", "zero"), "o", "tab:orange"),
    ("link", ("link",), "s", "tab:purple"),
    ("other", ("",), ".", "tab:gray"),
)


def family(kind: str) -> int:
    """Index into FAMILIES of a safety event kind (first match; "other" matches everything)."""
    for n, (_, keys, _, _) in enumerate(FAMILIES):
        if any(k in kind for k in keys):
            return n
    return len(FAMILIES) - 1


def safety_events(run_dir: Path) -> list[tuple[float, str]]:
    """(t, kind) of the safety events in run_dir/events.jsonl (lines cut short skipped)."""
    return [
        (float(ev["t"]), str(ev.get("kind", "")))
        for ev in read_events(run_dir)
        if ev.get("event") == "safety" and isinstance(ev.get("t"), int | float)
    ]


def plot_fault_summary(results: list[dict[str, Any]], path: Path) -> Path:
    """Write the figure for `results` (faults.json's "results": dicts with name, handled, details) to
    `path` and return it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, ax = plt.subplots(figsize=(10, 0.42 * n + 1.6))
    seen: set[int] = set()
    for row, r in enumerate(results):
        y = n - 1 - row
        ok = bool(r.get("handled"))
        ax.axhspan(y - 0.45, y + 0.45, color="tab:green" if ok else "tab:red", alpha=0.07)
        run_dir = (r.get("details") or {}).get("run_dir")
        for t, kind in safety_events(Path(run_dir)) if run_dir else []:
            f = family(kind)
            label, _, marker, colour = FAMILIES[f]
            ax.plot(t, y, marker, color=colour, ms=6, label=None if f in seen else label)
            seen.add(f)
    ax.set_yticks(range(n))
    names = [f"{r['name']}  {'handled' if r.get('handled') else 'NOT handled'}" for r in reversed(results)]
    ax.set_yticklabels(names, fontsize=8)
    for tick, r in zip(ax.get_yticklabels(), reversed(results), strict=True):
        tick.set_color("darkgreen" if r.get("handled") else "darkred")
    ax.set_ylim(-0.6, n - 0.4)
    ax.set_xlabel("mission time [s] (safety events of each row's run)")
    handled = sum(bool(r.get("handled")) for r in results)
    ax.set_title(f"Fault table: {handled} of {n} rows handled")
    ax.grid(True, axis="x", alpha=0.3)
    if seen:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the lanes
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
