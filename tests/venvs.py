"""Virtual environments that tests build: the one way to make a venv that imports what this one does.

A test that builds a venv runs inside the venv the README makes (and `.ci/run` makes, or is run in). A plain
`python -m venv --system-site-packages` made from there sees the *base* interpreter's packages, not this
venv's, so it cannot import flightstack or its dependencies. `venv_seeing_this_environment` adds this
environment's site directories to the new venv with `site.addsitedir` (which also runs their .pth files:
an editable install's finder), after the new venv's own site-packages. `.ci/venv-here` is the same rule
for the shell scripts. tests/test_venv_builders.py holds every venv a test builds to one of the two.
"""

from __future__ import annotations

import site
import subprocess
import sys
from pathlib import Path

VENV_TIMEOUT_S = 120.0
"""Bound on `python -m venv --without-pip` on a loaded 2-core machine (s)."""


def this_environments_site_dirs() -> list[str]:
    """The site-packages directories of the running interpreter's environment (a venv's or the system's)."""
    return [p for p in site.getsitepackages() if Path(p).is_dir()]


def site_packages(venv: Path) -> Path:
    """The venv's own site-packages (purelib) directory."""
    return venv / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"


def bare_venv(venv: Path) -> Path:
    """A venv (no pip) made from this interpreter that sees no other environment: the caller adds what it
    needs (a `.pth` of its own). Returns `venv`."""
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=VENV_TIMEOUT_S
    )
    return venv


def venv_seeing_this_environment(venv: Path) -> Path:
    """A venv (no pip) at `venv` that imports every package this environment imports, editable installs
    included, with its own site-packages first on sys.path (what it installs shadows ours). Returns `venv`."""
    bare_venv(venv)
    pth = "".join(f"import site; site.addsitedir({p!r})\n" for p in this_environments_site_dirs())
    (site_packages(venv) / "zz_this_environment.pth").write_text(pth)
    return venv
