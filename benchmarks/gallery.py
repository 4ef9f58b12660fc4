"""The docs' picture gallery (docs/gallery.md), made by running the commands it shows (never by hand).

    python benchmarks/gallery.py                      # runs everything below (~2 min on 2 cores)
    python benchmarks/gallery.py --sweep runs/sweep_paper   # reuse a finished sweep instead of running one
    python benchmarks/gallery.py --check              # only re-render docs/gallery.md from the manifest

It runs, each into a scratch directory:
1. `flightstack run paper_sim` (the paper's simulation: trajectory, ‖e_c‖ and ‖e_e‖ per mode);
2. `flightstack sweep paper_sim --seeds 20` (errors and ratios with 95 % confidence intervals);
3. `flightstack bench-loop --seconds 10` (the loop-health plot of the emulated lab);
4. `flightstack faults` on the simulated rows (the fault table's summary figure);

copies each picture to docs/gallery/, writes docs/gallery/manifest.json (file, caption, the command that
made it, the commit and date) and rewrites docs/gallery.md between `<!-- gallery:start -->` and
`<!-- gallery:end -->` from the manifest. tests/test_gallery.py holds the page's section equal to what the
manifest renders and every linked file present.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.table import DOCS, read_block, write_block  # noqa: E402

GALLERY = REPO / "docs" / "gallery"
MANIFEST = GALLERY / "manifest.json"
PAGE = DOCS / "gallery.md"
"""The page that shows the pictures; its links are relative to it (gallery/<file>)."""
SIM_FAULT_ROWS = ("link_loss", "mocap_dropout_short", "mocap_dropout_long", "occlusion_short",
                  "occlusion_long", "low_battery", "low_battery_takeoff")  # fmt: skip


def _run(argv: list[str]) -> None:
    """Run `flightstack ARGV` (this interpreter); a non-zero exit is kept (a failed fault row or a loop that
    did not keep dt is still a picture worth showing) but reported."""
    cmd = [sys.executable, "-m", "flightstack", *argv]
    print("$ flightstack " + " ".join(argv), flush=True)
    code = subprocess.run(cmd, cwd=REPO, check=False).returncode
    if code not in (0, 1):
        raise SystemExit(f"flightstack {' '.join(argv)} exited {code}")


def _commit() -> str:
    """HEAD's short hash, marked when tracked files other than the gallery's own differ from it."""

    def git(*argv: str) -> str:
        try:
            r = subprocess.run(["git", *argv], cwd=REPO, capture_output=True, text=True, check=False)
        except OSError:
            return ""
        return r.stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git(
        "status", "--porcelain", "--untracked-files=no", "--", ".", ":!docs/gallery", ":!docs/gallery.md"
    )
    return head + (" (with uncommitted changes)" if dirty else "")


def make(sweep: Path | None) -> list[dict[str, str]]:
    """Run the commands, copy the pictures, return the manifest's entries."""
    GALLERY.mkdir(parents=True, exist_ok=True)
    entries: list[dict[str, str]] = []

    def keep(src: Path, name: str, caption: str, command: str) -> None:
        shutil.copyfile(src, GALLERY / name)
        entries.append({"file": name, "caption": caption, "command": command})

    with tempfile.TemporaryDirectory(prefix="gallery-") as tmp:
        t = Path(tmp)
        cmd = "flightstack run paper_sim"
        _run(["run", "paper_sim", "--out", str(t / "paper"), "--no-progress"])
        keep(t / "paper" / "trajectory.png", "paper_trajectory.png",
             "The paper's simulation: the target's path, the three experts' regions and their training data",
             cmd)  # fmt: skip
        keep(t / "paper" / "error_ec.png", "paper_error_ec.png", "‖e_c‖ per mode (paper Fig. 4)", cmd)
        keep(t / "paper" / "error_ee.png", "paper_error_ee.png", "‖e_e‖ per mode (paper Fig. 5)", cmd)
        if sweep is None:
            sweep = t / "sweep"
            _run(["sweep", "paper_sim", "--seeds", "20", "--jobs", "2", "--out", str(sweep)])
        cmd = "flightstack sweep paper_sim --seeds 20"
        keep(
            sweep / "errors.png",
            "sweep_errors.png",
            "20 seeds of the paper's simulation: each mode's error, mean and 95 % confidence interval",
            cmd,
        )
        if (sweep / "ratios.png").is_file():
            keep(sweep / "ratios.png", "sweep_ratios.png",
                 "Ratios none/dgp and local/dgp over the seeds, the paper's values dashed", cmd)  # fmt: skip
        _run(["bench-loop", "--seconds", "10", "--out", str(t / "bench")])
        keep(
            t / "bench" / "loop_health.png",
            "loop_health.png",
            "Loop health on the emulated lab (2 drones' video decoded): period and compute time per tick "
            "against dt, and the age of the frame and pose each tick used",
            "flightstack bench-loop",
        )
        rows = [a for r in SIM_FAULT_ROWS for a in ("--only", r)]
        _run(["faults", *rows, "--out", str(t / "faults")])
        keep(t / "faults" / "faults.png", "faults.png",
             "The fault table's simulated rows: verdict and the safety events of each run",
             "flightstack faults " + " ".join(rows))  # fmt: skip
    return entries


def render(manifest: dict[str, Any]) -> str:
    """The page's section (between the markers) for a manifest."""
    lines = [
        f"Made by `python benchmarks/gallery.py` at commit {manifest['commit']} on {manifest['date']} "
        f"({manifest['machine']}); every picture is the output of the command under it.",
        "",
    ]
    for e in manifest["entries"]:
        lines += [
            f"**{e['caption']}** (`{e['command']}`)",
            "",
            f"![{e['caption']}]({GALLERY.name}/{e['file']})",
            "",
        ]
    return "\n".join(lines)


def page_section() -> str:
    """docs/gallery.md's current text between the gallery markers."""
    return read_block(PAGE, "gallery")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sweep", type=Path, default=None, help="a finished `flightstack sweep` directory")
    ap.add_argument("--check", action="store_true", help="only re-render docs/gallery.md from the manifest")
    args = ap.parse_args(argv)
    if not args.check:
        entries = make(args.sweep)
        manifest = {
            "commit": _commit(),
            "date": datetime.date.today().isoformat(),
            "machine": f"{os.cpu_count()} cores",
            "entries": entries,
        }
        MANIFEST.write_text(json.dumps(manifest, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    manifest = json.loads(MANIFEST.read_text(encoding="utf-8"))
    write_block(PAGE, "gallery", render(manifest))
    print(f"{PAGE.relative_to(REPO)}: {len(manifest['entries'])} pictures in {GALLERY.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
