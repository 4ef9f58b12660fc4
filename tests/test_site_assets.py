"""The manual's site loads nothing from another address, so that an offline laptop renders it (equations
included): mkdocs.yml's scripts and styles are files of the site, the theme loads no web fonts, no page
embeds a remote script, style or image, and the vendored MathJax has every file it fetches, with its
licence (docs/javascripts/mathjax/README.txt)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
MATHJAX = DOCS / "javascripts" / "mathjax"
REMOTE = re.compile(r"^(?:[a-z][a-z0-9+.-]*:)?//", re.IGNORECASE)
EMBEDDED_REMOTE = re.compile(
    r"""<(?:script|link|img|iframe|source)\b[^>]*\b(?:src|href)\s*=\s*["']?(?:https?:)?//"""
    r"""|!\[[^\]]*\]\(\s*<?(?:https?:)?//""",
    re.IGNORECASE,
)


def _mkdocs() -> dict[str, Any]:
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text(encoding="utf-8"))
    assert isinstance(config, dict)
    return config


def _entries(config: dict[str, Any], key: str) -> list[str]:
    """The paths of extra_javascript / extra_css (a string or a mapping with `path`)."""
    return [e if isinstance(e, str) else e["path"] for e in config.get(key, [])]


def test_every_script_and_style_is_a_file_of_the_site() -> None:
    config = _mkdocs()
    assets = _entries(config, "extra_javascript") + _entries(config, "extra_css")
    assert any("mathjax" in a for a in assets), assets  # the equations' renderer is among them
    remote = [a for a in assets if REMOTE.match(a)]
    assert not remote, f"mkdocs.yml loads assets from other addresses: {remote}"
    missing = [a for a in assets if not (DOCS / a).is_file()]
    assert not missing, f"mkdocs.yml names assets that docs/ does not hold: {missing}"


def test_the_theme_loads_no_web_fonts() -> None:
    """Material's default font is fetched from Google Fonts; `font: false` keeps the system's."""
    assert _mkdocs()["theme"].get("font") is False


def test_no_page_embeds_a_remote_asset() -> None:
    offenders = [
        f"{page.relative_to(REPO)}: {m.group(0)}"
        for page in sorted(DOCS.rglob("*.md"))
        for m in EMBEDDED_REMOTE.finditer(page.read_text(encoding="utf-8"))
    ]
    assert not offenders, offenders
    assert EMBEDDED_REMOTE.search('<script src="https://unpkg.com/x.js"></script>')  # the check sees one
    assert EMBEDDED_REMOTE.search("![plot](https://example.org/a.png)")
    assert not EMBEDDED_REMOTE.search("[a link](https://doi.org/10.1/x)")  # links are not assets


def test_vendored_mathjax_has_the_fonts_and_extensions_it_fetches_and_its_licence() -> None:
    script = (MATHJAX / "tex-mml-chtml.js").read_text(encoding="utf-8")
    fonts = set(re.findall(r"MathJax_[A-Za-z0-9-]+\.woff", script))
    assert len(fonts) > 10
    missing = sorted(f for f in fonts if not (MATHJAX / "output/chtml/fonts/woff-v2" / f).is_file())
    assert not missing, f"fonts MathJax loads that are not vendored: {missing}"
    extensions = set(re.findall(r'"\[tex\]/([a-z0-9]+)"', script))
    assert len(extensions) > 20
    missing = sorted(e for e in extensions if not (MATHJAX / "input/tex/extensions" / f"{e}.js").is_file())
    assert not missing, f"TeX extensions MathJax may autoload that are not vendored: {missing}"
    assert "Apache License" in (MATHJAX / "LICENSE").read_text(encoding="utf-8")
    assert "mathjax@3.2.2" in (MATHJAX / "README.txt").read_text(encoding="utf-8")
