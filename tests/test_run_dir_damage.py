"""`flightstack report` (and `export`) on damaged run directories: each either rebuilds what it can and
says what it skipped, or stops with RunDirError naming the file in one line; never another exception
(flightstack.recording.files.REQUIRED_FILES / OPTIONAL_FILES)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from flightstack.analysis.report import rebuild_run
from flightstack.cli import app as cli
from flightstack.config.mission import load_mission
from flightstack.learning.training import ExpertData, save_datasets, save_experts
from flightstack.paper.gp import GPExpert, GPHyperparameters
from flightstack.recording.files import (
    DATASETS_FILE,
    EVENTS_FILE,
    EXPERTS_FILE,
    METRICS_FILE,
    MISSION_FILE,
    STATE_FILE,
    RunDirError,
)
from flightstack.recording.mcap_export import export_mcap
from flightstack.recording.rows import MAGIC
from flightstack.recording.run_dir import RunWriter
from flightstack.runtime.flight import resolved_mission_yaml
from tests.conftest import MISSIONS, random_recording

NPZ = "timeseries_none.npz"
CSV = "timeseries_none.csv"  # written beside the final npz
ROWS = "timeseries_dgp.rows"
DGP_NPZ = "timeseries_dgp.npz"
N_TICKS = 60
NAMES = frozenset(
    [NPZ, CSV, ROWS, STATE_FILE, EVENTS_FILE, METRICS_FILE, MISSION_FILE, DATASETS_FILE, EXPERTS_FILE]
)
"""The files of the small run directory (`_make_run`)."""


def _make_run(out: Path) -> None:
    """A small run directory of the ideal rig's mission (3 drones): mode `none` closed (final npz), mode
    `dgp` cut short by a kill (row stream only, recording.json still `running`), events, datasets,
    experts, mission_resolved.yaml and the metrics.json of a first report."""
    overrides = {"compare_modes": ["none", "dgp"], "gain_analysis": {"samples": 50}}  # a fast report
    mission = load_mission(MISSIONS / "paper_sim.yaml", overrides)
    ids = [d.id for d in mission.drones]
    (out / MISSION_FILE).parent.mkdir(parents=True, exist_ok=True)
    (out / MISSION_FILE).write_text(resolved_mission_yaml(mission))
    run = RunWriter(out, block_period_s=0.0)
    for mode, seed in (("none", 1), ("dgp", 2)):
        rec = random_recording(mode, ids, N_TICKS, seed)
        rec.events = [
            {"t": 0.0, "event": "takeoff", "mode": mode},
            {"t": 1.0, "event": "safety", "kind": "x"},
        ]
        w = run.mode(mode, ids, N_TICKS)
        w.append(rec, N_TICKS)
        if mode == "none":
            w.close(rec)
    assert run.drain()
    run._queue.put(None)  # the writer thread dies with the process: dgp stays a row stream
    rng = np.random.default_rng(0)
    data = [
        ExpertData(i, (0.0, 1.0), rng.normal(size=(5, 4)), rng.normal(size=(5, 4)), np.arange(5)) for i in ids
    ]
    save_datasets(out / DATASETS_FILE, data)
    hyper = GPHyperparameters(np.ones(4), np.ones((4, 4)), np.full(4, 0.01))
    save_experts(out / EXPERTS_FILE, {d.drone_id: GPExpert(d.X, d.Y, hyper) for d in data})
    rebuild_run(out, plots=False)
    assert {p.name for p in out.iterdir()} == NAMES


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pristine") / "run"
    _make_run(out)
    return out


def _rows_header(path: Path) -> tuple[dict, bytes]:
    """(header JSON, the rows after the header) of a row stream."""
    data = path.read_bytes()
    (n,) = struct.unpack("<I", data[len(MAGIC) : len(MAGIC) + 4])
    return json.loads(data[len(MAGIC) + 4 : len(MAGIC) + 4 + n]), data[len(MAGIC) + 4 + n :]


def _write_rows_header(path: Path, doc: dict, rows: bytes) -> None:
    body = json.dumps(doc).encode()
    path.write_bytes(MAGIC + struct.pack("<I", len(body)) + body + rows)


def _edit_json(name: str, edit: Callable[[dict], object]) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        doc = json.loads((run / name).read_text())
        (run / name).write_text(json.dumps(edit(doc)))

    return damage


def _edit_rows_header(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        doc, rows = _rows_header(run / ROWS)
        edit(doc)
        _write_rows_header(run / ROWS, doc, rows)

    return damage


def _header_length(n: int) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        data = bytearray((run / ROWS).read_bytes())
        data[len(MAGIC) : len(MAGIC) + 4] = struct.pack("<I", n)
        (run / ROWS).write_bytes(bytes(data))

    return damage


def _one_more_drone(doc: dict) -> None:
    doc["meta"]["drone_ids"].append(99)  # 4 drones named, the columns hold 3


def _column(name: str, **change: object) -> Callable[[dict], None]:
    def edit(doc: dict) -> None:
        next(c for c in doc["columns"] if c["name"] == name).update(change)

    return edit


def _npz(name: str, **arrays: np.ndarray) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        with open(run / name, "wb") as fh:
            np.savez(fh, **arrays)

    return damage


def _garbage(name: str, data: bytes) -> Callable[[Path], None]:
    return lambda run: (run / name).write_bytes(data)


def _seq_of_row(k: int, value: int) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        doc, rows = _rows_header(run / ROWS)
        itemsize = len(rows) // N_TICKS
        b = bytearray(rows)
        b[k * itemsize : k * itemsize + 8] = struct.pack("<q", value)
        _write_rows_header(run / ROWS, doc, bytes(b))

    return damage


def _truncate(name: str, cut: int) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        data = (run / name).read_bytes()
        (run / name).write_bytes(data[: len(data) - cut])

    return damage


def _zip_of_text(name: str) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        with zipfile.ZipFile(run / name, "w") as zf:
            zf.writestr("readme.txt", "not an array")

    return damage


def _append(name: str, data: bytes) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        with open(run / name, "ab") as fh:
            fh.write(data)

    return damage


def _directory(name: str) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        (run / name).unlink()
        (run / name).mkdir()

    return damage


def _delete(*names: str) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        for name in names:
            (run / name).unlink()

    return damage


def _swap(src: str, dst: str) -> Callable[[Path], None]:
    return lambda run: shutil.copy(run / src, run / dst)


def _ticks_done_text(doc: dict) -> dict:
    doc["modes"]["none"]["ticks_done"] = "x"
    return doc


_TWO_DRONES_FOR_THREE = {
    "mode": np.array("none"),
    "drone_ids": np.array([1, 2, 3]),
    "t": np.zeros(4),
    "g_w0": np.zeros((4, 4)),
    "g_wi": np.zeros((4, 2, 4)),
    "g_bar_w": np.zeros((4, 3, 4)),
}
_ROWS_HEADER_NOT_JSON = MAGIC + struct.pack("<I", 4) + b"{{{{"

# name: (damage, the file then named, fails): named in the RunDirError when `fails` ("": the run
# directory itself), else in the one skipped line
CASES: dict[str, tuple[Callable[[Path], None], str, bool]] = {
    "rows header naming 4 drones for 3": (_edit_rows_header(_one_more_drone), ROWS, True),
    "rows header length 2**32-1": (_header_length(2**32 - 1), ROWS, True),
    "rows header length past the file": (_header_length(10_000_000), ROWS, True),
    "rows header not JSON": (_garbage(ROWS, _ROWS_HEADER_NOT_JSON), ROWS, True),
    "rows column of Python objects": (_edit_rows_header(_column("t", dtype="|O")), ROWS, True),
    "rows column shape of another recording": (_edit_rows_header(_column("g_wi", shape=[2, 4])), ROWS, True),
    "rows header a JSON list": (_garbage(ROWS, MAGIC + struct.pack("<I", 2) + b"[]"), ROWS, True),
    "rows _seq damaged at row 20": (_seq_of_row(20, 7), ROWS, False),
    "rows cut short mid-row (a kill)": (_truncate(ROWS, 5), ROWS, False),
    "recording.json not JSON": (_garbage(STATE_FILE, b'{"state": "clo'), STATE_FILE, False),
    "recording.json modes a list": (
        _edit_json(STATE_FILE, lambda d: {**d, "modes": [1, 2]}),
        STATE_FILE,
        False,
    ),
    "recording.json ticks_done a text": (_edit_json(STATE_FILE, _ticks_done_text), STATE_FILE, False),
    "npz not a zip": (_garbage(NPZ, b"PK\x03\x04 not really a zip"), NPZ, True),
    "npz cut short": (_truncate(NPZ, 100), NPZ, True),
    "npz with a pickled object array": (
        _npz(NPZ, mode=np.array("none"), t=np.array([{}], dtype=object)),
        NPZ,
        True,
    ),
    "npz of 2 drones for 3 ids": (_npz(NPZ, **_TWO_DRONES_FOR_THREE), NPZ, True),
    "npz a zip of a text file": (_zip_of_text(NPZ), NPZ, True),
    "npz damaged beside its row stream": (_garbage(DGP_NPZ, b"PK junk"), DGP_NPZ, False),
    "every recording deleted": (_delete(NPZ, ROWS), "", True),
    "mission_resolved.yaml garbage": (_garbage(MISSION_FILE, b"\xff\xfe: [unclosed"), MISSION_FILE, True),
    "mission_resolved.yaml deleted": (_delete(MISSION_FILE), MISSION_FILE, True),
    "datasets.npz bad zip": (_truncate(DATASETS_FILE, 50), DATASETS_FILE, False),
    "datasets.npz of the wrong shape": (_npz(DATASETS_FILE, drone1__X=np.zeros(3)), DATASETS_FILE, False),
    "datasets.npz of 0-d arrays": (
        _npz(DATASETS_FILE, drone1__X=np.zeros(()), drone1__Y=np.zeros(()), drone1__ticks=np.zeros((), int)),
        DATASETS_FILE,
        False,
    ),
    "experts.npz holds datasets": (_swap(DATASETS_FILE, EXPERTS_FILE), EXPERTS_FILE, False),
    "metrics.json a JSON list": (_garbage(METRICS_FILE, b"[1, 2]"), METRICS_FILE, False),
    "events.jsonl not UTF-8 and not objects": (
        _append(EVENTS_FILE, b'\xff\xfe\n[1, 2]\n"text"\n{"t": 1,'),
        EVENTS_FILE,
        False,
    ),
    "events.jsonl a directory": (_directory(EVENTS_FILE), EVENTS_FILE, False),
}


def _copy(pristine: Path, into: Path) -> Path:
    run = into / "run"
    shutil.copytree(pristine, run)
    return run


def _check_outcome(run: Path, plots: bool = False) -> tuple[RunDirError | None, list[str]]:
    """rebuild_run on `run`: (None, skipped) when it rebuilt metrics.json, (the RunDirError, []) when it
    stopped; any other exception fails the test. Either way what it says names a file of `run`."""
    names = {p.name for p in run.iterdir()} | {p.name for p in Path(run).parent.iterdir()}
    try:
        metrics, _, skipped = rebuild_run(run, plots=plots)
    except RunDirError as exc:
        assert exc.path == run or exc.path.parent == run, exc
        assert "\n" not in str(exc) and str(exc).startswith(str(run))
        return exc, []
    assert json.loads((run / METRICS_FILE).read_text()) == json.loads(json.dumps(metrics))
    for line in skipped:
        assert "\n" not in line and line.split(":")[0] in names, line
    return None, skipped


@pytest.mark.parametrize("case", list(CASES))
def test_a_named_damage_is_skipped_or_stops_naming_the_file(
    pristine: Path, tmp_path: Path, case: str
) -> None:
    damage, named, fails = CASES[case]
    run = _copy(pristine, tmp_path)
    damage(run)
    exc, skipped = _check_outcome(run)
    if fails:
        assert exc is not None, skipped
        assert exc.path == run / named if named else exc.path == run
    else:
        assert exc is None, exc
        assert any(line.startswith(f"{named}: ") for line in skipped), skipped
        assert len(skipped) == 1, skipped


def test_a_kill_keeps_the_rows_before_the_damage(pristine: Path, tmp_path: Path) -> None:
    run = _copy(pristine, tmp_path)
    _seq_of_row(20, 7)(run)
    metrics, _, skipped = rebuild_run(run, plots=False)
    assert metrics["modes"]["dgp"]["ticks"] == 20 and metrics["modes"]["none"]["ticks"] == N_TICKS
    assert skipped == [f"{ROWS}: kept the first 20 rows; dropped 40 rows whose _seq is not their row number"]
    _truncate(ROWS, 5)(run := _copy(pristine, tmp_path / "cut"))
    metrics, _, skipped = rebuild_run(run, plots=False)
    assert metrics["modes"]["dgp"]["ticks"] == N_TICKS - 1
    assert skipped == [
        f"{ROWS}: kept the first {N_TICKS - 1} rows; dropped a partial row of {_itemsize(run) - 5} B"
    ]


def _row_dtype(doc: dict) -> np.dtype:
    """The numpy dtype of one row of a row stream with header `doc`."""
    return np.dtype([("_seq", "<i8")] + [(c["name"], c["dtype"], tuple(c["shape"])) for c in doc["columns"]])


def _itemsize(run: Path) -> int:
    return _row_dtype(_rows_header(run / ROWS)[0]).itemsize


def _flip(data: bytes, where: list[int], xor: int) -> bytes:
    b = bytearray(data)
    for w in where:
        if b:
            b[w % len(b)] ^= xor
    return bytes(b)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=6,
)


KINDS = [
    "truncate",
    "flip",
    "garbage",
    "empty",
    "delete",
    "directory",
    "json",
    "field",
    "rows header",
    "swap",
]
JSON_FIELDS = [
    *("state", "complete", "reason", "modes", "modes.none", "modes.none.drone_ids", "modes.none.ticks_done"),
    *(
        "modes.none.bus_dropped",
        "modes.none.wall_seconds",
        "modes.none.error",
        "modes.none.vision_rejections",
    ),
    *("gp", "wall_seconds", "interrupted", "error"),
]
"""Fields of recording.json and metrics.json a damage sets to another JSON value."""


@st.composite
def damages(draw: st.DrawFn) -> tuple[str, str, Callable[[Path], None]]:
    """(file, kind, damage) of one random damage to one file of the run directory."""
    names = sorted(NAMES)
    name = draw(st.sampled_from(names))
    kind = draw(st.sampled_from(KINDS))
    if kind == "truncate":
        frac = draw(st.floats(0.0, 1.0))
        return (
            name,
            kind,
            lambda run: (run / name).write_bytes(
                (run / name).read_bytes()[: int(frac * (run / name).stat().st_size)]
            ),
        )
    if kind == "flip":
        where, xor = draw(st.lists(st.integers(0, 2**31), min_size=1, max_size=8)), draw(st.integers(1, 255))
        return name, kind, lambda run: (run / name).write_bytes(_flip((run / name).read_bytes(), where, xor))
    if kind == "garbage":
        junk = draw(st.binary(max_size=300))
        return name, kind, lambda run: (run / name).write_bytes(junk)
    if kind == "empty":
        return name, kind, lambda run: (run / name).write_bytes(b"")
    if kind == "delete":
        return name, kind, lambda run: (run / name).unlink()
    if kind == "directory":
        return name, kind, lambda run: ((run / name).unlink(), (run / name).mkdir())
    if kind == "json":  # valid JSON of any shape instead of the file
        doc = draw(json_values)
        return name, kind, lambda run: (run / name).write_text(json.dumps(doc))
    if (
        kind == "field"
    ):  # one field of recording.json or metrics.json (or a rows header) set to any JSON value
        value = draw(json_values | st.sampled_from([2**32 - 1, -1, 2**63, 1e308, "x", [], {}]))
        target = draw(st.sampled_from(JSON_FIELDS))
        file = draw(st.sampled_from([STATE_FILE, METRICS_FILE]))

        def set_field(doc: dict) -> dict:
            *path, last = target.split(".")
            d = doc
            for key in path:
                d = d.setdefault(key, {}) if isinstance(d, dict) else {}
            if isinstance(d, dict):
                d[last] = value
            return doc

        return file, kind, _edit_json(file, set_field)
    if kind == "rows header":  # a header field of the row stream set to an extreme or wrong value
        what = draw(st.sampled_from(["length", "drones", "shape", "dtype", "name", "meta", "columns"]))
        if what == "length":
            n = draw(st.sampled_from([0, 1, 2**32 - 1, 2**31, 2**20 + 1]) | st.integers(0, 2**32 - 1))
            return ROWS, f"{kind} {what}", _header_length(n)
        value = draw(
            json_values | st.sampled_from([2**32 - 1, -1, "|O", "<U5", "V8", "f8,i4", "(2,)f8", "_seq"])
        )
        column = draw(st.sampled_from(["t", "g_wi", "visible", "n_fused"]))
        ids = draw(st.lists(st.integers(-5, 2**40), max_size=6))

        def edit(doc: dict) -> None:
            col = next(c for c in doc["columns"] if c["name"] == column)
            if what == "drones":
                doc["meta"]["drone_ids"] = ids
            elif what in ("shape", "dtype", "name"):
                col[what] = value
            else:
                doc[what] = value

        return ROWS, f"{kind} {what}", _edit_rows_header(edit)
    other = draw(
        st.sampled_from([n for n in names if n != name])
    )  # a file replaced by another file of the run (valid, wrong content)
    return name, kind, lambda run: shutil.copy(run / other, run / name)


@settings(max_examples=40, deadline=None)
@given(damage=damages())
def test_report_on_any_damaged_run_dir_rebuilds_or_names_the_file(
    pristine: Path, damage: tuple[str, str, Callable[[Path], None]]
) -> None:
    """One random damage to a copy of a small run directory: rebuild_run either rebuilds metrics.json
    (listing what it skipped, each line naming a file of the run) or raises RunDirError naming a file
    of the run; never any other exception. export_mcap reads it the same way."""
    name, kind, apply = damage
    with tempfile.TemporaryDirectory() as tmp:
        run = _copy(pristine, Path(tmp))
        apply(run)
        try:
            summary = export_mcap(run, Path(tmp) / "run.mcap")
        except RunDirError as exc:
            assert exc.path == run or exc.path.parent == run, exc
            event("export: RunDirError")
        else:
            assert summary.messages > 0 and all(line.split(":")[0] in NAMES for line in summary.skipped)
            event(f"export: {'skipped' if summary.skipped else 'clean'}")
        exc, skipped = _check_outcome(run)
        event(f"report: {'RunDirError' if exc else 'skipped' if skipped else 'clean'}")
        if exc is None and kind in ("garbage", "directory") and name not in (NPZ, ROWS, MISSION_FILE):
            assert any(line.startswith(f"{name}: ") for line in skipped) or (run / name).is_file(), skipped


def test_plots_of_a_row_stream_with_implausible_values(pristine: Path, tmp_path: Path) -> None:
    """Bytes damaged inside the rows (no checksum there) that make a value NaN, inf or absurd: the rows
    from there on are dropped and said so; the plots and a strict metrics.json are still written."""
    for k, value in enumerate((np.nan, np.inf, 1e308)):
        run = _copy(pristine, tmp_path / str(k))
        doc, rows = _rows_header(run / ROWS)
        a = np.frombuffer(rows, dtype=_row_dtype(doc), count=N_TICKS).copy()
        a["g_bar_w"][7 + k, 1, 2] = value
        _write_rows_header(run / ROWS, doc, a.tobytes())
        metrics, plots, skipped = rebuild_run(run, plots=k == 0)
        assert metrics["modes"]["dgp"]["ticks"] == 7 + k
        why = f"g_bar_w not finite or beyond 1e+06 at tick {7 + k}"
        assert skipped == [f"{ROWS}: kept the first {7 + k} rows; dropped the rest: {why}"]
        assert len(plots) == (4 if k == 0 else 0)


def test_cli_report_prints_what_it_skipped(
    pristine: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _copy(pristine, tmp_path)
    CASES["recording.json not JSON"][0](run)
    CASES["datasets.npz bad zip"][0](run)
    assert cli.main(["report", str(run), "--no-plots"]) == 0
    out, err = capsys.readouterr()
    assert err.splitlines() == [
        "warning: skipped: recording.json: not JSON "
        "(Unterminated string starting at: line 1 column 11 (char 10))",
        "warning: skipped: datasets.npz: not a readable npz (not a zip archive: File is not a zip file)",
    ]
    assert "recording INCOMPLETE: unknown: recording.json damaged" in out


@pytest.mark.parametrize(
    "case", ["rows header length 2**32-1", "npz not a zip", "recording.json modes a list"]
)
def test_export_reads_through_the_same_checks(pristine: Path, tmp_path: Path, case: str) -> None:
    damage, named, fails = CASES[case]
    run = _copy(pristine, tmp_path)
    damage(run)
    if fails:
        with pytest.raises(RunDirError) as err:
            export_mcap(run, tmp_path / "run.mcap")
        assert err.value.path == run / str(named) and not (tmp_path / "run.mcap").exists()
    else:
        s = export_mcap(run, tmp_path / "run.mcap")
        assert s.skipped == [f"{named}: modes: not an object"] and s.mode_ticks == {
            "none": N_TICKS,
            "dgp": N_TICKS,
        }


@pytest.mark.system
@pytest.mark.parametrize(
    "command", [["report"], ["export", "--mcap", "out.mcap"], ["view", "--save", "out.rrd"]]
)
def test_cli_on_a_damaged_run_exits_2_with_one_line(
    pristine: Path, tmp_path: Path, command: list[str]
) -> None:
    """The installed command on a row stream whose header length is 2**32-1: exit 2, one line on stderr
    naming the file, no traceback."""
    if command[0] == "view":
        pytest.importorskip("rerun")
    run = _copy(pristine, tmp_path)
    _header_length(2**32 - 1)(run)
    argv = [sys.executable, "-m", "flightstack", command[0], str(run), *command[1:]]
    proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    size = (run / ROWS).stat().st_size
    assert proc.stderr.splitlines() == [
        f"error: {run / ROWS}: header length 4294967295 B: more than the file ({size} B) or 1048576 B"
    ]
    assert "Traceback" not in proc.stdout + proc.stderr
