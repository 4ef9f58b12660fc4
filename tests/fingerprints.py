"""Fly the short runs that tests/data/fingerprints.json fingerprints; compare with it, or re-baseline it.

    python tests/fingerprints.py            # fly, compare with the stored file; exit 1 naming what differs
    python tests/fingerprints.py --update   # fly and rewrite tests/data/fingerprints.json (re-baseline)

Each run of RUNS is `flightstack run EXPERIMENT --rig RIG --duration S --modes M` through the CLI's own
entry point (the data run, GP training, every mode, the run directory written as it flies, the plots),
read back from its run directory (flightstack.recording.run_reader.read_run) and fingerprinted per mode
(flightstack.recording.fingerprint says what is fingerprinted and why). tests/test_fingerprints.py runs
the comparison in the unit tier; docs/fingerprints.md says when and how to re-baseline.

Portability. Bit-exact results depend on the code a numeric library picks for the CPU: numpy dispatches
its loops by CPU (on AVX-512 its SVML transcendentals, which differ from the AVX2 and scalar paths in the
last bit), OpenBLAS picks its kernels by CPU and splits work by thread count, OpenCV dispatches its image
functions, and glibc's libm has FMA variants of exp, log, pow, sin, cos, atan, ... that round
differently. So the runs fly in a child process started with `pinned_env()`, in place before numpy is
imported: numpy without any dispatched loop (its baseline, x86-64-v2 in numpy 2.4), OpenBLAS's Nehalem
(SSE) kernels on one thread, OpenCV without its dispatched paths (its SSE3 baseline) on one thread,
glibc's libm without its FMA variants. Every x86-64-v2 machine (what numpy 2.4 itself requires) has
that code, so the same library versions should give the same bits on any of them (checked on one machine
by forcing each path further down, below; no second machine yet). The numba kernels
(flightstack/paper/kernels.py) are compiled for the host CPU, but without fastmath LLVM neither
contracts nor reorders floating-point arithmetic, and numba uses no SVML (it would with Intel's icc_rt
installed); NUMBA_CPU_NAME is left alone (it changes numba's cache key: every kernel would compile
again, ~20 s).

Measured on a 2-core AMD EPYC (Zen 4, AVX-512) over the 170 fingerprints: without the pinning 79 differ
from the pinned ones (poses, estimates, errors, commands and GP outputs; never t, visible, n_fused, the
ages, the events or the facts), 55 of them from numpy's AVX-512 loops alone. Pinned only to AVX2 level
(numpy without AVX-512, OpenBLAS Haswell, libm with FMA), 79 differ too; from there each step down
changes bits on its own (OpenBLAS Haswell → Nehalem 52, OpenCV without SSE4.1 to AVX2 23, glibc's libm
without FMA 76) except numpy's (AVX2 loops → baseline: none), which is why the pinning goes down to the
baseline. With it, forcing further (numba compiled for a generic x86-64, glibc without AVX or AVX-512
either) changes none, and repeated runs, also beside a CPU-bound process, are identical.

Limits: the bits are also a function of the libraries' versions (numpy, scipy — its L-BFGS-B fits the
GP experts —, numba/llvmlite, OpenCV, the OpenBLAS builds they bundle, glibc) and of the platform: ARM
(Apple silicon, Graviton), macOS and Windows (another libm, other builds) give other bits, and so does an
older glibc that does not know these tunables. `environment()` records what the bits depend on;
`differences` compares the SHA-256 exactly where it is the same and only the summaries elsewhere.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import platform
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

STORED = Path(__file__).resolve().parent / "data" / "fingerprints.json"
COMMAND = "python tests/fingerprints.py --update"
"""The command that regenerates STORED (from the repository's root)."""
FORMAT = 1
"""Version of STORED's layout (and of fingerprint.array_fingerprint's header); bump with either."""
SUMMARY_REL = 1e-3
SUMMARY_ABS = 1e-9
"""How far an array's norm may move in another environment (relative; absolute, in the array's unit):
the CPU paths of the module docstring moved the norms by at most 1.2e-4 of themselves (the GP modes: the
experts' fit amplifies last bits), and those of arrays at rounding level (the oracle's errors, norm
~1e-13) by 0.6 %, far below SUMMARY_ABS."""
SAME_SUMMARY = "same summary: a change it does not show, e.g. below the norm's 6 significant digits"
"""Said of a fingerprint that differs while its summary does not."""
CHILD_TIMEOUT_S = 600.0
"""Bound on the child process that flies every run (s); it takes ~15 s on 2 busy cores."""


@dataclass(frozen=True)
class Run:
    """One `flightstack run` whose recordings are fingerprinted (duration in s of mission time)."""

    rig: str
    experiment: str
    duration_s: float
    modes: tuple[str, ...]

    @property
    def key(self) -> str:
        return f"{self.rig}/{self.experiment}"

    def argv(self, out: Path) -> list[str]:
        """The `flightstack` arguments of this run into the run directory `out`."""
        return [
            "run", self.experiment, "--rig", self.rig, "--duration", f"{self.duration_s:g}",
            "--modes", ",".join(self.modes), "--out", str(out), "--no-progress",
        ]  # fmt: skip


RUNS = (
    # the paper's simulation on its rig: the compiled loop; 12 s is the shortest that trains the experts
    Run("ideal", "paper_sim", 12.0, ("none", "local", "dgp", "oracle")),
    # the paper's experiment (square-driving target, camera mounts, an observer-less drone) on both rigs;
    # 10 s: 8 s is the shortest that trains on lab-sim, and a little margin keeps a small change of the
    # flight from leaving a band short of samples. `oracle` knows only the Duffing target.
    Run("ideal", "paper_experiment", 10.0, ("none", "local", "dgp")),
    Run("lab-sim", "paper_experiment", 10.0, ("none", "local", "dgp")),
)


def _numpy_dispatch_targets() -> tuple[list[str], list[str]]:
    """(numpy's dispatch targets, those this CPU runs), by the names NPY_DISABLE_CPU_FEATURES takes."""
    try:
        from numpy._core import _multiarray_umath as um
    except ImportError:  # numpy 1.x
        from numpy.core import _multiarray_umath as um  # type: ignore[no-redef]
    targets = list(um.__cpu_dispatch__)
    return targets, [t for t in targets if um.__cpu_features__.get(t)]


def pinned_env() -> dict[str, str]:
    """The environment that pins the numeric libraries to their x86-64 baseline code (module docstring:
    portability), by the names this machine's numpy and OpenCV builds use; set before numpy is imported."""
    import cv2

    env = {
        "OPENBLAS_CORETYPE": "Nehalem",  # OpenBLAS (numpy's and scipy's): its SSE kernels on any CPU
        "OPENBLAS_NUM_THREADS": "1",  # and one thread: no work split by core count
        "OMP_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "OPENCV_FOR_THREADS_NUM": "1",
        # glibc's libm: not its FMA variants of exp, log, pow, sin, cos, tan, atan, ... (they round
        # differently in the last bit); numba's kernels call these too
        "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-FMA4",
    }
    # every dispatch target: numpy runs its baseline loops (a name that is not a target voids the whole
    # variable in numpy 2.4, so only the names this numpy reports)
    targets, _ = _numpy_dispatch_targets()
    if targets:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(targets)
    dispatched = [f.strip("*?") for f in cv2.getCPUFeaturesLine().split() if f.startswith("*")]
    if dispatched:  # OpenCV: its baseline code (SSE3 in the wheels), none of the dispatched paths
        env["OPENCV_CPU_DISABLE"] = ",".join(dispatched)
    return env


def environment() -> dict[str, str]:
    """What the bits depend on besides the code: the platform, the numeric libraries' versions and the
    code paths they run here (numpy's SIMD targets, OpenBLAS's kernels and threads, OpenCV's SIMD)."""
    import cv2
    import llvmlite
    import numba
    import numpy
    import scipy
    import scipy.linalg  # loads scipy's OpenBLAS, for threadpoolctl to see
    from threadpoolctl import threadpool_info

    _, running = _numpy_dispatch_targets()
    blas = [
        f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')} x{i.get('num_threads')}"
        for i in threadpool_info()
        if i.get("user_api") == "blas"
    ]
    return {
        "platform": f"{platform.system()} {platform.machine()} {' '.join(platform.libc_ver())}".strip(),
        "python": ".".join(platform.python_version_tuple()[:2]),
        "numpy": numpy.__version__,
        "numpy_simd": " ".join(running) or "baseline",
        "blas": "; ".join(sorted(blas)),
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "llvmlite": llvmlite.__version__,
        "opencv": cv2.__version__,
        "opencv_simd": cv2.getCPUFeaturesLine(),
    }


def _fly(runs: tuple[Run, ...]) -> dict[str, Any]:
    """In this process: fly every run and fingerprint its recordings (the child's work)."""
    from flightstack.cli.app import main
    from flightstack.recording.fingerprint import fingerprints, summaries
    from flightstack.recording.run_reader import read_run

    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="fingerprints-") as tmp:
        for run in runs:
            run_dir = Path(tmp) / run.key.replace("/", "-")
            with contextlib.redirect_stdout(sys.stderr):  # the run's summary; stdout is not ours
                code = main(run.argv(run_dir))
            if code != 0:
                raise RuntimeError(f"{run.key}: `flightstack {' '.join(run.argv(run_dir))}` exited {code}")
            contents = read_run(run_dir)
            if contents.skipped or not contents.status.get("complete"):
                raise RuntimeError(f"{run.key}: recording not complete: {contents.status} {contents.skipped}")
            modes: dict[str, Any] = {}
            for mode, rec in contents.recordings.items():
                sums = summaries(rec)
                modes[mode] = {name: {"sha256": h, **sums[name]} for name, h in fingerprints(rec).items()}
            out[run.key] = {"command": "flightstack " + " ".join(run.argv(Path("DIR"))), "modes": modes}
    return out


