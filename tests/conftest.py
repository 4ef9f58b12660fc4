"""Shared test helpers."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from flightstack.paper.geometry import Pose
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording

# Property tests are deterministic in CI and locally: the same examples every run (derandomize), no
# wall-clock deadline (a 2-core CI machine under load must not turn a slow example into a failure).
settings.register_profile(
    "flightstack", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("flightstack")

REPO = Path(__file__).resolve().parents[1]
PEERS = REPO.parent / "shared" / "data" / "peers"
"""Real device recordings, read in place (../shared/data/peers/ beside the checkout; never copied in)."""

# Test tiers (pyproject.toml registers the markers; docs/getting-started.md). `pytest -m unit` is the fast
# tier for development (pure functions, in-process simulations, no emulators, no child processes but the one
# that flies the fingerprinted runs in a pinned numeric environment, test_fingerprints); `system` runs the
# loopback emulators, agent processes, the fault tables and the CLI end to end. CI runs both. A module is
# `system` when it is listed here; a single slow test elsewhere carries @pytest.mark.system itself.
SYSTEM_MODULES = frozenset(
    {
        "test_abort",
        "test_agent_processes",
        "test_attacker",
        "test_cli_sim",
        "test_decoders_property",  # hypothesis fuzzing of every decoder (~25 s)
        "test_emulated_camera",
        "test_ci_venv",
        "test_clock_offset",
        "test_closed_loop_square",
        "test_driver_threads",
        "test_emulated_lab",
        "test_faults",
        "test_faults_lab",
        "test_faults_lab_kills",
        "test_guard",
        "test_guardian",
        "test_hardware_mission",
        "test_keep_awake",
        "test_key_ownership",
        "test_lab_sim",
        "test_mocap",
        "test_natnet_emulator",
        "test_recorder",
        "test_rigs",
        "test_safety_background",
        "test_scamper",
        "test_secured_bus",
        "test_sim_pursuit",
        "test_tello_access_point",
        "test_tello_driver",
        "test_tello_emulator",
        "test_tello_interfaces",
        "test_tello_radio",
        "test_zenoh_bus",
        "test_zenoh_runner",
    }
)


# The system tier runs in two parts (.ci/run; docs/getting-started.md): its `timing` tests (is_timing, below)
# one at a time, the rest on four workers (`-n 4 --dist loadgroup`, pytest-xdist), where most of the time
# is spent waiting on real-time flights, not computing. The groups below matter on workers. The modules
# that drive the device emulators and drivers directly (some at the real Tello's fixed ports, in their own
# network namespaces or on addresses a module owns) run one after the other in one group, as without
# xdist; every other module (simulations, Zenoh agents on picked ports, sweeps, fuzzing) is a group of its
# own, so that a module-scoped fixture runs once. A module split between the two parts has no
# module-scoped fixture that its worker tests share with its timing tests (test_tello_replay's autouse
# summary only prints), so nothing runs twice.
# A new module that binds a fixed port or address joins DEVICE_MODULES.
DEVICE_MODULES = frozenset(
    {
        "test_driver_threads",
        "test_emulated_links",
        "test_guard",
        "test_guardian",
        "test_hardware_mission",
        "test_identify",
        "test_keep_awake",
        "test_mocap",
        "test_natnet_emulator",
        "test_tello_access_point",
        "test_tello_driver",
        "test_tello_emulator",
        "test_tello_radio",
    }
)


FAULT_FLIGHT_MODULES = frozenset({"test_faults_lab", "test_faults_lab_kills"})
"""The fault tables flown on the emulated lab: one group, so that their flights (each a flight process, its
guardian and the emulators) never run beside each other and load the other timing tests twice over."""

FIRST_GROUPS = (
    "loopback-devices",
    "test_emulated_lab",
    "test_tello_replay",
    "test_scamper_failsafe",
    "test_ci_venv",
    "test_duplicate_identity",
    "test_attacker",
    "test_latency_flight_emulated",
)
"""The groups handed out first to the worker tier's four workers (.ci/run), longest first as measured on
2026-12-06 on 2 idle cores with three workers (about 215, 80, 75, 60, 8, 60, 45 and 40 s). xdist's
loadgroup gives each worker one group in this order, then a second at once: the device group, the
longest, is paired with the shortest; the rest follow in collection order as workers free up."""


CPU_TIMED_TESTS = frozenset(
    {
        # the measured video latency holds the decode pipeline's own delay (0.43-0.45 s beside three worker
        # groups, bound 0.42 s)
        "tests/test_latency_flight_emulated.py::test_the_command_writes_a_links_file_the_rig_includes",
        # what a kill loses holds the niced follower's backlog (12-14 s beside three worker groups)
        "tests/test_mcap_live.py::test_a_killed_follower_loses_at_most_its_open_chunk",
        # four processes a run, whose lock-step decides what is fused
        "tests/test_duplicate_identity.py::test_a_key_holder_one_message_ahead_is_fused_once_and_quarantined",
        # the emulator's 10 Hz state must reach the driver through 8 rc steps: starved beside three worker
        # groups it fell silent for 0.88 s (link_lost) and a step saw no motion
        "tests/test_identify.py::test_identify_against_the_emulator",
        # a real-time lap whose control loop must find a fresh motion-capture sample every tick: starved
        # beside three worker groups it found 8 stale (at most 2 allowed)
        "tests/test_closed_loop_square.py::test_closed_loop_square_lap",
    }
)
"""Tests that bound no safety reaction but whose outcome depends on the CPU time they get: `timing` too
(each failed on the worker tier in fresh-clone CI runs of 2026-12-06, beside three other groups)."""


def is_timing(item: pytest.Item) -> bool:
    """A test that bounds a safety reaction's wall-clock time (it requests `safety_bound`), a row of a
    fault table flown on the emulated lab (its module fixture flies every row once, so the whole module
    goes together), or one of CPU_TIMED_TESTS: .ci/run runs these one at a time, at a raised CPU priority,
    nothing else of the suite CPU-heavy beside them. Every other test, in whatever module, runs on the
    workers."""
    return (
        SAFETY_BOUND_FIXTURE in getattr(item, "fixturenames", ())
        or item.path.stem in FAULT_FLIGHT_MODULES
        or item.nodeid.split("[")[0] in CPU_TIMED_TESTS
    )


def _xdist_group(item: pytest.Item) -> str:
    if item.path.stem in FAULT_FLIGHT_MODULES:
        return "emulated-lab-faults"
    return "loopback-devices" if item.path.stem in DEVICE_MODULES else item.path.stem


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config.option, "loadscopereorder"):  # xdist: keep FIRST_GROUPS' order (not by test count)
        config.option.loadscopereorder = False


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups and before `-m` deselects
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test is in exactly one tier: `system` (listed module or explicit marker) or `unit`; a module's
    tests share one xdist group, and the device modules' tests all share one. A test that bounds a
    reaction's time, or a fault table's row, is also `timing` (is_timing), and a fault table's row also
    `fault_table`: .ci/run runs those one at a time, apart from the worker tests, the fault tables last
    with nothing beside them."""
    for item in items:
        if is_timing(item):
            item.add_marker(pytest.mark.timing)
        if item.path.stem in FAULT_FLIGHT_MODULES:
            item.add_marker(pytest.mark.fault_table)
        if item.path.stem in SYSTEM_MODULES or item.get_closest_marker("system") is not None:
            item.add_marker(pytest.mark.system)
        else:
            item.add_marker(pytest.mark.unit)
        # one worker per module (its module-scoped fixtures, such as a fault table, run once), and one for
        # all the device modules together
        item.add_marker(pytest.mark.xdist_group(_xdist_group(item)))
    first = {g: k for k, g in enumerate(FIRST_GROUPS)}
    items.sort(key=lambda item: first.get(_xdist_group(item), len(first)))  # stable: modules keep their order


