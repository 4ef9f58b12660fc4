"""CITATION.cff is valid Citation File Format 1.2.0 (the schema shipped in tests/data/cff-1.2.0/, with its
source and licence): the software's version and release date as pyproject.toml and CHANGELOG.md give them,
and as its preferred citation the paper it implements, typed as what it is; the manual's BibTeX entry says
the same."""

from __future__ import annotations

import json
import re
import tomllib
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
    bad["preferred-citation"]["doi"] = "arXiv:2205.13714"
    assert list(validator.iter_errors(bad))


def test_the_preferred_citation_is_the_ifac_conference_paper() -> None:
    """The paper as published: a conference paper of the IFAC World Congress 2023 (proceedings
    IFAC-PapersOnLine). The only identifiers known here are its arXiv preprint's, given as such, never as
    the conference paper's DOI."""
    paper = _citation()["preferred-citation"]
    assert paper["type"] == "conference-paper" and paper["title"] == TITLE
    assert [a["family-names"] for a in paper["authors"]] == AUTHORS
    assert paper["year"] == 2023 and paper["conference"]["name"] == "IFAC World Congress 2023"
    assert paper["collection-title"] == "IFAC-PapersOnLine"
    assert "10.48550" not in str(paper.get("doi", "")), "the arXiv DOI is the preprint's, not the paper's"
    assert paper["url"] == f"https://arxiv.org/abs/{ARXIV}"
    ids = {(i["type"], i["value"]) for i in paper["identifiers"]}
    assert ids == {("other", f"arXiv:{ARXIV}"), ("url", f"https://arxiv.org/abs/{ARXIV}")}
    assert all("preprint" in i["description"] for i in paper["identifiers"])
    assert "references" not in _citation()  # the paper is stated once


def test_the_version_is_pyprojects_and_released_on_its_changelog_date() -> None:
    data = _citation()
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert data["version"] == project["version"]
    changelog = (REPO / "CHANGELOG.md").read_text(encoding="utf-8")
    released = re.search(
        rf"^## \[{re.escape(project['version'])}\] - (\d{{4}}-\d{{2}}-\d{{2}})$", changelog, re.M
    )
    assert released is not None, f"CHANGELOG.md: no heading for {project['version']}"
    assert data["date-released"] == released.group(1)
    assert data["license"] == "MIT" and project["license"] == "MIT"


def test_the_citation_names_the_code_repository_pyproject_names() -> None:
    """`repository-code` is the repository pyproject.toml names (`[project.urls] Repository`), an https
    address; while pyproject names none (the project has no public address yet), the citation names none
    either: no address is made up."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    url = project.get("urls", {}).get("Repository")
    cited = _citation().get("repository-code")
    assert cited == url, (cited, url)
    assert url is None or url.startswith("https://")


def _bibtex() -> tuple[str, str, dict[str, str]]:
    """The BibTeX entry of the manual's "How to cite": (entry type, key, fields)."""
    text = (REPO / "docs" / "index.md").read_text(encoding="utf-8")
    block = re.search(r"^## How to cite\n.*?```bibtex\n(.*?)```", text, re.M | re.S)
    assert block is not None, "docs/index.md: no BibTeX block under `## How to cite`"
    head = re.match(r"@(\w+)\{([^,\s]+),\n", block.group(1))
    assert head is not None, block.group(1)
    fields = dict(re.findall(r"^\s+(\w+)\s*=\s*\{(.*)\},$", block.group(1), re.M))
    return head.group(1), head.group(2), fields


def test_the_docs_give_a_bibtex_entry_of_the_paper() -> None:
    """A real key (first author, year, first title word), and the year, URL and authors of CITATION.cff."""
    kind, key, fields = _bibtex()
    paper = _citation()["preferred-citation"]
    assert kind == "inproceedings"  # BibTeX's conference paper
    assert key == f"saito{paper['year']}distributed"
    assert fields["year"] == str(paper["year"]) == "2023"
    assert fields["url"] == paper["url"] == f"https://arxiv.org/abs/{ARXIV}"
    assert fields["eprint"] == ARXIV and fields["archivePrefix"] == "arXiv"
    assert fields["title"].strip("{}") == TITLE
    assert [a.split(",")[0] for a in fields["author"].split(" and ")] == AUTHORS


def test_every_page_that_names_the_paper_gives_its_arxiv_link() -> None:
    """The README and the manual cite the paper the same way: by name and with its arXiv link."""
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    naming = [p for p in pages if "Saito" in p.read_text(encoding="utf-8")]
    assert len(naming) >= 4, naming  # README, index, equations, paper-comparison at least
    link = f"[arXiv:{ARXIV}](https://arxiv.org/abs/{ARXIV})"
    missing = [str(p.relative_to(REPO)) for p in naming if link not in p.read_text(encoding="utf-8")]
    assert not missing, f"pages that name the paper without {link}: {missing}"