def compute(env: dict[str, str] | None = None, pinned: bool = True) -> dict[str, Any]:
    """Fly RUNS in a child process and return the document STORED holds: the fingerprints and summaries
    per run, mode and array, the environment and the command that regenerates it.

    env: more environment for the child (experiments: other CPU paths); pinned: start the child with
    `pinned_env()` (False only to measure what the pinning changes). RuntimeError with the
    child's stderr when a run fails."""
    pins = pinned_env()
    child_env = {k: v for k, v in os.environ.items() if k not in pins}
    child_env.update(pins if pinned else {})
    child_env.update(env or {})
    with tempfile.TemporaryDirectory(prefix="fingerprints-") as tmp:
        result = Path(tmp) / "result.json"
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--child", str(result)],
            env=child_env,
            capture_output=True,
            text=True,
            timeout=CHILD_TIMEOUT_S,
        )
        if proc.returncode != 0 or not result.exists():
            raise RuntimeError(f"the runs failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}")
        runs = json.loads(result.read_text())
    return {
        "format": FORMAT,
        "command": COMMAND,
        "environment": runs.pop("environment"),
        "pinned_env": pins if pinned else {},
        "runs": runs["runs"],
    }


def _summary(entry: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in entry.items() if k != "sha256"}


def _entry_text(entry: dict[str, Any] | None) -> str:
    return "absent" if entry is None else json.dumps(_summary(entry), sort_keys=True)


