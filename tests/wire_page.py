"""The prediction layout as docs/wire-format.md states it, read from the page's text (not from the package):
what an independent reader of the manual has. Used by tests/test_wire_format.py (produced messages) and
tests/test_wire_subscriber.py (messages heard on a running bus)."""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PAGE = Path(__file__).resolve().parents[1] / "docs" / "wire-format.md"
_ROW = re.compile(r"^\| ([0-9L +]+) \| (\S+) \| (`[^`]+`|UTF-8) \| `([\w.]+)` \|", re.MULTILINE)


@dataclass(frozen=True)
class PageField:
    """One row of the page's prediction table: offset = base + (L if after_name) (bytes)."""

    name: str
    base: int
    after_name: bool
    fmt: str | None  # a struct format; None: the UTF-8 mission name (L bytes)


def prediction_layout(text: str | None = None) -> list[PageField]:
    """The rows of the page's prediction table (between its generated-block markers), in order."""
    text = PAGE.read_text(encoding="utf-8") if text is None else text
    block = text.split("<!-- generated: wire-prediction -->", 1)[1].split("<!-- /generated", 1)[0]
    fields = []
    for offset, _size, fmt, name in _ROW.findall(block):
        terms = [t.strip() for t in offset.split("+")]
        after = "L" in terms
        base = sum(int(t) for t in terms if t != "L")
        fields.append(PageField(name, base, after, None if fmt == "UTF-8" else fmt.strip("`")))
    return fields


def decode_with_page(data: bytes, layout: list[PageField]) -> dict[str, Any]:
    """Every field of a prediction message by the page's offsets and struct formats alone."""
    by_name = {f.name: f for f in layout}
    length = by_name["name_len"]
    assert length.fmt is not None and not length.after_name
    (name_len,) = struct.unpack_from(length.fmt, data, length.base)
    out: dict[str, Any] = {}
    for f in layout:
        offset = f.base + (name_len if f.after_name else 0)
        if f.fmt is None:
            out[f.name] = data[offset : offset + name_len].decode("utf-8")
        else:
            (out[f.name],) = struct.unpack_from(f.fmt, data, offset)
    return out


def same_as_project(page: dict[str, Any], msg: Any) -> list[str]:
    """The fields where the page's decoding differs from the project's decoded PredictionMessage `msg`."""
    want: dict[str, Any] = {
        "sender": msg.sender,
        "seq": msg.seq,
        "stamp": msg.stamp,
        "mission": msg.mission,
        "flags": int(msg.visible),
    }
    comps = {"g_bar_w": ("x", "y", "z", "theta"), "mu": ("v_x", "v_y", "v_z", "omega")}
    comps["var"] = comps["prior_var"] = comps["mu"]
    for arr, names in comps.items():
        for k, c in enumerate(names):
            want[f"{arr}.{c}"] = float(getattr(msg, arr)[k])
    return [f"{k}: page {page.get(k)!r} != {v!r}" for k, v in want.items() if page.get(k) != v]
