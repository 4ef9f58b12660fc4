"""flightstack.runtime.keep_awake: the sleep inhibitor is held exactly while flying and released after,
also when the block raises; a refused or missing inhibitor is reported, never fatal."""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import pytest

from flightstack.runtime import keep_awake as ka

FAKE = """#!/bin/sh
echo "$@" > "{log}"
echo $$ > "{pid}"
exec cat
"""


def fake_inhibitor(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, body: str = FAKE) -> tuple[Path, Path]:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log, pid = tmp_path / "args", tmp_path / "pid"
    exe = bin_dir / "systemd-inhibit"
    exe.write_text(body.format(log=log, pid=pid))
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(ka.sys, "platform", "linux")
    return log, pid


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    status = Path(f"/proc/{pid}/status")
    return not (status.exists() and "State:\tZ" in status.read_text())


def test_the_inhibitor_is_held_while_inside_and_released_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log, pid_file = fake_inhibitor(tmp_path, monkeypatch)
    with pytest.raises(RuntimeError), ka.keep_awake("test flight") as how:
        assert how.startswith("sleep inhibited (systemd-inhibit")
        t_end = time.monotonic() + 10.0  # a loaded machine may not have run the fake's first lines yet
        while not (pid_file.exists() and pid_file.read_text().strip()) and time.monotonic() < t_end:
            time.sleep(0.02)
        pid = int(pid_file.read_text())
        assert f"pid {pid})" in how and alive(pid)  # the fake execs `cat`: its pid is the one started
        args = log.read_text()
        assert "--what=sleep:idle:handle-lid-switch" in args and "--why=test flight" in args
        raise RuntimeError("the flight failed")
    t_end = time.monotonic() + 2.0
    while alive(pid) and time.monotonic() < t_end:
        time.sleep(0.02)
    assert not alive(pid)


def test_a_refusing_inhibitor_is_reported_and_the_block_still_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake_inhibitor(tmp_path, monkeypatch, "#!/bin/sh\necho 'Failed to connect to bus' >&2\nexit 1\n")
    ran = False
    with ka.keep_awake() as how:
        ran = True
    assert ran and how.startswith("sleep not inhibited: systemd-inhibit refused (Failed to connect to bus")


def test_no_inhibitor_at_all(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ka.shutil, "which", lambda name: None)
    with ka.keep_awake() as how:
        assert how.startswith("sleep not inhibited: no systemd-inhibit or caffeinate")
