"""Where a recording goes: a spawned viewer, a running viewer (gRPC), or an .rrd file.

`--viewer` (run/sim/fly/agent) takes `spawn`, `connect`, `connect:ADDR`, `save:FILE.rrd`, or nothing
(`auto`: spawn a viewer when there is a display and the `rerun` executable, else save into the run
directory); `flightstack view` takes `--spawn`, `--connect [ADDR]` or `--save FILE` the same way.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import sys
import urllib.parse
import uuid
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from rerun import RecordingStream

APPLICATION_ID = "flightstack"
DEFAULT_ADDR = "127.0.0.1:9876"
"""Where `connect` finds a viewer by default (the port `rerun` listens on)."""
AUTO = "auto"


@dataclass(frozen=True)
class Sink:
    """kind spawn (a new viewer process), connect (`target`: a viewer's gRPC URL) or save (`target`: an
    .rrd path)."""

    kind: Literal["spawn", "connect", "save"]
    target: str | None = None

    def describe(self) -> str:
        if self.kind == "spawn":
            return "a new Rerun viewer"
        if self.kind == "connect":
            return f"the Rerun viewer at {self.target}"
        return f"{self.target} (open it with: rerun {self.target})"


def display_available() -> bool:
    """A viewer window can open: macOS and Windows always, elsewhere when DISPLAY or WAYLAND_DISPLAY is
    set; and the `rerun` executable (installed with rerun-sdk) is on PATH."""
    if shutil.which("rerun") is None:
        return False
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def connect_url(addr: str | None) -> str:
    """A viewer's gRPC URL from HOST:PORT (or a full rerun+http:// URL, kept as given)."""
    addr = addr or DEFAULT_ADDR
    return addr if "://" in addr else f"rerun+http://{addr}/proxy"


def unreachable(sink: Sink, timeout_s: float = 2.0) -> str | None:
    """Why a `connect` sink cannot be reached (nothing accepts a TCP connection at its host and port
    within timeout_s), said before anything is logged; None when it can, or for other sinks."""
    if sink.kind != "connect" or sink.target is None:
        return None
    parts = urllib.parse.urlsplit(sink.target.replace("rerun+", "", 1))
    host, port = parts.hostname or "127.0.0.1", parts.port or 9876
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return None
    except OSError as exc:
        return f"no Rerun viewer answers at {host}:{port} ({exc.strerror or exc}); start one with `rerun`"


def viewer_spec(text: str) -> str:
    """argparse type of --viewer: spawn | connect | connect:ADDR | save:FILE.rrd (auto when empty) for
    Rerun, foxglove | foxglove:PORT for Foxglove's live WebSocket view (viewer/foxglove_live.py)."""
    text = text.strip()
    if text in ("", AUTO, "spawn", "connect", "foxglove") or text.startswith("connect:"):
        return text or AUTO
    if text.startswith("foxglove:"):
        port = text.partition(":")[2].strip()
        if port.isdigit() and 0 < int(port) < 65536:
            return text
        raise argparse.ArgumentTypeError(f"{text!r}: foxglove:PORT needs a port in 1..65535")
    if text.startswith("save:") and text[5:].strip():
        return text
    raise argparse.ArgumentTypeError(
        f"{text!r}: use spawn, connect[:HOST:PORT], save:FILE.rrd (Rerun) or foxglove[:PORT] (Foxglove)"
    )


def resolve(spec: str, default_file: Path) -> Sink:
    """The Sink of a --viewer value; `auto` spawns when display_available(), else saves `default_file`."""
    if spec == AUTO:
        return Sink("spawn") if display_available() else Sink("save", str(default_file))
    if spec == "spawn":
        return Sink("spawn")
    if spec == "connect" or spec.startswith("connect:"):
        return Sink("connect", connect_url(spec.partition(":")[2] or None))
    return Sink("save", spec.partition(":")[2].strip())


def open_stream(rr: ModuleType, sink: Sink, name: str, blueprint: Any = None) -> RecordingStream:
    """A new recording (its own id), named `name`, sent to `sink` (with the default `blueprint`); only
    the `mission_time` timeline (no log_time). OSError when the file cannot be created or no viewer
    answers at a `connect` address."""
    problem = unreachable(sink)
    if problem is not None:
        raise ConnectionRefusedError(problem)
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
    stream.set_log_time_enabled(False)
    stream.set_log_tick_enabled(False)
    if sink.kind == "save":
        assert sink.target is not None
        path = Path(sink.target)
        path.parent.mkdir(parents=True, exist_ok=True)
        stream.save(path, default_blueprint=blueprint)
    elif sink.kind == "connect":
        stream.connect_grpc(sink.target, default_blueprint=blueprint)
    else:
        stream.spawn(default_blueprint=blueprint, hide_welcome_screen=True)
    stream.send_recording_name(name)
    return stream


def close_stream(stream: RecordingStream, timeout_s: float = 5.0) -> None:
    """Flush (bounded) and close the sinks: an .rrd file gets its footer and is complete. RuntimeError
    when not everything was sent within timeout_s (a viewer that went away)."""
    try:
        stream.flush(timeout_sec=timeout_s)
    finally:
        stream.disconnect()
