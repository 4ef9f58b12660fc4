"""`.ci/venv-here` makes the type and package checks' venvs see the environment `.ci/run` was started
from: a venv's packages (also its editable installs' .pth files), not only the base interpreter's."""

from __future__ import annotations

import os
import subprocess
import sysconfig
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _purelib(python: Path) -> Path:
    out = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    return Path(out.stdout.strip())


def test_child_venv_sees_the_parent_venv(tmp_path: Path) -> None:
    base = Path(sysconfig.get_config_var("BINDIR")) / "python3"  # the interpreter a venv is made from
    parent = tmp_path / "parent"
    # venv: the parent environment itself, made from the base interpreter
    subprocess.run([str(base), "-m", "venv", "--without-pip", str(parent)], check=True, timeout=120)
    site = _purelib(parent / "bin" / "python")
    (site / "probe_in_parent.py").write_text("WHERE = 'parent venv'\n")
    extra = tmp_path / "editable_src"  # what an editable install's .pth adds
    extra.mkdir()
    (extra / "probe_editable.py").write_text("WHERE = 'editable'\n")
    (site / "__editable__probe.pth").write_text(f"{extra}\n")
    env = {**os.environ, "PATH": f"{parent / 'bin'}{os.pathsep}{os.environ['PATH']}"}
    env.pop("PYTHONPATH", None)
    child = tmp_path / "child"
    subprocess.run(["bash", str(REPO / ".ci" / "venv-here"), str(child)], check=True, env=env, timeout=300)
    probe = "import probe_in_parent, probe_editable, sys; print(probe_in_parent.WHERE, probe_editable.WHERE)"
    out = subprocess.run(
        [str(child / "bin" / "python"), "-c", probe], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["parent", "venv", "editable"]
    # the child's own site-packages comes first: what it installs shadows the parent's
    (_purelib(child / "bin" / "python") / "probe_in_parent.py").write_text("WHERE = 'child venv'\n")
    out = subprocess.run(
        [str(child / "bin" / "python"), "-c", "import probe_in_parent; print(probe_in_parent.WHERE)"],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert out.stdout.strip() == "child venv", out.stderr
    # a plain --system-site-packages venv made from the same python3 would not see the parent's packages
    plain = tmp_path / "plain"
    subprocess.run(
        # venv: the blind venv venv-here exists to avoid, built to show that it is blind
        [str(parent / "bin" / "python"), "-m", "venv", "--without-pip", "--system-site-packages", str(plain)],
        check=True,
        env=env,
        timeout=120,
    )
    out = subprocess.run(
        [str(plain / "bin" / "python"), "-c", "import probe_in_parent"],
        capture_output=True,
        env=env,
        timeout=60,
    )
    assert out.returncode != 0
