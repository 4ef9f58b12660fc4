"""A torn MCAP made whole (flightstack.recording.mcap_finalise): a file cut anywhere after its first chunk
opens in the `mcap` package's seeking reader once finalised, with every message a stream read of the torn
file recovers, their times and bytes unchanged; the torn original is kept; a whole file is left alone."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from flightstack.cli import app as cli
from flightstack.recording.files import LIVE_MCAP_FILE
from flightstack.recording.mcap_finalise import finalise_torn, opens
from flightstack.recording.mcap_writer import RunMcap
from flightstack.recording.timeseries import ARRAY_FIELDS
from tests.conftest import random_recording
from tests.mcap_read import read_mcap, read_mcap_stream


def _raw(topics: dict[str, list[tuple[int, Any]]]) -> dict[str, list[tuple[int, bytes]]]:
    """Each topic's (log time, message bytes), sorted (NaN != NaN in decoded messages)."""
    return {t: sorted((w, m.SerializeToString()) for w, m in ms) for t, ms in topics.items()}


@pytest.fixture
def whole(tmp_path: Path) -> Path:
    """An MCAP of 600 ticks of three drones in chunks of about 16 kB, closed."""
    rec = random_recording("none", [1, 2, 3], 600, seed=3)
    path = tmp_path / "whole.mcap"
    mcap = RunMcap(path, chunk_bytes=1 << 14)
    for k in range(0, 600, 50):
        mcap.ticks("none", rec.drone_ids, {f: getattr(rec, f)[k : k + 50] for f in ARRAY_FIELDS})
        mcap.events("none", [{"event": "mark", "t": float(rec.t[k])}])
    mcap.attach("note.txt", "text/plain", b"kept")
    mcap.close()
    return path


@pytest.mark.parametrize("cut", [0.3, 0.6, 0.95])
def test_a_torn_file_is_finalised_with_every_message_a_stream_read_recovers(
    whole: Path, tmp_path: Path, cut: float
) -> None:
    data = whole.read_bytes()
    path, torn = tmp_path / "recording.mcap", tmp_path / "recording.mcap.torn"
    path.write_bytes(data[: int(len(data) * cut)])
    streamed = read_mcap_stream(path)
    assert streamed.error is not None and streamed.messages > 0 and not opens(path)
    done = finalise_torn(path, torn)
    assert done is not None and done.messages == streamed.messages
    got = read_mcap(path)  # the seeking reader
    assert _raw(got.topics) == _raw(streamed.topics)
    assert torn.read_bytes() == data[: int(len(data) * cut)] and done.torn_bytes == torn.stat().st_size
    assert finalise_torn(path, torn) is None  # whole now: left alone
    assert not list(tmp_path.glob(".*finalising*"))


def test_a_whole_file_is_left_alone_and_a_non_mcap_refused(whole: Path, tmp_path: Path) -> None:
    before = whole.read_bytes()
    assert opens(whole) and finalise_torn(whole, tmp_path / "x.torn") is None
    assert whole.read_bytes() == before and not (tmp_path / "x.torn").exists()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(np.arange(100, dtype=np.uint8).tobytes())
    with pytest.raises(ValueError, match="header"):
        finalise_torn(junk, tmp_path / "junk.torn")
    assert junk.read_bytes() == np.arange(100, dtype=np.uint8).tobytes()
    assert not list(tmp_path.glob(".*finalising*")) and not (tmp_path / "junk.torn").exists()


def test_report_warns_when_the_live_mcap_cannot_be_finalised(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not even a header: `report` leaves the file as it is and says so in one `warning: skipped:` line;
    the metrics are rebuilt (exit 0)."""
    out = tmp_path / "run"
    argv = ["run", "paper_sim", "--modes", "none", "--duration", "0.1", "--no-progress", "--no-live-mcap"]
    assert cli.main([*argv, "--out", str(out)]) == 0
    (out / LIVE_MCAP_FILE).write_bytes(b"not an mcap file")
    capsys.readouterr()
    assert cli.main(["report", str(out), "--no-plots"]) == 0
    err = capsys.readouterr().err
    assert f"warning: skipped: {LIVE_MCAP_FILE}: torn, and not finalised: not an MCAP file" in err, err
    assert (out / LIVE_MCAP_FILE).read_bytes() == b"not an mcap file"
