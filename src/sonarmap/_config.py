"""Validation helpers shared by the frozen configuration dataclasses."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["is_finite_number"]


def is_finite_number(v: Any) -> bool:
    """True for a finite int or float (``bool`` is not a number here)."""
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
