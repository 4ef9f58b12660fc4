"""One truth per setting: Motive's streaming settings are stated once, in the table of docs/real-lab.md
("Motive's streaming settings"), and every page that states Motive's transmission type, up axis, command or
data port or multicast group says what that table says (a stated default: Motive's default there).

A statement is recognised in a paragraph, list item or table row that names Motive, NatNet or OptiTrack, in
the forms the pages use: "Transmission Type: X", "X transmission", "set … transmission type to X", "Motive
streams X", "Up Axis: X", "Up Axis = X", "with X up", "command port N", "data port N", a multicast address;
and, in a clause that names Motive's default, a bare "multicast", "Y up" or "Y axis". The CHANGELOG is
history and is not read."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.test_docs import _prose, anchors

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
TRUTH_PAGE = DOCS / "real-lab.md"
SECTION = "Motive's streaming settings"
ANCHOR = "real-lab.md#motives-streaming-settings"
PAGES = [REPO / "README.md", *sorted(p for p in DOCS.rglob("*.md") if "hooks" not in p.parts)]

SETTINGS = {  # the table's first column -> the setting's name here
    "up axis": "up axis",
    "transmission type": "transmission",
    "command port": "command port",
    "data port": "data port",
    "multicast interface": "multicast group",
}
MOTIVE = re.compile(r"\b(motive|natnet|optitrack)\b")
BOUNDARY = re.compile(r"\.\s|[;()|]")
MOTIVE_DEFAULT = re.compile(r"motive's defaults?\b")
DEFAULT_AFTER = re.compile(r"\s*(\((its|motive's) default\s*[),;]|by default)")
GROUP = r"(2(?:2[4-9]|3\d)\.\d{1,3}\.\d{1,3}\.\d{1,3})"
FORMS: tuple[tuple[str, re.Pattern[str]], ...] = tuple(
    (setting, re.compile(form))
    for setting, form in (
        ("transmission", r"transmission(?: type)?\s*(?::|=|to|is)\s*(unicast|multicast)\b"),
        ("transmission", r"\b(unicast|multicast)\s+transmission\b"),
        ("transmission", r"\bmotive\s+streams\s+(?:by\s+|in\s+)?(unicast|multicast)\b"),
        ("up axis", r"\bup[ -]axis\s*(?:setting\s*)?(?::|=|to|is)\s*([xyz])\b"),
        ("up axis", r"\bmotive\s+streams\s+([xyz])[ -]up\b"),
        ("up axis", r"\bwith\s+([xyz])[ -]up\b"),
        ("command port", r"\bcommand port\b\D{0,25}?\b(\d{4,5})\b"),
        ("data port", r"\bdata port\b\D{0,25}?\b(\d{4,5})\b"),
        ("multicast group", rf"\b{GROUP}\b"),
    )
)
BARE_DEFAULTS: tuple[tuple[str, re.Pattern[str]], ...] = (
    ("transmission", re.compile(r"\b(unicast|multicast)\b")),
    ("up axis", re.compile(r"\b([xyz])(?:[ -]up| axis)\b")),
)


@dataclass(frozen=True)
class Claim:
    """One statement of a setting on a page: its value, and whether it states Motive's default."""

    page: str
    setting: str
    value: str
    default: bool
    text: str


def _value(setting: str, text: str) -> str:
    """A table cell or a matched value in the one spelling claims are compared in."""
    text = text.strip().lower()
    if setting == "up axis":
        return text.split()[0]
    if setting == "transmission":
        return text
    return re.findall(r"[\d.]+", text)[0]


def truth(markdown: str) -> dict[str, tuple[str, str]]:
    """The section's table: setting -> (what to set it to, Motive's default)."""
    section = markdown.split(f"### {SECTION}", 1)[1].split("\n#", 1)[0]
    out: dict[str, tuple[str, str]] = {}
    for row in re.findall(r"^\|(.+)\|\s*$", section, re.M):
        cells = [c.strip() for c in row.split("|")]
        setting = SETTINGS.get(cells[0].lower())
        if setting is not None:
            out[setting] = (_value(setting, cells[1]), _value(setting, cells[2]))
    return out


def without_truth_table(markdown: str) -> str:
    """The page without the section's table rows (the truth is not a claim about itself)."""
    head, sep, rest = markdown.partition(f"### {SECTION}")
    section, nxt, tail = rest.partition("\n#")
    section = "\n".join(ln for ln in section.splitlines() if not ln.lstrip().startswith("|"))
    return head + sep + section + nxt + tail


def units(markdown: str) -> list[str]:
    """The prose's paragraphs, list items and table rows, one line each: lower case, a link as its text,
    no emphasis, no code."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", _prose(markdown))
    text = re.sub(r"\*\*|\*|__", "", text).lower()
    out: list[str] = []
    for block in re.split(r"\n\s*\n", text):
        current: list[str] = []
        for line in block.splitlines():
            if re.match(r"\s*(?:[-+]|\d+\.|\|)\s", line) and current:
                out.append(" ".join(current))
                current = []
            current.append(line.strip())
        if current:
            out.append(" ".join(current))
    return out


def _names_default(unit: str, start: int, end: int) -> bool:
    """Whether the clause up to the value names Motive's default, or the value is followed by one."""
    clause = BOUNDARY.split(unit[:start])[-1]
    return bool(MOTIVE_DEFAULT.search(clause) or DEFAULT_AFTER.match(unit, end))


