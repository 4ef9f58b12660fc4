"""What a native library writes to the process's standard output, taken for the length of one call and
handed back as lines, so that the console says who wrote it and at which level (docs/logs.md, "What a run
prints"). libmotioncapture's C++ writes "Using unicast from server …" with std::cout while it connects.

The capture is at file-descriptor level (fd 1 onto a temporary file, C stdio flushed before it is put
back): a Python `print` in another thread during the window is kept and handed back with the rest, not
lost. Keep the window short: it is one connect, bounded by its timeout. One capture at a time in the
process: a second one while the first is open captures nothing (its output goes to fd 1 as it would
without), since two threads swapping fd 1 could leave it on a closed file.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
import threading
from collections.abc import Iterator

STDOUT_FD = 1
_ONE_AT_A_TIME = threading.Lock()


def _flush_c_stdio() -> None:
    """fflush(NULL): every C stdio stream, so that what a library buffered reaches the fd it wrote to."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).fflush(None)


@contextlib.contextmanager
def native_stdout() -> Iterator[list[str]]:
    """Redirect fd 1 for the block; the list it yields holds the block's non-empty output lines on exit
    (also when the block raises). Without a usable fd 1 (closed, or not a real descriptor) it captures
    nothing and redirects nothing."""
    lines: list[str] = []
    if not _ONE_AT_A_TIME.acquire(blocking=False):
        yield lines
        return
    try:
        with _redirected(lines):
            yield lines
    finally:
        _ONE_AT_A_TIME.release()


@contextlib.contextmanager
def _redirected(lines: list[str]) -> Iterator[None]:
    """fd 1 onto a temporary file for the block; its lines appended to `lines` on exit."""
    try:
        sys.stdout.flush()
        saved = os.dup(STDOUT_FD)
    except (OSError, ValueError, AttributeError):
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), STDOUT_FD)
        try:
            yield
        finally:
            with contextlib.suppress(OSError, ValueError):
                sys.stdout.flush()
            _flush_c_stdio()
            os.dup2(saved, STDOUT_FD)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", errors="replace")
            lines.extend(line.rstrip() for line in text.splitlines() if line.strip())
