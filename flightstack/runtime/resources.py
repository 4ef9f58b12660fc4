"""What a run will take of the computer, checked before anything is allocated or flies.

The recording of every mode lives in memory while the run flies: `run_mode` allocates one
`Recording.empty` per mode and the flight (runtime.flight) keeps every mode's for the metrics. Its size is
`recording_nbytes` (flightstack.recording.timeseries: computed from the layout that allocates it) times the
modes flown (Mission.flown_modes). It must fit in MEMORY_FRACTION of the memory the computer has available
(MemAvailable of /proc/meminfo, read when checked): the rest is for what a run allocates besides the
recording (fill_true_errors and the metrics make temporaries of up to about one recording's size, the GP
training, Python, numba). Each mode's recording must also be one whose final compressed npz the
recorder can write within its close timeout (MAX_MODE_RECORDING_BYTES): a larger one flies, then ends
"recording incomplete" after the landing. `flightstack validate` checks both on the computer that
validates, `run` again before anything takes off; a mission that does not fit raises MissionError
(exit 2) naming the numbers and the keys to change.
"""

from __future__ import annotations

from pathlib import Path

from flightstack.config.mission import Mission, MissionError
from flightstack.recording.files import CLOSE_TIMEOUT_S
from flightstack.recording.timeseries import recording_nbytes

MEMORY_FRACTION = 0.5
"""The recordings may take at most this fraction of the available memory."""
MEMINFO = Path("/proc/meminfo")
NPZ_WRITE_BYTES_PER_S = 12.5e6
"""Bytes of in-memory recording per second that the final npz is assumed to be written at: a quarter of
the 50 MB/s measured on the 2-core CI machine when the npz was still deflated (paper_sim, 20 MB in 0.40 s;
stored, it writes faster), for a loaded computer and a slower disk."""
MAX_MODE_RECORDING_BYTES = int(CLOSE_TIMEOUT_S * NPZ_WRITE_BYTES_PER_S)
"""At most this many bytes of recording per mode (750 MB: scaling_31, the largest shipped, is 195 MB)."""


def available_memory_bytes(meminfo: Path = MEMINFO) -> int | None:
    """MemAvailable of `meminfo` in bytes (the kernel's estimate of what can be allocated without
    swapping); None where the file or the line is missing (not Linux): then nothing is checked."""
    try:
        text = meminfo.read_text(encoding="ascii", errors="replace")
    except OSError:
        return None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key == "MemAvailable":
            parts = value.split()
            if parts and parts[0].isdigit():
                return int(parts[0]) * (1024 if parts[1:] == ["kB"] else 1)
    return None


def recording_memory_bytes(mission: Mission) -> int:
    """Bytes of the in-memory recordings of every mode `mission` flies (all kept until the metrics)."""
    n_ticks = mission.n_ticks
    return len(mission.flown_modes()) * recording_nbytes(len(mission.drones), n_ticks)


def _gib(x: float) -> str:
    return f"{x / 2**30:.3g} GiB"


def check_recording_fits(mission: Mission, available_bytes: int | None = None) -> None:
    """Raise MissionError when one mode's recording exceeds MAX_MODE_RECORDING_BYTES, or the recordings
    need more than MEMORY_FRACTION of the available memory.

    available_bytes: the memory to check against (default: MemAvailable of this computer, read now; when
    the system does not say, the memory is not checked)."""
    n_ticks = mission.n_ticks
    per_mode = recording_nbytes(len(mission.drones), n_ticks)
    if per_mode > MAX_MODE_RECORDING_BYTES:
        raise MissionError(
            f"{mission.name}: duration_s / dt_s: one mode's recording would be {per_mode / 1e6:.0f} MB "
            f"({n_ticks} ticks × {len(mission.drones)} drone(s)), more than the "
            f"{MAX_MODE_RECORDING_BYTES / 1e6:.0f} MB the recorder can write within its "
            f"{CLOSE_TIMEOUT_S:g} s close timeout; shorten duration_s, raise dt_s, or fly fewer drones"
        )
    avail = available_memory_bytes() if available_bytes is None else available_bytes
    if avail is None:
        return
    need = recording_memory_bytes(mission)
    if need <= MEMORY_FRACTION * avail:
        return
    modes = mission.flown_modes()
    raise MissionError(
        f"{mission.name}: duration_s / dt_s: the recording needs {_gib(need)} of memory ({len(modes)} "
        f"mode(s) {', '.join(modes)} × {n_ticks} ticks × {len(mission.drones)} drone(s), "
        f"{recording_nbytes(len(mission.drones), 1)} bytes per tick), more than {MEMORY_FRACTION:.0%} of the "
        f"{_gib(avail)} this computer has available; shorten duration_s, raise dt_s, or fly fewer "
        "compare_modes or drones"
    )


__all__ = [
    "MAX_MODE_RECORDING_BYTES",
    "MEMORY_FRACTION",
    "available_memory_bytes",
    "check_recording_fits",
    "recording_memory_bytes",
]