# Safety reactions bounded in time (a hover, a landing, a tick that must not block): the bound is the one
# that matters for safety, never loosened for a slow machine, and every measured value is printed in the
# session's summary (`safety reaction bounds`), so CI's log shows the margin. Anything else asserts
# behaviour, not speed; speed lives in benchmarks/ and in the fault table's measured columns.
Bound = Callable[..., None]
"""The type of the `safety_bound` fixture."""
SAFETY_BOUND_FIXTURE = "safety_bound"
"""The fixture's name (a test that requests it is a timing test)."""
SAFETY_BOUND = "safety_bound"
"""The user_properties key of a recorded bound: (what, measured, bound, unit)."""


@pytest.fixture
def safety_bound(request: pytest.FixtureRequest) -> Bound:
    """`safety_bound(what, measured, bound, unit="ms")`: assert `measured <= bound` for a safety reaction
    and record both in the test's report (printed in the session's summary)."""

    def check(what: str, measured: float, bound: float, unit: str = "ms") -> None:
        request.node.user_properties.append((SAFETY_BOUND, (what, float(measured), float(bound), unit)))
        assert measured <= bound, f"{what}: {measured:.1f} {unit}, above its safety bound of {bound:g} {unit}"

    return check


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    rows = [
        (report.nodeid, *value)
        for reports in terminalreporter.stats.values()
        for report in reports
        if getattr(report, "when", None) == "call"
        for key, value in getattr(report, "user_properties", ())
        if key == SAFETY_BOUND
    ]
    if not rows:
        return
    terminalreporter.section("safety reaction bounds (measured / bound)")
    for test, what, measured, bound, unit in sorted(rows, key=lambda r: -r[2] / max(r[3], 1e-9)):
        share = f"{100 * measured / bound:3.0f} %" if bound > 0 else ""
        terminalreporter.write_line(f"{measured:9.1f} / {bound:7g} {unit:2s} {share:>5s}  {what}  [{test}]")


