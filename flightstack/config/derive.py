"""Device and physics settings derived from the schema: no field-by-field copies.

A driver's or simulator's settings dataclass (e.g. flightstack.drivers.tello.TelloConfig,
flightstack.sim_backend.lab.TelloParams) is built from its schema section by field name, so a field added
to the section reaches the dataclass, and a section field the dataclass has no counterpart for is an
error at start-up (not a setting silently ignored).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from pydantic import BaseModel

T = TypeVar("T")


def derive(
    cls: type[T],
    spec: BaseModel,
    *,
    rename: Mapping[str, str] | None = None,
    skip: Iterable[str] = (),
    **extra: Any,
) -> T:
    """An instance of the dataclass `cls` from the schema section `spec`.

    Every field of `spec` goes to the field of `cls` with the same name (or the name `rename` gives it),
    except those in `skip` (consumed by the caller, e.g. converted and passed in `extra`). `extra` sets
    fields of `cls` that the section does not hold. Fields of `cls` that neither provides keep their
    defaults. Raises TypeError for a section field or an `extra` name with no field in `cls`.
    """
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    rename = dict(rename or {})
    skipped = set(skip)
    values: dict[str, Any] = {}
    for key in type(spec).model_fields:
        if key in skipped:
            continue
        target = rename.get(key, key)
        if target not in names:
            raise TypeError(f"{type(spec).__name__}.{key} has no field {target!r} in {cls.__name__}")
        values[target] = getattr(spec, key)
    unknown = set(extra) - names
    if unknown:
        raise TypeError(f"{cls.__name__} has no field(s) {sorted(unknown)}")
    values.update(extra)
    return cls(**values)
