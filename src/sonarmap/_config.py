"""Validation helpers shared by the frozen configuration dataclasses."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from sonarmap.errors import InputError

__all__ = ["is_finite_number", "config_table", "check_field_names", "config_error", "coerce_reals", "check_integers",
           "check_integer_argument", "check_booleans", "check_choice", "ConfigSection", "config_dict", "jsonable"]


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


def config_error(where: str, key: str, what: str, value: Any) -> InputError:
    """``InputError("<where><key>: <what> (got <value>)")``: the one message form of a bad option.

    ``where`` names the configuration and ends with its separator (``"track config: "``,
    ``"pipeline config: classify."``).
    """
    return InputError(f"{where}{key}: {what} (got {value!r})")


def coerce_reals(obj: Any, keys: tuple[str, ...], where: str, *, minimum: float | None = None) -> None:
    """Check that the fields ``keys`` of the frozen dataclass ``obj`` are finite numbers (and
    ``>= minimum`` when given) and store them as ``float``.

    Raises
    ------
    InputError
        Naming the first bad field (:func:`config_error`).
    """
    for key in keys:
        v = getattr(obj, key)
        if not is_finite_number(v) or (minimum is not None and v < minimum):
            what = "must be a finite number" + ("" if minimum is None else f" >= {minimum:g}")
            raise config_error(where, key, what, v)
        object.__setattr__(obj, key, float(v))


def check_integers(obj: Any, table: tuple[tuple[str, int], ...], where: str) -> None:
    """Check that every field ``key`` of ``(key, lo)`` in ``table`` is an integer (not a bool) >= ``lo``.

    Raises
    ------
    InputError
        "``<where><key>``: must be an integer >= lo (got ...)".
    """
    for key, lo in table:
        v = getattr(obj, key)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise config_error(where, key, f"must be an integer >= {lo}", v)


def check_integer_argument(name: str, value: Any, lo: int) -> None:
    """Check that a function's argument ``name`` is an integer (Python or numpy, not a bool) >= ``lo``.

    Raises
    ------
    InputError
        "``<name>``: must be an integer >= lo, got <value!r>".
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < lo:
        raise InputError(f"{name}: must be an integer >= {lo}, got {value!r}")


def check_booleans(obj: Any, keys: tuple[str, ...], where: str) -> None:
    """Check that the fields ``keys`` are ``True`` or ``False``."""
    for key in keys:
        v = getattr(obj, key)
        if not isinstance(v, bool):
            raise config_error(where, key, "must be true or false", v)


def check_choice(obj: Any, key: str, choices: tuple[str, ...], where: str) -> None:
    """Check that field ``key`` is one of ``choices`` ("must be 'a' or 'b'" / "must be one of a, b, c")."""
    v = getattr(obj, key)
    if v not in choices:
        what = (f"must be '{choices[0]}' or '{choices[1]}'" if len(choices) == 2
                else f"must be one of {', '.join(choices)}")
        raise config_error(where, key, what, v)


class ConfigSection:
    """Base of the frozen dataclasses that are the sections of :class:`sonarmap.config.PipelineConfig`
    (one per stage): the section's name, its message prefix and its (de)serialisation."""

    SECTION: ClassVar[str] = ""

    @property
    def _where(self) -> str:
        return f"pipeline config: {self.SECTION}."

    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-compatible dict of the section's options."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    @classmethod
    def from_dict(cls, d: Any) -> Any:
        """Build from a table; unknown keys or bad values raise :class:`InputError` naming the key."""
        return cls(**config_table(d, cls, f"pipeline config: {cls.SECTION}"))


def config_dict(config: Any) -> dict[str, Any]:
    """A configuration as a plain dict: its ``to_dict()``, a dataclass's fields, a mapping's items, else ``{"repr": ...}``."""
    if hasattr(config, "to_dict"):
        return dict(config.to_dict())
    if dataclasses.is_dataclass(config):
        return dataclasses.asdict(config)  # type: ignore[arg-type]
    if isinstance(config, Mapping):
        return dict(config)
    return {"repr": repr(config)}


def jsonable(obj: Any) -> Any:
    """``obj`` with every value JSON can hold: numpy arrays and scalars as lists and numbers, non-finite
    floats and other objects as their ``repr``, mapping keys as strings."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return repr(obj)
    if isinstance(obj, str | int | float | bool) or obj is None:
        return obj
    return repr(obj)