MISSIONS = REPO / "mission_configs"


def completion_env(line: str, out: Path) -> dict[str, str]:
    """This environment plus argcomplete's request to complete `line` (cursor at its end), answered into
    the file `out` instead of file descriptor 8."""
    env = {
        **os.environ,
        "_ARGCOMPLETE": "1",
        "COMP_LINE": line,
        "COMP_POINT": str(len(line)),
        "_ARGCOMPLETE_IFS": "\n",
        "_ARGCOMPLETE_STDOUT_FILENAME": str(out),
    }
    env.pop("_ARGCOMPLETE_SHELL", None)
    return env


def skip_or_fail_in_ci(reason: str) -> NoReturn:
    """Skip the test for a missing optional input (a package, a recording in ../shared) with `reason`
    saying how to provide it; under CI=true, where CI provides every input, fail instead, so that CI never
    passes by skipping."""
    if os.environ.get("CI") == "true":
        pytest.fail(f"{reason} (CI=true: CI must provide it)", pytrace=False)
    pytest.skip(reason, allow_module_level=True)


finite = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-3.14159, 3.14159, allow_nan=False, allow_infinity=False)


@st.composite
def poses(draw: st.DrawFn) -> Pose:
    return Pose.make([draw(finite), draw(finite), draw(finite)], draw(angles))


@st.composite
def twists(draw: st.DrawFn) -> np.ndarray:
    return np.array([draw(finite), draw(finite), draw(finite), draw(st.floats(-3.0, 3.0))])