def differences(stored: dict[str, Any], new: dict[str, Any]) -> tuple[list[str], bool]:
    """(what differs, exact): one line per run, mode or fingerprint of `new` that does not match `stored`.

    exact: the two were made in the same `environment()`, and every SHA-256 must be equal. In another
    one (a library release, another platform) only the summaries must agree (fingerprint.summaries_agree
    within SUMMARY_REL or SUMMARY_ABS): last bits do not count there, a change of values beyond them, of
    shapes, events or facts does."""
    from flightstack.recording.fingerprint import summaries_agree

    exact = stored.get("environment") == new.get("environment")
    if stored.get("format") != new.get("format"):
        return [f"format {stored.get('format')} stored, {new.get('format')} now"], exact

    def agree(a: dict[str, Any], b: dict[str, Any]) -> bool:
        if exact:
            return bool(a["sha256"] == b["sha256"])
        return summaries_agree(_summary(a), _summary(b), SUMMARY_REL, SUMMARY_ABS)

    lines: list[str] = []
    s_runs, n_runs = stored.get("runs", {}), new.get("runs", {})
    for key in sorted(set(s_runs) | set(n_runs)):
        if key not in s_runs or key not in n_runs:
            lines.append(f"{key}: {'not stored' if key not in s_runs else 'not flown now'}")
            continue
        s_modes, n_modes = s_runs[key]["modes"], n_runs[key]["modes"]
        if list(s_modes) != list(n_modes):
            lines.append(f"{key}: modes {list(s_modes)} stored, {list(n_modes)} now")
        for mode in [m for m in n_modes if m in s_modes]:
            s, n = s_modes[mode], n_modes[mode]
            for name in [*s, *(x for x in n if x not in s)]:
                a, b = s.get(name), n.get(name)
                if a is not None and b is not None and agree(a, b):
                    continue
                noise = f" ({SAME_SUMMARY})" if _entry_text(a) == _entry_text(b) else ""
                lines.append(
                    f"{key} {mode} {name}{noise}:\n    stored {_entry_text(a)}\n    now    {_entry_text(b)}"
                )
    return lines, exact


