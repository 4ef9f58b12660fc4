"""The one place that imports rerun (lazily): a clear error naming the extra when it is missing."""

from __future__ import annotations

import logging
from types import ModuleType

PINNED_VERSION = "0.41.0"
"""The rerun-sdk version of pyproject.toml's `viewer` extra (its read-back API is used by the tests)."""

INSTALL_HINT = "pip install 'flightstack[viewer]'"

_log = logging.getLogger(__name__)


class ViewerUnavailable(RuntimeError):  # noqa: N818  (a condition, not a programming error)
    """rerun-sdk cannot be imported; the message says how to install it."""


def load_rerun() -> ModuleType:
    """The `rerun` module; ViewerUnavailable naming `pip install 'flightstack[viewer]'` when it cannot be
    imported. A version other than PINNED_VERSION is used with a warning (its API may differ)."""
    try:
        import rerun
    except ImportError as exc:
        raise ViewerUnavailable(
            f"the 3-D viewer needs rerun-sdk {PINNED_VERSION}, which is not importable ({exc}); "
            f"install it with: {INSTALL_HINT}"
        ) from None
    found = getattr(rerun, "__version__", "unknown")
    if found != PINNED_VERSION:
        _log.warning(
            "rerun-sdk %s found, flightstack is tested with %s (%s)", found, PINNED_VERSION, INSTALL_HINT
        )
    return rerun
