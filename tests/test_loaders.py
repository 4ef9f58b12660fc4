"""One hardened loader (flightstack/config/safe_load.py) for missions and calibration files.

Every input the fuzzer once crashed or hung the loaders with exits 2 (`flightstack validate`) with one
line naming the file and, where there is one, the line and key path. Property tests: arbitrary bytes
and arbitrary edits of the shipped mission either load or raise the loader's own error, nothing else.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from flightstack.cli.app import main
from flightstack.config.mission import MissionError, load_mission
from flightstack.safe_yaml import LoadError, load_yaml
from flightstack.vision.camera_file import CalibrationError, load_calibration
from tests.conftest import MISSIONS

SIM = MISSIONS / "paper_sim.yaml"
CAL = MISSIONS / "cameras" / "tello_down_template.yaml"


def validate(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["validate", str(path)])
    return code, capsys.readouterr().err


BAD_FILES: list[tuple[str, bytes, str]] = [
    ("utf8.yaml", b"name: \xff\xfe\n", "not UTF-8 text (byte 6)"),
    ("utf16.yaml", "name: x\n".encode("utf-16"), "UTF-16 text"),
    ("bigint.yaml", b"seed: " + b"9" * 5000 + b"\n", "line 1, seed: an integer of 5000 digits"),
    ("deep.yaml", b"[" * 100_000, "nested too deeply"),  # crashed libyaml's C composer (segfault)
    ("deep2.yaml", b"[" * 10_000 + b"]" * 10_000, "nested too deeply"),
    ("deep3.yaml", b"a: " + b"[" * 100 + b"]" * 100 + b"\n", "line 1, a.0.0.0"),
    ("dup.yaml", SIM.read_bytes() + b"seed: 3\n", "duplicate key 'seed'"),
    (
        "bomb.yaml",
        SIM.read_bytes()
        + b"x0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]\n"
        + b"".join(f"x{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n".encode() for i in range(1, 9)),
        "anchors and aliases are not allowed",
    ),
    ("big.yaml", b"# " + b"x" * (1 << 20) + b"\n", "larger than 1048576 bytes"),
]


@pytest.mark.parametrize(("name", "data", "why"), BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_bad_mission_files_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, data: bytes, why: str
) -> None:
    path = tmp_path / name
    path.write_bytes(data)
    code, err = validate(path, capsys)
    assert code == 2, err
    assert why in err and str(path) in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_devices_fifos_and_directories_exit_2_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # nobody writes: a plain open() would block forever
    cases = [(fifo, "is a FIFO"), (tmp_path, "is a directory")]
    if Path("/dev/zero").exists():
        cases.append((Path("/dev/zero"), "is a device"))  # was read until MemoryError
    for path, why in cases:
        code, err = validate(path, capsys)
        assert code == 2 and why in err, err


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"seed": -1}, "seed: Input should be greater than or equal to 0"),
        ({"dt_s": 1e-300}, "dt_s: Input should be greater than or equal to 0.0001"),
        ({"duration_s": 86400, "dt_s": 0.0001}, "at most 1e+07"),
    ],
)
def test_values_the_runtime_cannot_use_are_refused_by_the_schema(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], change: dict[str, object], why: str
) -> None:
    m = yaml.safe_load(SIM.read_text())
    m.update(change)
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(m))
    code, err = validate(path, capsys)
    assert code == 2 and why in err, err
    assert "(line " in err or "(top level)" in err  # the line of the offending key, where there is one


def test_duration_zero_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["sim", str(SIM), "--duration", "0"])
    assert exc.value.code == 2
    assert "must be a finite number of seconds > 0" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        ("markers: 5", "markers"),
        ('rms_px: "x"', "rms_px"),
        ("rms_px: .nan", "rms_px"),
        ("rms_px: -1", "rms_px"),
    ],
)
def test_bad_calibration_fields_are_named(tmp_path: Path, edit: str, field: str) -> None:
    doc = yaml.safe_load(CAL.read_text())
    key = edit.split(":")[0]
    doc.pop(key, None)
    path = tmp_path / "cal.yaml"
    path.write_text(yaml.safe_dump(doc) + edit + "\n")
    with pytest.raises(CalibrationError, match=rf"cal\.yaml: {field}:"):
        load_calibration(path)


@pytest.mark.system  # long (emulator or fuzzing): the system tier
@settings(max_examples=3000)
@given(st.binary(max_size=400))
def test_arbitrary_bytes_load_or_raise_load_error(data: bytes) -> None:
    import tempfile

    with tempfile.NamedTemporaryFile(suffix=".yaml") as f:
        f.write(data)
        f.flush()
        with contextlib.suppress(LoadError):  # anything else fails the test
            load_yaml(f.name)


_LINES = SIM.read_text().splitlines()
_SCALARS = st.sampled_from(
    [
        "-1",
        "1e-300",
        ".nan",
        ".inf",
        "~",
        "[]",
        "{}",
        "'x'",
        "9" * 40,
        "*a",
        "&a 1",
        "[[[[",
        "true",
        "0",
        "-0.0",
    ]
)


@pytest.mark.system  # long (emulator or fuzzing): the system tier
@settings(max_examples=1500)
@given(st.integers(0, len(_LINES) - 1), st.sampled_from(["delete", "duplicate", "value"]), _SCALARS)
def test_edited_missions_load_or_raise_mission_error(line: int, how: str, scalar: str) -> None:
    import tempfile

    lines = list(_LINES)
    if how == "delete":
        del lines[line]
    elif how == "duplicate":
        lines.insert(line, lines[line])
    elif ":" in lines[line]:
        key = lines[line].split(":", 1)[0]
        lines[line] = f"{key}: {scalar}"
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "m.yaml"
        path.write_text("\n".join(lines) + "\n")
        with contextlib.suppress(MissionError):  # anything else fails the test
            load_mission(path, check_files=False)


@pytest.mark.system  # long (emulator or fuzzing): the system tier
@settings(max_examples=800)
@given(st.sampled_from(list(yaml.safe_load(CAL.read_text()))), _SCALARS)
def test_edited_calibrations_load_or_raise_calibration_error(key: str, scalar: str) -> None:
    import tempfile

    lines = [ln for ln in CAL.read_text().splitlines() if not ln.startswith(f"{key}:")]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "c.yaml"
        path.write_text("\n".join(lines) + f"\n{key}: {scalar}\n")
        with contextlib.suppress(CalibrationError):  # anything else fails the test
            load_calibration(path)
