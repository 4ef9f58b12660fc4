"""The README stays a front door (short), and every relative link of the README and of the docs pages points
to a file that exists. `mkdocs build --strict` (.ci/run) checks links between pages of docs/; the README
lies outside the site and docs/ pages may link out of it, so both are checked here, by file."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = REPO / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "hooks" not in p.parts)

MAX_README_LINES = 250
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")


def _prose(text: str) -> str:
    """The text outside fenced code blocks and inline code spans (links there are not links)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append(re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def relative_targets(markdown: str) -> list[str]:
    """The link and image targets of markdown text that name a file (no scheme, not a bare #anchor)."""
    targets = LINK.findall(_prose(markdown))
    return [t for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t, re.I) and not t.startswith("#")]


def relative_links(page: Path) -> list[str]:
    return relative_targets(page.read_text(encoding="utf-8"))


def slug(heading: str) -> str:
    """The anchor GitHub and MkDocs (toc's default slugify) give a heading of plain words."""
    text = re.sub(r"`|\*\*|\*", "", heading).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return re.sub(r"[\s]+", "-", text)


def anchors(page: Path) -> set[str]:
    return {slug(h) for h in re.findall(r"^#{1,6} +(.+?) *#*$", _prose(page.read_text("utf-8")), re.M)}


def test_readme_is_short() -> None:
    lines = README.read_text(encoding="utf-8").count("\n")
    assert lines <= MAX_README_LINES, f"README.md: {lines} lines, limit {MAX_README_LINES}; write in docs/"


@pytest.mark.parametrize("page", [README, *PAGES], ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_points_to_a_file(page: Path) -> None:
    missing = []
    for target in relative_links(page):
        path = target.split("#", 1)[0]
        if path and not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(REPO)}: links to missing files: {missing}"


def test_readme_anchors_exist() -> None:
    """README links into docs pages by heading (GitHub renders them; mkdocs never sees the README)."""
    broken = []
    for target in relative_links(README):
        path, _, anchor = target.partition("#")
        if anchor and path.endswith(".md") and anchor not in anchors(README.parent / path):
            broken.append(target)
    assert not broken, f"README.md: links to headings that do not exist: {broken}"


def test_the_link_checker_sees_links() -> None:
    """The checks above are not vacuous: the README links into docs/ and the gallery page shows pictures."""
    readme = relative_links(README)
    assert any(t.startswith("docs/") and t.endswith(".md") for t in readme)
    assert any(t.endswith(".png") for t in readme)
    assert any(t.endswith(".png") for t in relative_links(DOCS / "gallery.md"))
    sample = "a [b](c.md#d) `[e](f.md)` [g](https://h) ![i](j.png) [k](#l)"
    assert relative_targets(sample) == ["c.md#d", "j.png"]


def test_readme_results_come_from_the_sweep_table_script() -> None:
    """The README's results table is a generated block of benchmarks/sweep_tables.py, never typed."""
    spec = importlib.util.spec_from_file_location("sweep_tables", REPO / "benchmarks" / "sweep_tables.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    block = re.search(
        r"<!-- sweep:paper:summary:start[^\n]*-->\n(.*?)<!-- sweep:paper:summary:end -->",
        README.read_text(encoding="utf-8"),
        re.S,
    )
    assert block is not None and "| none/dgp |" in block.group(1)
    ci = {"mean": 1.0, "median": 1.0, "ci_low": 0.5, "ci_high": 1.5}
    mode = {"mean_sq_error": ci, "sq_mean_error": ci}
    summary = {
        "experiment": "paper_sim",
        "rig": "ideal",
        "seeds": 2,
        "points": [
            {
                "modes": {"none": mode, "local": mode, "dgp": mode},
                "ratios": {"mean_sq_error": {"none/dgp": ci, "local/dgp": ci}, "sq_mean_error": {}},
            }
        ],
    }
    table = mod.summary_table(summary)
    assert table.splitlines()[2].startswith("| mode |") and "3.0e-07" in table and "53.6" in table