def run_cli(*args: str, timeout: float = 400) -> subprocess.CompletedProcess:
    """Run `flightstack ARGS` in a subprocess from the repository root (bounded by `timeout` s)."""
    return subprocess.run(
        [sys.executable, "-m", "flightstack", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )


def interrupt_cli_sim(
    mission: Path, out: Path, run_seconds: float = 1.0, sigint_ignored: bool = False
) -> tuple[int, str, str]:
    """Start `flightstack sim MISSION --duration 600`, wait for its first progress bar, let it fly
    `run_seconds`, send SIGINT; returns (exit code, stderr, stdout). Bounded: kills the process after
    60 s. sigint_ignored: start it with SIGINT ignored, as a background job of a script inherits it."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "flightstack",
            "sim",
            str(mission),
            "--out",
            str(out),
            "--duration",
            "600",
            "--progress",  # stderr is a pipe here: the bars only with --progress
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if sigint_ignored else None,
    )
    try:
        buf, deadline = "", time.monotonic() + 60
        while "mode none" not in buf and time.monotonic() < deadline and proc.poll() is None:
            buf += proc.stderr.read(1) if proc.stderr else ""
        # the bar appears at the mode's start, before takeoff: wait for its first recorded rows (on a
        # loaded machine the takeoff alone outlasted run_seconds, and the interrupt found nothing to keep)
        rows = out / "timeseries_none.rows"
        eventually(lambda: (rows.exists() and rows.stat().st_size > 4096) or proc.poll() is not None, 60.0)
        time.sleep(run_seconds)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, buf + stderr, stdout


def terminal_lines(text: str) -> list[str]:
    """The lines a terminal shows after printing `text`: a carriage return goes back to the line's start
    and what follows overwrites it, a newline starts the next line, ESC [ A goes one line up (tqdm's
    moves between bars); trailing blanks dropped."""
    rows: list[list[str]] = [[]]
    r = c = i = 0
    while i < len(text):
        if text.startswith("\x1b[A", i):
            r, i = max(0, r - 1), i + 3
            continue
        ch, i = text[i], i + 1
        if ch == "\r":
            c = 0
        elif ch == "\n":
            r, c = r + 1, 0
            rows.extend([] for _ in range(r + 1 - len(rows)))
        else:
            row = rows[r]
            row.extend(" " * max(0, c + 1 - len(row)))
            row[c], c = ch, c + 1
    return ["".join(row).rstrip() for row in rows]


def secured_bus(
    certs_dir: Path, mission: str, drone_ids: list[int], names: tuple[str, ...], **zenoh: object
) -> dict:
    """A `bus:` section of kind zenoh with mutual TLS on free loopback ports: `flightstack certs`' files
    for `mission` (drones `drone_ids`, endpoints `names`) written to `certs_dir`, one
    `tls/127.0.0.1:PORT` per name."""
    from flightstack.comms.certs import create_mission_certs, participants
    from flightstack.comms.factory import free_loopback_endpoints

    create_mission_certs(mission, participants(drone_ids, names), certs_dir)
    eps = [e.replace("tcp/", "tls/", 1) for e in free_loopback_endpoints(len(names))]
    endpoints = dict(zip(names, eps, strict=True))
    return {"kind": "zenoh", "certs": str(certs_dir), "zenoh": {"endpoints": endpoints, **zenoh}}


def status_payload(drone: int, flying: bool = True, **changes: object) -> dict:
    """A full status payload (runner.StatusPublisher's fields, exactly what control.StatusReport takes)."""
    return {
        "drone": drone,
        "mode": "dgp",
        "t": 1.0,
        "tick": 1,
        "battery_pct": 80.0,
        "flying": flying,
        "link_alive": True,
        "visible": True,
        "n_fused": 1,
        "pose_fresh": True,
        "rejection": None,
        "dropped": {},
        "restarts": {},
        **changes,
    }


def process_running(pid: int) -> bool:
    """pid exists and is not a zombie (a process nobody reaps, e.g. under a container's init, has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def eventually(pred: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """True as soon as pred() is (polled every 5 ms), else pred() after timeout_s seconds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return pred()


def random_recording(mode: str, ids: list[int], n_ticks: int, seed: int = 0) -> Recording:
    """A recording of n_ticks ticks with every array of ARRAY_FIELDS random (bool, small ints, normal
    floats), t every 0.05 s and ticks_done = n_ticks: for tests of what stores or exports recordings."""
    rng = np.random.default_rng(seed)
    rec = Recording.empty(mode, list(ids), n_ticks)
    for f in ARRAY_FIELDS:
        a = getattr(rec, f)
        if a.dtype == bool:
            a[:] = rng.random(a.shape) > 0.5
        elif a.dtype.kind == "i":
            a[:] = rng.integers(0, 4, a.shape)
        else:
            a[:] = rng.normal(size=a.shape)
    rec.t[:] = np.arange(n_ticks) * 0.05
    rec.ticks_done = n_ticks
    return rec


def fly_mode(
    mission: Any,
    mode: str,
    predictors: Any = None,
    progress: Callable[[int], None] | None = None,
    **flight: Any,
) -> Recording:
    """One mode of `mission` through flightstack.runtime.flight.Flight, as every entry point flies it;
    `flight`: Flight's keyword arguments (compiled, taps, backend, bus, ...)."""
    from flightstack.runtime.flight import Flight

    factory = None if progress is None else (lambda _mode, _n: progress)
    with Flight(mission, progress=factory, **flight) as f:
        return f.fly_mode(mode, predictors)


def tello_emulator(ip: str = "127.0.0.3", **kw: Any) -> Any:
    """A TelloEmulator on `ip` whose state and video go to free ports of 127.0.0.1 (not started)."""
    from flightstack.ports import free_udp_port
    from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator

    kw.setdefault("video_port", free_udp_port())
    return TelloEmulator(ip, state_port=free_udp_port(), **kw)


def tello_config(emu: Any, **kw: Any) -> Any:
    """A TelloConfig for the driver against `emu`: the driver's default timing but short connect and
    command timeouts (2 s, 1 s) and the lab's rc gains; `kw` replaces any field."""
    from flightstack.drivers.tello.config import TelloConfig
    from flightstack.drivers.tello.rc import RcGains

    base: dict[str, Any] = dict(
        host=emu.ip,
        control_port=emu.address[1],
        video_port=emu.video_port,
        state_port=emu.state_port,
        connect_timeout_s=2.0,
        command_timeout_s=1.0,
        rc_gains=RcGains(0.01, 0.01, 0.0175),
    )
    return TelloConfig(**{**base, **kw})
