"""CITATION.cff is valid Citation File Format 1.2.0 (the schema shipped in tests/data/cff-1.2.0/, with its
source and licence) and cites the paper the project implements by its arXiv identifier."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import yaml

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "tests" / "data" / "cff-1.2.0" / "schema.json"
ARXIV = "2205.13714"
TITLE = "Distributed Gaussian Process Based Cooperative Visual Pursuit Control for Drone Networks"
AUTHORS = ["Saito", "Yamauchi", "Fujinami", "Omainska", "Fujita"]


def _citation() -> dict[str, Any]:
    data = yaml.safe_load((REPO / "CITATION.cff").read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def test_citation_file_is_valid_cff_1_2_0() -> None:
    schema = json.loads(SCHEMA.read_text(encoding="utf-8"))
    assert schema["$id"] == "https://citation-file-format.github.io/1.2.0/schema.json"
    data = _citation()
    assert data["cff-version"] == "1.2.0"
    checker = jsonschema.FormatChecker()
    jsonschema.validate(data, schema, cls=jsonschema.Draft7Validator, format_checker=checker)


def test_the_validation_rejects_an_invalid_citation() -> None:
    """The check above is not vacuous: the schema refuses a citation without authors or with a bad DOI."""
    schema = json.loads(SCHEMA.read_text(encoding="utf-8"))
    validator = jsonschema.Draft7Validator(schema)
    data = _citation()
    assert not list(validator.iter_errors(data))
    assert list(validator.iter_errors({k: v for k, v in data.items() if k != "authors"}))
    bad = json.loads(json.dumps(data))
    bad["references"][0]["doi"] = "arXiv:2205.13714"
    assert list(validator.iter_errors(bad))


def test_citation_cites_the_paper_by_its_arxiv_identifier() -> None:
    data = _citation()
    papers = [r for r in data.get("references", []) if r.get("title") == TITLE]
    assert len(papers) == 1, f"CITATION.cff: one reference titled {TITLE!r} expected"
    paper = papers[0]
    assert [a["family-names"] for a in paper["authors"]] == AUTHORS
    assert paper["year"] == 2023 and paper["conference"]["name"] == "IFAC World Congress 2023"
    assert paper["doi"] == f"10.48550/arXiv.{ARXIV}"
    assert paper["url"] == f"https://arxiv.org/abs/{ARXIV}"
    assert {"type": "other", "value": f"arXiv:{ARXIV}"}.items() <= paper["identifiers"][0].items()


def test_citation_keeps_no_copy_of_the_version_and_names_the_licence() -> None:
    """The version lives in pyproject.toml only; the licence is the one pyproject declares."""
    data = _citation()
    assert "version" not in data
    assert data["license"] == "MIT"
    assert 'license = "MIT"' in (REPO / "pyproject.toml").read_text(encoding="utf-8")


def test_every_page_that_names_the_paper_gives_its_arxiv_link() -> None:
    """The README and the manual cite the paper the same way: by name and with its arXiv link."""
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    naming = [p for p in pages if "Saito" in p.read_text(encoding="utf-8")]
    assert len(naming) >= 4, naming  # README, index, equations, paper-comparison at least
    link = f"[arXiv:{ARXIV}](https://arxiv.org/abs/{ARXIV})"
    missing = [str(p.relative_to(REPO)) for p in naming if link not in p.read_text(encoding="utf-8")]
    assert not missing, f"pages that name the paper without {link}: {missing}"