def claims(page: str, markdown: str) -> list[Claim]:
    """Every statement of Motive's settings on a page (module docstring)."""
    found: list[Claim] = []
    for unit in units(markdown):
        if not MOTIVE.search(unit):
            continue
        taken: set[int] = set()
        for setting, form in FORMS:
            for m in form.finditer(unit):
                default = _names_default(unit, m.start(1), m.end())
                found.append(Claim(page, setting, _value(setting, m.group(1)), default, unit))
                taken.add(m.start(1))
        for setting, form in BARE_DEFAULTS:
            for m in form.finditer(unit):
                clause = BOUNDARY.split(unit[: m.start(1)])[-1]
                if m.start(1) not in taken and MOTIVE_DEFAULT.search(clause):
                    found.append(Claim(page, setting, _value(setting, m.group(1)), True, unit))
    return found


def disagreements(found: list[Claim], table: dict[str, tuple[str, str]]) -> list[str]:
    """One line per claim that is not what the table says."""
    out = []
    for c in found:
        want = table[c.setting][1 if c.default else 0]
        if c.value != want:
            which = "Motive's default" if c.default else "the setting"
            out.append(
                f"{c.page}: {c.setting} {c.value!r}, but {which} is {want!r} ({ANCHOR}): {c.text[:200]}"
            )
    return out


def _pages() -> dict[str, str]:
    texts = {str(p.relative_to(REPO)): p.read_text(encoding="utf-8") for p in PAGES}
    key = str(TRUTH_PAGE.relative_to(REPO))
    texts[key] = without_truth_table(texts[key])
    return texts


def _all_claims(texts: dict[str, str]) -> list[Claim]:
    return [c for page, text in texts.items() for c in claims(page, text)]


TABLE = truth(TRUTH_PAGE.read_text(encoding="utf-8"))


def test_the_settings_are_stated_in_one_table() -> None:
    assert TABLE == {
        "up axis": ("z", "y"),
        "transmission": ("multicast", "multicast"),
        "multicast group": ("239.255.42.99", "239.255.42.99"),
        "command port": ("1510", "1510"),
        "data port": ("1511", "1511"),
    }
    assert "motives-streaming-settings" in anchors(TRUTH_PAGE)
    rows = [p for p in PAGES if re.search(r"^\| *Transmission Type *\|", p.read_text("utf-8"), re.M)]
    assert rows == [TRUTH_PAGE]


@pytest.mark.parametrize("page", ["checklist.md", "troubleshooting.md", "supported.md"])
def test_the_pages_that_name_motives_settings_link_to_the_table(page: str) -> None:
    assert f"]({ANCHOR})" in (DOCS / page).read_text(encoding="utf-8"), page


def test_every_page_agrees_with_the_table() -> None:
    found = _all_claims(_pages())
    assert not disagreements(found, TABLE), "\n".join(disagreements(found, TABLE))
    # not vacuous: the checker reads statements of each setting, a stated default and other pages' words
    assert {c.setting for c in found} >= {"transmission", "up axis", "data port"}, found
    assert any(c.default for c in found) and any(not c.default for c in found)
    assert {c.page for c in found} >= {"docs/drivers.md", "docs/supported.md"}


PLANTED = [  # (a statement that contradicts the table, the setting it gets wrong)
    (  # what docs/checklist.md said before the table was the one truth
        "- [ ] Motive streams rigid bodies on the interface of the lab network, with **Z up** (Motive's "
        "default is Y\n  up; flightstack's world frame is z up) and **unicast** transmission (the verified "
        "path:\n  [Troubleshooting](troubleshooting.md#multicast)).",
        "transmission",
    ),
    (  # what docs/troubleshooting.md said
        "- **Motive** streams by multicast by default (239.255.42.99, data port 1511). Set Motive's "
        "transmission type to Unicast ([Pre-flight checklist](checklist.md#motion-capture)).",
        "transmission",
    ),
    ("In Motive, set **Up Axis: Y Axis** before the first preflight.", "up axis"),
    ("Motive streams Z up by default.", "up axis"),
    ("| motion capture (OptiTrack NatNet) | out to the server's command port 1520 | UDP |", "command port"),
    ("Motive sends every frame to its data port 9000.", "data port"),
    ("Motive streams to the multicast group 239.255.42.100.", "multicast group"),
]


@pytest.mark.parametrize(("statement", "setting"), PLANTED, ids=[s for _, s in PLANTED])
def test_a_planted_contradiction_fails(statement: str, setting: str) -> None:
    texts = _pages()
    texts["docs/checklist.md"] += f"\n\n{statement}\n"
    found = disagreements(_all_claims(texts), TABLE)
    assert len(found) == 1 and found[0].startswith(f"docs/checklist.md: {setting} "), found


def test_statements_that_agree_are_not_flagged() -> None:
    """Motive's own default stated as its default, and the lab's settings stated as such, pass."""
    page = (
        "Motive streams Y up (its default): set Up Axis to Z Axis. Motive's default is Y Axis; keep its "
        "Transmission Type: Multicast, its Command Port 1510 and its Data Port 1511.\n\n"
        "- The emulator streams unicast to an ephemeral port, which is not Motive's way.\n"
    )
    found = claims("page.md", page)
    assert {(c.setting, c.value, c.default) for c in found} == {
        ("up axis", "z", False),
        ("up axis", "y", True),
        ("transmission", "multicast", False),
        ("command port", "1510", False),
        ("data port", "1511", False),
    }
    assert not disagreements(found, TABLE)
