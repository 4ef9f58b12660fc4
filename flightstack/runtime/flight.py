"""One flight: an experiment on a rig, from the run directory to the metrics (DESIGN §1, §7).

`Flight` is the one way anything flies: `flightstack run/sim/fly`, `agent`, `bench-loop`, the fault
table's rows, the sweeps, the benchmarks and the tests.

    with Flight(mission, out, taps=[...], say=print) as flight:  # the rig's emulators, the run directory
        result = flight.fly()      # every mode: the data run, training, the compared modes; metrics.json
    # or one mode:  rec = flight.fly_mode("none")

Entering opens what lives for the whole flight: what the rig opens (`Rig.open`: the emulated lab's
devices), the sleep inhibitor (drones not simulated), the run directory's writer, and for an agent process
(one drone over the network) its bus and backend. Each mode then gets its fleet
(`runtime.fleet.assemble_fleet`: bus, backend, safety layer, agents) and flies it
(`runtime.runner.run_mode`), with the loop the rig offers (`Rig.compiled_loop`: the ideal rig's).
Leaving closes everything opened, in reverse order, on success or failure. Only this module imports
`run_mode` and `assemble_fleet` (tests/import_contract.toml).
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import yaml

from flightstack import threads
from flightstack.analysis.metrics import build_metrics
from flightstack.comms.bus import Bus
from flightstack.config.mission import Mission, MissionError, mission_to_dict
from flightstack.config.types import Mode
from flightstack.events import Event, end_kind
from flightstack.hal import Backend
from flightstack.learning.training import (
    ExpertData,
    collect_datasets,
    load_experts,
    save_datasets,
    save_experts,
    train_experts,
)
from flightstack.paper.gp import GPExpert
from flightstack.paper.target_motion import DuffingParams
from flightstack.recording.files import (
    AGENT_SUMMARY_FILE,
    DATASETS_FILE,
    EMULATED_LAB_DIR,
    EXPERTS_FILE,
    GUARDIAN_LOG,
    MISSION_FILE,
    DeviceFiles,
    check_out_dir,
)
from flightstack.recording.run_dir import RunWriter
from flightstack.recording.timeseries import Recording
from flightstack.runtime.agent import Predictor, TruthPredictor
from flightstack.runtime.camera_tap import CameraTap, has_image_cameras
from flightstack.runtime.fleet import Fleet, assemble_fleet
from flightstack.runtime.keep_awake import keep_awake
from flightstack.runtime.resources import check_recording_fits
from flightstack.runtime.rig import AgentSeat, open_agent_backend, opened, rig_of
from flightstack.runtime.runner import SafePause, run_mode, run_procedure
from flightstack.runtime.taps import TickTap

_R = TypeVar("_R")

ProgressFactory = Callable[[str, int], Callable[[int], None]]
"""(mode, number of ticks) -> a callback told how many ticks were flown since its last call."""


class NotFlownError(RuntimeError):
    """The flight could not start (the run directory, the agent's seat, ...): nothing took off."""


@dataclass
class FlightResult:
    """What a flight produced: each flown mode's recording, the training data and experts, the metrics
    (metrics.json's content; with "recording": {"complete", "reason"} once written), and how it ended."""

    recordings: dict[str, Recording] = field(default_factory=dict)
    datasets: list[ExpertData] = field(default_factory=list)
    experts: dict[int, GPExpert] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    interrupted: bool = False
    error: str | None = None
    gp_info: dict[str, object] = field(default_factory=dict)


def quiet(line: str) -> None:
    """The default `say`: the flight's status lines go nowhere."""


class Flight:
    """One flight of `mission` (a context manager; see the module).

    out: the run directory (None: nothing is written). modes: the modes to fly (default the mission's
    compare_modes); a GP mode without gp.experts_file gets the data run `none` and training first.
    agent_id: fly only this drone, over the mission's network bus (an agent process; its GP modes need
    gp.experts_file). backend, bus: given by the caller (kept open; the caller closes them), else built
    per mode. wrap_backend, wrap_bus: applied to what is built (the fault table's injectors). taps:
    observers of every tick (runtime.taps; on a rig with image cameras a CameraTap records the frames
    into `out` besides). progress: per-mode progress callbacks. compiled: use the
    rig's compiled loop where it has one (False: every tick through the Agents, the reference path).
    plots: draw the run's plots into `out` at the end. live_mcap: `out`/recording.mcap written as the
    run goes (flightstack.recording.mcap_live). say: where status lines go (the CLI: stderr)."""

    def __init__(
        self,
        mission: Mission,
        out: Path | None = None,
        *,
        modes: Sequence[str] | None = None,
        agent_id: int | None = None,
        backend: Backend | None = None,
        bus: Bus | None = None,
        wrap_backend: Callable[[Backend], Backend] | None = None,
        wrap_bus: Callable[[Bus], Bus] | None = None,
        taps: Sequence[TickTap] = (),
        progress: ProgressFactory | None = None,
        compiled: bool = True,
        plots: bool = False,
        live_mcap: bool = False,
        say: Callable[[str], None] = quiet,
    ) -> None:
        self.mission = mission
        self.live_mcap = live_mcap
        self.out = None if out is None else Path(out)
        self.agent_id = agent_id
        self.modes = _with_data_run(mission, list(mission.compare_modes if modes is None else modes))
        if agent_id is not None:
            _check_agent(mission, agent_id, self.modes)
        self.taps = list(taps)
        self.progress = progress
        self.compiled = compiled
        self.plots = plots
        self.say = say
        self.writer: RunWriter | None = None
        self._backend, self._bus = backend, bus
        self._wrap_backend, self._wrap_bus = wrap_backend, wrap_bus
        self._stack: contextlib.ExitStack | None = None
        self._plan_loop = rig_of(mission).compiled_loop() if compiled else None

    @property
    def n_ticks(self) -> int:
        """Ticks of pursuit per mode (Mission.n_ticks)."""
        return self.mission.n_ticks

    @property
    def ids(self) -> list[int]:
        """The drones this process flies (recording order)."""
        return [d.id for d in self.mission.drones] if self.agent_id is None else [self.agent_id]

    # ---- what lives for the whole flight --------------------------------------------------------------
    def __enter__(self) -> Flight:
        stack = contextlib.ExitStack()
        try:
            if rig_of(self.mission).starts_emulators:  # the emulated-lab rig: its devices, on loopback
                lab_dir = None if self.out is None else self.out / EMULATED_LAB_DIR
                self.mission = stack.enter_context(opened(self.mission, lab_dir))
                self._plan_loop = rig_of(self.mission).compiled_loop() if self.compiled else None
                self.say(
                    f"emulated lab: {len(self.mission.drones)} Tello emulators, NatNet, rover on loopback"
                )
            if not self.mission.simulated:  # hardware (or its emulation): the computer must not sleep
                self.say(
                    stack.enter_context(keep_awake(f"flightstack: mission {self.mission.name} in flight"))
                )
            if self.out is not None:
                self.writer = stack.enter_context(_open_run_dir(self.out, self.live_mcap))
                self.writer.write_file(MISSION_FILE, resolved_mission_yaml(self.mission))  # for `report`
            if self.agent_id is not None:
                self._open_seat(stack)
        except BaseException:
            stack.close()
            raise
        self._stack = stack
        return self

    def __exit__(self, *exc: object) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            stack.close()

    def _open_seat(self, stack: contextlib.ExitStack) -> None:
        """An agent's bus and backend, open for the whole flight (the kernels compiled first: the bus's
        receive thread checks messages with them)."""
        from flightstack.comms.factory import make_bus
        from flightstack.comms.zenoh_bus import ZenohBus
        from flightstack.paper.kernels_warmup import warm_up

        assert self.agent_id is not None
        warm_up()
        bus = make_bus(self.mission, self.mission.identity(self.agent_id).agent, {self.agent_id})
        stack.callback(bus.close)
        log = str((self.out or Path(tempfile.gettempdir())) / GUARDIAN_LOG)
        session = bus.session if isinstance(bus, ZenohBus) else None
        seat = AgentSeat(self.agent_id, session, log, self._device_files("+".join(self.modes)))
        self._bus = bus
        self._backend = stack.enter_context(open_agent_backend(self.mission, seat))

    # ---- flying ---------------------------------------------------------------------------------------
    def fly_mode(self, mode: str, predictors: Mapping[int, Predictor] | None = None) -> Recording:
        """Fly one mode: its fleet assembled, flown, landed, recorded (into the run directory as it
        flies); never leaves a drone flying. The Recording holds what was flown (truncated if cut short)."""
        if self._stack is None:
            raise RuntimeError("a Flight flies inside `with Flight(...) as flight:`")
        writer = None if self.writer is None else self.writer.mode(mode, self.ids, self.n_ticks)
        progress = None if self.progress is None else self.progress(mode, self.n_ticks)
        taps = list(self.taps)
        if self.out is not None and has_image_cameras(self.mission):  # the frames, for the MCAP's images
            taps.append(CameraTap(self.out))
        flying = False  # run_mode has the mode: it closes the recording itself (flown rows and all)
        try:
            with self._assemble(self.mission, mode, predictors, writer, mode) as fleet:
                flying = True
                return run_mode(fleet, progress, writer=writer, taps=taps, plan_loop=self._plan_loop)
        except BaseException as exc:
            # stopped while the fleet was assembled; after that a recording left open keeps its row stream
            if not flying and writer is not None and not writer.closed:
                _close_unflown(writer, mode, self.ids, self.n_ticks, exc)
            raise

    def _assemble(
        self,
        mission: Mission,
        mode: str,
        predictors: Mapping[int, Predictor] | None,
        writer: Any,
        session: str,
    ) -> contextlib.AbstractContextManager[Fleet]:
        """This flight's fleet for one mode or procedure: its backend, bus, agents and fault wrappers,
        the devices' traffic recorded under `session` (see DeviceFiles)."""
        return assemble_fleet(
            mission,
            mode,
            predictors,
            backend=self._backend,
            bus=self._bus,
            agent_ids=None if self.agent_id is None else [self.agent_id],
            writer=writer,
            wrap_backend=self._wrap_backend,
            wrap_bus=self._wrap_bus,
            devices=self._device_files(session),
        )

    def _device_files(self, session: str) -> DeviceFiles | None:
        """Where the devices' raw traffic of one connection (`session`: see DeviceFiles) is recorded: in
        the run directory, when there is one."""
        return None if self.out is None else DeviceFiles(self.out, session)

    def fly_procedure(
        self, procedure: Callable[[Fleet, SafePause], _R], mission: Mission | None = None
    ) -> _R:
        """Fly `procedure(fleet, pause)` instead of pursuit (runtime.runner.run_procedure: take off, the
        procedure, land whatever ends it; nothing recorded): a calibration's pattern. mission: the
        mission the fleet is built from (default `self.mission`, which for the emulated lab is re-pointed
        at its running devices once the flight is entered: edit that one)."""
        if self._stack is None:
            raise RuntimeError("a Flight flies inside `with Flight(...) as flight:`")
        with self._assemble(
            self.mission if mission is None else mission, Mode.NONE.value, None, None, "procedure"
        ) as fleet:
            return run_procedure(fleet, procedure)

    def fly(self) -> FlightResult:
        """Every mode of `self.modes` (the data run first, then training), then the metrics; with a run
        directory, everything written there (metrics.json last: "recording" says whether the recording is
        complete, also when metrics.json itself could not be written; the plots if asked). Stops at the
        first mode that was interrupted or ended in an error (the recordings so far are kept; a Ctrl-C
        outside a mode's flight, e.g. while its fleet is assembled or in training, ends it the same
        way). Raises MissionError before anything flies when the recordings would not fit in memory."""
        check_recording_fits(self.mission)
        mission, res = self.mission, FlightResult()
        wall0 = time.perf_counter()
        needs_training = _needs_training(mission, self.modes)
        if any(Mode(m).uses_gp for m in self.modes) and mission.gp.experts_file is not None:
            res.experts = load_experts(mission.resolve(mission.gp.experts_file))
            missing = set(self.ids) - set(res.experts)
            if missing:
                raise MissionError(f"gp.experts_file has no expert for drone(s) {sorted(missing)}")
        try:
            for mode in self.modes:
                rec = self.fly_mode(mode, self._predictors(mode, res))
                res.recordings[mode] = rec
                if rec.interrupted or rec.error:
                    res.interrupted, res.error = rec.interrupted, rec.error
                    break
                if mode == Mode.NONE and needs_training and not self._train(rec, res):
                    break
        except KeyboardInterrupt:  # between modes, in training, or while a mode's fleet was assembled
            res.interrupted = True  # (run_mode lands and records a Ctrl-C once its fleet flies)
        res.metrics = build_metrics(
            mission,
            res.recordings,
            res.experts,
            res.gp_info,
            time.perf_counter() - wall0,
            interrupted=res.interrupted,
            error=res.error,
        )
        res.metrics["threads"] = threads.in_effect().as_dict()  # the pools this flight ran with
        if self.writer is not None:
            try:
                res.metrics = _write_results(self.writer, res)
            except OSError as exc:  # every drone has landed; the row streams and events.jsonl stay readable
                reason = f"metrics.json not written: {exc.strerror or exc}"
                res.metrics["recording"] = {"complete": False, "reason": reason}
                self.say(f"error: {reason}")
            if self.agent_id is not None:
                self._write_agent_summary(res)
            if self.plots and res.recordings:
                self._draw_plots(res)
        return res

    def _predictors(self, mode: str, res: FlightResult) -> Mapping[int, Predictor] | None:
        if Mode(mode).uses_gp:
            return res.experts
        if mode == Mode.ORACLE:
            prm = DuffingParams(**self.mission.target.duffing.model_dump())
            return {i: TruthPredictor(prm) for i in self.ids}
        return None

    def _train(self, rec: Recording, res: FlightResult) -> bool:
        """Datasets from the data run and one expert per drone (written at once, so that a run killed
        later still has them for `report`); False (res.error set) when the data cannot train them."""
        mission, t0, cpu0 = self.mission, time.perf_counter(), time.process_time()
        try:
            res.datasets = collect_datasets(mission, rec, mission.seed)
        except ValueError as exc:  # too little data in a region: say so, keep the `none` run
            res.error = f"GP training data: {exc} (fly longer, or lower gp.samples_per_region)"
            return False
        res.experts = train_experts(mission, res.datasets, mission.seed)
        if self.writer is not None:
            _write_training(self.writer, res)
        res.gp_info = {
            "train_seconds": time.perf_counter() - t0,
            "train_cpu_seconds": time.process_time() - cpu0,  # every thread's: BLAS's spinning shows here
            "experts": {
                str(i): {
                    "samples": int(ex.X.shape[0]),
                    "sigma_f": ex.hyper.sigma_f.tolist(),
                    "length_scales": ex.hyper.length_scales.tolist(),
                    "log_marginal_likelihood": ex.log_marginal_likelihood().tolist(),
                }
                for i, ex in res.experts.items()
            },
        }
        return True

    def _write_agent_summary(self, res: FlightResult) -> None:
        """agent_summary.json: what an agent's flight saw of the network (drops, gaps, other sessions)."""
        assert self.writer is not None and self.agent_id is not None
        rec = next(iter(res.recordings.values()), None)
        link = getattr(self._backend, "link", None)  # the served world's link (simulated rigs)
        summary = {
            "drone": self.agent_id,
            "mode": None if rec is None else rec.mode,
            "ticks": 0 if rec is None else rec.ticks_done,
            "interrupted": res.interrupted,
            "error": res.error,
            "bus_dropped": {} if rec is None else rec.bus_dropped,
            # served world only: world ticks this agent refused, by reason (world_messages.py)
            "world_dropped": dict(link.dropped) if link is not None else {},
            # ticks the world went on without this agent's cmd (tick_gate.py)
            "world_gaps": dict(link.gaps) if link is not None else {},
            # other processes that spoke as a drone (comms/identity.py): one line each
            "second_sessions": self.session_reports(),
        }
        try:
            self.writer.write_metrics(summary, AGENT_SUMMARY_FILE)
        except OSError as exc:
            self.say(f"agent {self.agent_id}: {AGENT_SUMMARY_FILE} not written: {exc}")

    def session_reports(self) -> list[str]:
        """Other processes that spoke as one of this flight's drones on the bus (one line each)."""
        return list(getattr(self._bus, "session_reports", []))

    def _draw_plots(self, res: FlightResult) -> None:
        """The run's plots; a write error (a full disk) is said, not raised: `report` redraws them."""
        from flightstack.analysis.report import write_plots

        assert self.out is not None
        try:
            write_plots(self.out, self.mission, res.recordings, res.datasets)
        except OSError as exc:
            self.say(f"warning: plots not written ({exc}); `flightstack report {self.out}` redraws them")


def _close_unflown(writer: Any, mode: str, ids: list[int], n_ticks: int, exc: BaseException) -> None:
    """Close the recording of a mode that stopped before its fleet flew (a Ctrl-C or an error while the
    fleet was assembled, e.g. the kernels loading on a busy computer): no tick, interrupted or with the
    error, and its end event, so that the run's recording is complete with what there is."""
    rec = Recording.empty(mode, ids, n_ticks)
    rec.interrupted = isinstance(exc, KeyboardInterrupt)
    reason = "interrupted" if rec.interrupted else f"exception: {type(exc).__name__}: {exc}"
    rec.error = None if rec.interrupted else reason.removeprefix("exception: ")
    facts = {"reason": reason, "before_takeoff": True}
    rec.events.append(Event(0.0, None, end_kind(reason), facts=facts).record(mode))
    writer.close(rec)


def _with_data_run(mission: Mission, modes: list[str]) -> list[str]:
    """`modes` with the data run `none` first when a GP mode needs experts that are not given."""
    if _needs_training(mission, modes):
        return [Mode.NONE.value] + [m for m in modes if m != Mode.NONE]
    return modes


def _needs_training(mission: Mission, modes: Sequence[str]) -> bool:
    return mission.gp.experts_file is None and any(Mode(m).uses_gp for m in modes)


def _check_agent(mission: Mission, agent_id: int, modes: list[str]) -> None:
    """An agent flies one drone of the mission over its network bus, from trained experts."""
    ids = [d.id for d in mission.drones]
    if agent_id not in ids:
        raise MissionError(f"--id {agent_id}: the mission's drones are {ids}")
    if mission.bus.zenoh is None:
        raise MissionError("bus.kind: an agent process needs the zenoh bus")
    if Mode.ORACLE in modes:  # the truth predictor needs the world's truth, which agents do not get
        raise MissionError("mode 'oracle' runs in one process only (flightstack sim)")
    if mission.gp.experts_file is None and any(Mode(m).needs_predictor for m in modes):
        raise MissionError(f"gp.experts_file: mode(s) {modes} in an agent process need trained experts")


@contextlib.contextmanager
def _open_run_dir(out: Path, live_mcap: bool = False) -> Any:
    """The run directory's writer, after checking (before anything takes off) that `out` is writable
    and has flightstack.recording.files.MIN_FREE_BYTES free; NotFlownError naming the problem.
    live_mcap: recording.mcap written as the run goes (flightstack.recording.mcap_live)."""
    problem = check_out_dir(out)
    if problem is not None:
        raise NotFlownError(f"--out {out}: {problem}")
    try:
        writer = RunWriter(out, live_mcap=live_mcap)
    except OSError as exc:
        raise NotFlownError(f"--out {out}: cannot start the recording: {exc.strerror or exc}") from None
    with writer:
        yield writer


def resolved_mission_yaml(mission: Mission) -> str:
    """The mission as YAML with absolute file paths, so that it loads from the run directory."""
    resolved = mission_to_dict(mission)
    for d in resolved["drones"]:
        if d.get("camera") and d["camera"].get("calibration"):
            d["camera"]["calibration"] = str(mission.resolve(d["camera"]["calibration"]))
    if resolved["gp"].get("experts_file"):
        resolved["gp"]["experts_file"] = str(mission.resolve(resolved["gp"]["experts_file"]))
    return yaml.safe_dump(resolved, sort_keys=False)


def write_run_dir(out: Path, mission: Mission, res: FlightResult) -> dict[str, Any]:
    """A finished flight's run directory written afterwards (a sweep's kept runs): the resolved mission,
    one npz per mode, events.jsonl, the datasets and experts, then metrics.json; returns what
    metrics.json holds (OSError when it cannot be written)."""
    with RunWriter(out) as writer:
        writer.write_file(MISSION_FILE, resolved_mission_yaml(mission))
        return _write_results(writer, res)


def _write_results(writer: RunWriter, res: FlightResult) -> dict[str, Any]:
    """Each mode's final npz and events, the training's files, then metrics.json (atomically; with
    "recording": {"complete", "reason"}); after an error non-finite metrics are written as null."""
    for rec in res.recordings.values():
        writer.record(rec)
    _write_training(writer, res)
    return writer.write_metrics(res.metrics, strict=res.error is None)


def _write_training(writer: RunWriter, res: FlightResult) -> None:
    """experts.npz and datasets.npz (when there are any); a write error stops the recording."""
    try:
        if res.experts:
            save_experts(writer.out / EXPERTS_FILE, res.experts)
        if res.datasets:
            save_datasets(writer.out / DATASETS_FILE, res.datasets)
    except OSError as exc:
        writer.fail(f"experts/datasets not written: {exc.strerror or exc}")
