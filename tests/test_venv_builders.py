"""Every virtual environment a test or a CI script builds can import what the environment running it
imports: it is made by tests/venvs.py or `.ci/venv-here`, or says on its line (or the line above) why it
need not (`# venv: <reason>`). The suite runs inside the README's venv, where a plain
`--system-site-packages` venv sees only the base interpreter and cannot import flightstack."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from tests.venvs import venv_seeing_this_environment

REPO = Path(__file__).resolve().parents[1]
BUILDERS = {REPO / ".ci" / "venv-here", REPO / "tests" / "venvs.py"}
"""The two whose whole purpose is such a venv."""
BUILDS_A_VENV = re.compile(r"""-m["',\s]+venv\b|\bvenv\.create\(|\bEnvBuilder\(|\bvirtualenv\b""")
REASON = re.compile(r"#\s*venv:\s*\S")


def _scanned() -> list[Path]:
    files = [*REPO.glob("tests/**/*.py"), *REPO.glob("benchmarks/**/*.py")]
    files += [p for p in (REPO / ".ci").iterdir() if p.is_file()]
    return sorted(p for p in files if p not in BUILDERS and p != Path(__file__))


def unexplained_venv_builders(files: list[Path]) -> list[str]:
    """`path:line: text` of every line that builds a venv without a `# venv:` reason on it or just above."""
    found = []
    for path in files:
        name = path.relative_to(REPO) if path.is_relative_to(REPO) else path
        lines = path.read_text(errors="replace").splitlines()
        for k, line in enumerate(lines):
            if BUILDS_A_VENV.search(line) and not (
                REASON.search(line) or (k > 0 and REASON.search(lines[k - 1]))
            ):
                found.append(f"{name}:{k + 1}: {line.strip()}")
    return found


def test_no_test_builds_a_venv_blind_to_this_environment() -> None:
    found = unexplained_venv_builders(_scanned())
    assert not found, (
        "these build a venv that may not import flightstack when the suite runs inside a venv: use "
        "tests/venvs.py (or .ci/venv-here), or say why not with `# venv: <reason>`:\n" + "\n".join(found)
    )


def test_the_scan_finds_the_forms_a_venv_is_built_with(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text(
        'subprocess.run([sys.executable, "-m", "venv", str(d)])\n'
        "venv.create(d)\n"
        "python3 -m venv --system-site-packages d\n"
        "# venv: the base interpreter on purpose\n"
        'subprocess.run(["python3", "-m", "venv", d])\n'
        'run(["python3", "-m", "venv", d])  # venv: bare on purpose\n'
        "import venvs  # a module name, not a build\n"
    )
    found = unexplained_venv_builders([probe])
    assert [f.removeprefix(f"{probe}:").split(":")[0] for f in found] == ["1", "2", "3"]


def test_a_venv_from_tests_venvs_imports_flightstack_outside_the_checkout(tmp_path: Path) -> None:
    venv = venv_seeing_this_environment(tmp_path / "child")
    probe = "import flightstack.drivers.guardian.launcher as g; print(g.GUARDIAN_NAME)"
    out = subprocess.run(
        [str(venv / "bin" / "python"), "-c", probe],
        cwd=tmp_path,  # not the checkout: the import comes through the environment, not the cwd
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "tello-guardian"
