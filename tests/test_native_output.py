"""flightstack.drivers.native_output: what a native library writes on fd 1 during one call is taken and
handed back as lines, the descriptor is put back also when the call raises, and C stdio's buffer (full
buffering on a file) is flushed before it is; the motion-capture client's connect line gets a level."""

from __future__ import annotations

import ctypes
import os

import pytest

from flightstack.drivers.native_output import native_stdout


def _c_printf(text: bytes) -> None:
    """Write through C stdio without flushing (fd 1 is a file here: fully buffered)."""
    ctypes.CDLL(None).printf(b"%s", text)


def test_writes_on_fd_1_are_taken_and_handed_back(capfd: pytest.CaptureFixture[str]) -> None:
    with native_stdout() as lines:
        os.write(1, b"Using unicast from server 127.0.0.1:1511\n\n")
        _c_printf(b"buffered by C stdio\n")
    assert lines == ["Using unicast from server 127.0.0.1:1511", "buffered by C stdio"]
    os.write(1, b"after\n")
    out, _ = capfd.readouterr()
    assert out == "after\n"  # nothing of the block reached fd 1; fd 1 is back


def test_fd_1_is_put_back_when_the_block_raises(capfd: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(RuntimeError, match="connect failed"), native_stdout() as lines:
        os.write(1, b"said before failing\n")
        raise RuntimeError("connect failed")
    assert lines == ["said before failing"]
    os.write(1, b"after\n")
    assert capfd.readouterr().out == "after\n"


def test_a_second_capture_while_one_is_open_captures_nothing(capfd: pytest.CaptureFixture[str]) -> None:
    """Two captures swapping fd 1 could leave it on a closed file: the second one lets its output through."""
    with native_stdout() as outer:
        with native_stdout() as inner:
            os.write(1, b"during both\n")
        os.write(1, b"after the inner\n")
    assert inner == [] and outer == ["during both", "after the inner"]
    os.write(1, b"after\n")
    assert capfd.readouterr().out == "after\n"
