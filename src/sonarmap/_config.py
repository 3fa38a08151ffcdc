"""Validation helpers shared by the frozen configuration dataclasses."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from sonarmap.errors import InputError

__all__ = ["is_finite_number", "config_table", "check_field_names"]


def is_finite_number(v: Any) -> bool:
    """True for a finite int or float (``bool`` is not a number here)."""
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)


def _field_names(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def config_table(d: Any, cls: type, what: str, *, section: str | None = None,
                 expected: str = "a table") -> dict[str, Any]:
    """The keys of a configuration table for the dataclass ``cls``, checked.

    ``d`` must be a dict (else "``what``: expected ``expected``, got <type>"); a table holding only
    ``{section: {...}}`` (as in a TOML file) is unwrapped; a key that is not a field of ``cls``
    raises "``what``: unknown key 'k' (valid: ...)".

    Raises
    ------
    InputError
        As above.
    """
    if not isinstance(d, dict):
        raise InputError(f"{what}: expected {expected}, got {type(d).__name__}")
    if section is not None and set(d) == {section} and isinstance(d[section], dict):
        d = d[section]
    known = _field_names(cls)
    for key in d:
        if key not in known:
            raise InputError(f"{what}: unknown key '{key}' (valid: {', '.join(sorted(known))})")
    return d


def check_field_names(d: Mapping[str, Any], cls: type, name: str) -> None:
    """Raise "``name``.k: unknown key (expected [...])" for a key of ``d`` that ``cls`` lacks.

    The form of the serialised results (a calibration's ``radial_gain``, a recording's
    ``background``), whose fields are named with their dotted path.
    """
    known = _field_names(cls)
    for key in d:
        if key not in known:
            raise InputError(f"{name}.{key}: unknown key (expected {sorted(known)})")
