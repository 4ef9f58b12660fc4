"""Fingerprints of the results (flightstack.recording.fingerprint, tests/fingerprints.py): the short runs of
every deterministic rig and mode still give the recordings of tests/data/fingerprints.json, and the
fingerprint is of what the flight did, not of the computer that flew it."""

from __future__ import annotations

import copy
import hashlib
import json
import struct
import warnings

import numpy as np
import pytest

from flightstack.recording.fingerprint import (
    EVENTS,
    META,
    array_fingerprint,
    array_summary,
    fingerprints,
    summaries,
)
from flightstack.recording.timeseries import ARRAY_FIELDS, MACHINE_FIELDS, Recording
from tests.fingerprints import COMMAND, RUNS, STORED, compute, differences, report


def _recording(n_ticks: int = 6, done: int = 5, seed: int = 0) -> Recording:
    """A recording of two drones with random values in every array and a few events."""
    rng = np.random.default_rng(seed)
    rec = Recording.empty("dgp", [1, 2], n_ticks)
    for f in ARRAY_FIELDS:
        a = getattr(rec, f)
        if a.dtype.kind == "f":
            a[...] = rng.normal(size=a.shape)
        elif a.dtype.kind == "b":
            a[...] = rng.random(a.shape) < 0.5
        else:
            a[...] = rng.integers(0, 3, a.shape)
    rec.ticks_done = done
    rec.wall_seconds = 1.25
    rec.vision_rejections = {"2": {"marker 'red': 0 blobs": 3}}
    rec.events = [
        {"t": 0.0, "event": "safety", "kind": "takeoff", "drone": 1, "mode": "dgp", "detail": "battery 90 %"},
        {
            "t": 0.01,
            "event": "safety tick",
            "mode": "dgp",
            "ticks": 5,
            "p50_ms": 0.2,
            "p99_ms": 0.4,
            "max_ms": 0.5,
        },
    ]
    return rec


def test_array_fingerprint_is_sha256_of_the_header_and_little_endian_values() -> None:
    a = np.arange(6, dtype=np.float64).reshape(2, 3) / 7
    expected = hashlib.sha256(b"<f8 (2, 3)\n" + struct.pack("<6d", *(i / 7 for i in range(6)))).hexdigest()
    assert array_fingerprint(a) == expected
    flags = np.array([True, False, True])
    assert array_fingerprint(flags) == hashlib.sha256(b"|b1 (3,)\n\x01\x00\x01").hexdigest()
    # the same values in another layout or byte order: the same fingerprint
    assert array_fingerprint(np.asfortranarray(a)) == expected
    assert array_fingerprint(a.astype(">f8")) == expected
    assert array_fingerprint(a.T.copy().T) == expected


def test_array_fingerprint_changes_with_any_value_shape_or_dtype() -> None:
    a = np.linspace(-1.0, 1.0, 12)
    base = array_fingerprint(a)
    b = a.copy()
    b[7] = np.nextafter(b[7], 2.0)  # one ulp
    assert array_fingerprint(b) != base
    assert array_fingerprint(a.reshape(3, 4)) != base
    assert array_fingerprint(a.astype(np.float32).astype(np.float64)) != base  # other values
    assert array_fingerprint(np.arange(12)) != array_fingerprint(np.arange(12, dtype=np.int32))


def test_array_fingerprint_is_of_values_not_of_nan_payloads_or_the_sign_of_zero() -> None:
    a = np.array([1.0, np.nan, 0.0])
    other_nan = np.frombuffer(struct.pack("<d", 1.0) + bytes.fromhex("010000000000f8ff") + bytes(8), "<f8")
    assert np.isnan(other_nan[1]) and other_nan.tobytes() != a.tobytes()
    assert array_fingerprint(other_nan) == array_fingerprint(a)
    assert array_fingerprint(np.array([1.0, np.nan, -0.0])) == array_fingerprint(a)


def test_array_summary() -> None:
    s = array_summary(np.array([[3.0, np.nan], [4.0, 1e-30]]))
    assert s == {"shape": [2, 2], "dtype": "float64", "norm": 5.0, "nonfinite": 1}
    assert array_summary(np.array([1.0, 2.0, 2.0]) / 3 * np.pi)["norm"] == 3.14159  # 6 significant digits
    assert array_summary(np.array([True, True, False, True]))["norm"] == pytest.approx(3**0.5, rel=1e-6)


def test_every_array_but_the_machines_is_fingerprinted_over_the_ticks_done() -> None:
    rec = _recording()
    fp = fingerprints(rec)
    assert set(fp) == {*ARRAY_FIELDS, EVENTS, META} - set(MACHINE_FIELDS)
    assert set(summaries(rec)) == set(fp)
    assert fp["g_wi"] == array_fingerprint(rec.g_wi[:5])
    rec.g_wi[5] += 1.0  # a tick not flown
    assert fingerprints(rec) == fp


def test_what_measures_the_computer_does_not_change_the_fingerprints() -> None:
    rec = _recording()
    fp = fingerprints(rec)
    for f in MACHINE_FIELDS:
        getattr(rec, f)[:] += 0.125
    rec.wall_seconds = 99.0
    rec.events[1].update(p50_ms=3.0, p99_ms=4.0, max_ms=5.0)
    assert fingerprints(rec) == fp