def report(lines: list[str], exact: bool, stored_env: dict[str, Any], new_env: dict[str, Any]) -> str:
    """The message of a mismatch: what differs, in which comparison, and how to re-baseline."""
    if exact:
        how = "exact comparison: same platform, library versions and CPU paths"
    else:
        changed = {k: (stored_env.get(k), new_env.get(k)) for k in stored_env | new_env}
        changed = {k: v for k, v in changed.items() if v[0] != v[1]}
        how = f"summary comparison, the environment differs (stored, now): {changed}"
    return (
        f"{len(lines)} fingerprint(s) differ from {STORED.name} ({how}):\n"
        + "\n".join(f"  {line}" for line in lines)
        + f"\nIf the change of the recordings is intended, re-baseline: `{COMMAND}`, and commit "
        f"tests/data/{STORED.name} in a commit of its own that says why they changed."
    )


def dumps(doc: dict[str, Any]) -> str:
    """`doc` (compute's document) as indented JSON with one line per fingerprint, so that a re-baseline's
    diff shows one line per array that changed."""
    entries: list[str] = []
    skeleton = copy.deepcopy(doc)
    for run in skeleton.get("runs", {}).values():
        for entries_of_mode in run["modes"].values():
            for name, entry in entries_of_mode.items():
                entries_of_mode[name] = f"@{len(entries)}@"
                entries.append(json.dumps(entry))
    text = json.dumps(skeleton, indent=1)
    for i, entry in enumerate(entries):
        text = text.replace(f'"@{i}@"', entry, 1)
    return text + "\n"


def _child(result: Path) -> None:
    out = {"environment": environment(), "runs": _fly(RUNS)}
    result.write_text(json.dumps(out))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--update", action="store_true", help=f"rewrite {STORED} (re-baseline)")
    p.add_argument("--json", metavar="FILE", help="write the computed document to FILE (no comparison)")
    p.add_argument("--env", action="append", default=[], metavar="K=V", help="more environment for the runs")
    p.add_argument("--no-pin", action="store_true", help="without pinned_env() (experiments)")
    p.add_argument("--child", metavar="FILE", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.update and (args.env or args.no_pin):
        p.error("--update stores what the pinned environment gives: not with --env or --no-pin")
    if args.child:
        _child(Path(args.child))
        return 0
    extra = dict(kv.split("=", 1) for kv in args.env)
    new = compute(extra, pinned=not args.no_pin)
    if args.json:
        Path(args.json).write_text(dumps(new))
        return 0
    if args.update:
        STORED.write_text(dumps(new))
        print(f"wrote {STORED}")
        return 0
    stored = json.loads(STORED.read_text())
    lines, exact = differences(stored, new)
    if lines:
        print(report(lines, exact, stored["environment"], new["environment"]), file=sys.stderr)
        return 1
    print(f"every fingerprint matches {STORED.name} ({'exact' if exact else 'summaries'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
