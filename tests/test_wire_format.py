"""docs/wire-format.md against the code: every key the code builds is on the page, every channel's publisher
declares the encoding the page names, and a prediction decoded with nothing but the page's byte table and
`struct` equals the project's decoding (the page's tables are generated from the code, and
tests/test_generated_pages.py keeps them current; this checks that what they say is enough)."""

from __future__ import annotations

import inspect
import math
import re
import struct
from typing import Any

import numpy as np
import pytest
import zenoh

from flightstack.comms import acl, wire
from flightstack.comms.messages import PredictionMessage, decode, encode
from tests.wire_page import PAGE, decode_with_page, prediction_layout, same_as_project

TEXT = PAGE.read_text(encoding="utf-8")


def test_every_key_the_code_builds_is_on_the_page() -> None:
    builders = {f for name, f in inspect.getmembers(acl, inspect.isfunction) if name.endswith("_key")}
    assert builders == {c.builder for c in wire.CHANNELS}, "a key builder of acl.py without its channel"
    for c in wire.CHANNELS:
        assert f"`{c.pattern}`" in TEXT, c.pattern
        if c.encoding is not None:
            assert f"`{c.pattern}` |" in TEXT and f"`{c.encoding}`" in TEXT, c.name


def test_encodings_are_ones_zenoh_reads_back() -> None:
    """Each encoding text is what zenoh reports for it on receipt (str of the parsed Encoding), JSON is
    zenoh's predefined APPLICATION_JSON and the binary ones its APPLICATION_OCTET_STREAM with a schema."""
    for c in wire.CHANNELS:
        if c.encoding is not None:
            assert str(zenoh.Encoding(c.encoding)) == c.encoding
    assert zenoh.Encoding(wire.CONTROL_ENCODING) == zenoh.Encoding.APPLICATION_JSON
    octet = str(zenoh.Encoding.APPLICATION_OCTET_STREAM)
    for enc in (wire.PRED_ENCODING, wire.WORLD_TICK_ENCODING, wire.WORLD_CMD_ENCODING):
        assert enc.startswith(octet + ";") and zenoh.Encoding(enc) != zenoh.Encoding.APPLICATION_OCTET_STREAM


def _message(
    mission: str, sender: int, seq: int, visible: bool, rng: np.random.Generator
) -> PredictionMessage:
    body = np.concatenate(
        [rng.normal(size=4), rng.normal(size=4), rng.uniform(1e-6, 2.0, 4), rng.uniform(0.5, 3.0, 4)]
    )
    return PredictionMessage.of_body(mission, sender, seq, float(rng.uniform(0, 1e4)), visible, body)


@pytest.mark.parametrize("mission", ["", "lab", "paper_sim", "ü" * 32])
def test_a_prediction_decodes_with_the_page_alone(mission: str) -> None:
    layout = prediction_layout()
    assert [f.name for f in layout][:8] == [
        "magic", "version", "flags", "sender", "seq", "stamp", "name_len", "mission"
    ]  # fmt: skip
    assert len(layout) == 8 + 16
    rng = np.random.default_rng(len(mission))
    for k, visible in enumerate((True, False)):
        sender = 7 + 60000 * k
        data = encode(_message(mission, sender, 2**32 - 1 - k, visible, rng))
        msg, why = decode(data, mission, {sender})
        assert msg is not None, why
        page = decode_with_page(data, layout)
        assert page["magic"] == b"FSPM" and page["version"] == 1
        assert same_as_project(page, msg) == []
        # the page's total length (its sentence under the table)
        m = re.search(r"exactly (\d+) \+ L \+ (\d+) bytes", TEXT)
        assert m is not None and len(data) == int(m[1]) + page["name_len"] + int(m[2])


def test_the_pages_example_decoder_runs() -> None:
    """The page's `decode_prediction` example, executed as printed, on a produced message."""
    blocks = re.findall(r"```python\n(.*?)```", TEXT, re.DOTALL)
    code = next(b for b in blocks if "def decode_prediction" in b)
    scope: dict[str, Any] = {}
    exec(compile(code, str(PAGE), "exec"), scope)
    msg = _message("paper_sim", 3, 41, True, np.random.default_rng(0))
    out = scope["decode_prediction"](encode(msg))
    assert out["sender"] == 3 and out["seq"] == 41 and out["visible"] and out["mission"] == "paper_sim"
    assert out["stamp_s"] == msg.stamp
    for name in ("g_bar_w", "mu", "var", "prior_var"):
        assert list(out[name]) == getattr(msg, name).tolist()


def test_the_page_states_little_endian_and_the_struct_sizes() -> None:
    """Every struct format in the table is explicitly little endian and its size column is its size."""
    block = TEXT.split("<!-- generated: wire-prediction -->", 1)[1].split("<!-- /generated", 1)[0]
    rows = re.findall(r"^\| [0-9L +]+ \| (\d+) \| `([^`]+)` \|", block, re.MULTILINE)
    assert len(rows) == 7 + 16
    for size, fmt in rows:
        assert fmt.startswith("<") and struct.calcsize(fmt) == int(size), fmt
    assert math.isclose(struct.unpack("<d", struct.pack("<d", 0.1))[0], 0.1)
