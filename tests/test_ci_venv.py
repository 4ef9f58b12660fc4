"""`.ci/venv-here` makes the type and package checks' venvs see the environment `.ci/run` was started
from: a venv's packages (also its editable installs' .pth files), not only the base interpreter's."""

from __future__ import annotations

import json
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


def test_a_build_in_the_child_venv_does_not_see_the_parent(tmp_path: Path) -> None:
    """pip's build isolation (pip/_internal/build_env, the sitecustomize of its legacy environment, which
    the pip a Python 3.11 venv ships uses) drops every path that re-adding the venv's own site-packages with
    a fresh known-paths set brings in. The parent's directories must be among them, or a `pip install .`
    in the child builds with the parent's setuptools instead of pyproject.toml's build requirements."""
    base = Path(sysconfig.get_config_var("BINDIR")) / "python3"
    parent = tmp_path / "parent"
    # venv: the parent environment itself, made from the base interpreter
    subprocess.run([str(base), "-m", "venv", "--without-pip", str(parent)], check=True, timeout=120)
    parent_site = _purelib(parent / "bin" / "python")
    env = {**os.environ, "PATH": f"{parent / 'bin'}{os.pathsep}{os.environ['PATH']}"}
    env.pop("PYTHONPATH", None)
    child = tmp_path / "child"
    subprocess.run(["bash", str(REPO / ".ci" / "venv-here"), str(child)], check=True, env=env, timeout=300)
    isolate = (
        "import json, os, site, sys, sysconfig\n"
        "original = sys.path[:]\n"
        "site.addsitedir(sysconfig.get_paths()['purelib'], known_paths=set())\n"
        "dropped = {os.path.normcase(p) for p in sys.path[len(original):]}\n"
        "print(json.dumps([p for p in original if os.path.normcase(p) not in dropped]))\n"
    )
    out = subprocess.run(
        [str(child / "bin" / "python"), "-c", isolate], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == 0, out.stderr
    kept = json.loads(out.stdout)
    assert str(parent_site) not in kept, kept
    assert str(_purelib(child / "bin" / "python")) not in kept  # the child's own dropped too, as pip intends