def test_the_order_in_which_events_were_written_does_not_count() -> None:
    """events.jsonl gets the safety log's events when its writer thread polls it (wall time)."""
    rec = _recording()
    rec.events.append({"t": 0.005, "event": "neighbours", "drone": 2, "added": [1], "mode": "dgp"})
    rec.events.append({"t": None, "event": "recording_stopped", "reason": "disk full", "wall_t": 1.7e9})
    fp = fingerprints(rec)[EVENTS]
    rec.events.reverse()
    rec.events[0]["wall_t"] = 1.8e9
    assert fingerprints(rec)[EVENTS] == fp


@pytest.mark.parametrize(
    ("change", "changed"),
    [
        (lambda r: r.g_wi.__setitem__((2, 1, 3), np.nextafter(r.g_wi[2, 1, 3], 9.0)), "g_wi"),
        (lambda r: r.frame_age.__setitem__((0, 0), r.frame_age[0, 0] + 0.05), "frame_age"),
        (lambda r: r.visible.__setitem__((4, 0), ~r.visible[4, 0]), "visible"),
        (lambda r: r.events[0].__setitem__("t", 0.05), EVENTS),
        (lambda r: r.events[1].__setitem__("ticks", 6), EVENTS),
        (lambda r: r.events.pop(), EVENTS),
        (lambda r: r.vision_rejections["2"].__setitem__("marker 'red': 0 blobs", 4), META),
        (lambda r: setattr(r, "interrupted", True), META),
    ],
)
def test_a_change_of_the_flight_changes_its_fingerprint_and_only_that(change, changed: str) -> None:
    rec = _recording()
    fp = fingerprints(rec)
    change(rec)
    new = fingerprints(rec)
    assert [k for k in fp if fp[k] != new[k]] == [changed]


def _doc(norm: float = 2.5, sha: str = "a" * 64, env: str = "numpy 2.4.6") -> dict:
    entry = {"sha256": sha, "shape": [10, 2, 4], "dtype": "float64", "norm": norm, "nonfinite": 0}
    modes = {"none": {"g_wi": entry, "e_c": dict(entry, norm=1e-13)}}
    return {"format": 1, "environment": {"numpy": env}, "runs": {"ideal/paper_sim": {"modes": modes}}}


def test_differences_are_exact_in_the_same_environment() -> None:
    stored = _doc()
    assert differences(stored, copy.deepcopy(stored)) == ([], True)
    new = _doc(sha="b" * 64)  # last bits only: the same summaries
    lines, exact = differences(stored, new)
    assert exact and len(lines) == 2 and lines[0].startswith("ideal/paper_sim none g_wi (same summary")
    text = report(lines, exact, stored["environment"], new["environment"])
    assert "ideal/paper_sim none e_c" in text and COMMAND in text and "commit of its own" in text


def test_differences_in_another_environment_compare_the_summaries() -> None:
    stored = _doc()
    noise = _doc(norm=2.5 * (1 + 2e-4), sha="b" * 64, env="numpy 2.5.0")
    noise["runs"]["ideal/paper_sim"]["modes"]["none"]["e_c"]["norm"] = 1.3e-13
    assert differences(stored, noise) == ([], False)
    changed = _doc(norm=2.51, sha="b" * 64, env="numpy 2.5.0")
    lines, exact = differences(stored, changed)
    assert not exact and len(lines) == 1 and "g_wi" in lines[0] and "2.51" in lines[0]
    assert "numpy" in report(lines, exact, stored["environment"], changed["environment"])
    gone = _doc(env="numpy 2.5.0")
    del gone["runs"]["ideal/paper_sim"]["modes"]["none"]["e_c"]
    assert differences(stored, gone)[0] == [
        'ideal/paper_sim none e_c:\n    stored {"dtype": "float64", "nonfinite": 0, "norm": 1e-13, '
        '"shape": [10, 2, 4]}\n    now    absent'
    ]


def test_the_stored_file_covers_every_run_and_mode() -> None:
    stored = json.loads(STORED.read_text())
    assert stored["command"] == COMMAND
    assert {r.key: list(r.modes) for r in RUNS} == {k: list(v["modes"]) for k, v in stored["runs"].items()}
    for run in stored["runs"].values():
        for entries in run["modes"].values():
            assert set(entries) == {*ARRAY_FIELDS, EVENTS, META} - set(MACHINE_FIELDS)


def test_the_short_runs_give_the_stored_recordings() -> None:
    """Every rig, experiment and mode of RUNS, flown as `flightstack run` flies them (in a child process
    with the pinned numeric environment), against tests/data/fingerprints.json."""
    stored = json.loads(STORED.read_text())
    new = compute()
    lines, exact = differences(stored, new)
    if lines:
        pytest.fail(report(lines, exact, stored["environment"], new["environment"]), pytrace=False)
    if not exact:
        warnings.warn(
            f"fingerprints compared by their summaries only: this environment is not that of {STORED.name} "
            f"({new['environment']} vs {stored['environment']})",
            stacklevel=1,
        )
