"""The generated blocks of the manual (docs/hooks/generated.py) are committed up to date, so a reader on a
code host sees the same CLI reference, file list, event kinds, fault rows and import contract as the site.
A stale block fails here; `python3 docs/hooks/generated.py --update` rewrites it."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]
HOOK = REPO / "docs" / "hooks" / "generated.py"


def _hook() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docs_generated_hook", HOOK)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


HOOK_MODULE = _hook()
PAGES = HOOK_MODULE.pages_with_blocks()


def test_every_renderer_has_a_committed_block() -> None:
    names = {n for p in PAGES for n in HOOK_MODULE.OPEN.findall(p.read_text(encoding="utf-8"))}
    assert names == set(HOOK_MODULE.RENDERERS), names


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_committed_block_is_current(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    fresh = HOOK_MODULE.render_blocks(text, str(page.relative_to(REPO)))
    where = page.relative_to(REPO)
    assert fresh == text, f"{where}: a generated block is stale: python3 docs/hooks/generated.py --update"
    for name, body in HOOK_MODULE.BLOCK.findall(text):
        assert body.count("\n") >= 3, f"{where}: block {name} holds no content"


def test_a_block_without_its_closing_line_is_refused() -> None:
    with pytest.raises(ValueError, match="without its closing line"):
        HOOK_MODULE.render_blocks("<!-- generated: run-files -->\ntext\n", "page.md")
    with pytest.raises(ValueError, match="unknown generated block"):
        HOOK_MODULE.render_blocks("<!-- generated: nothing -->\n<!-- /generated: nothing -->\n", "page.md")
