"""Checks of controller and scenario parameters: one clear ValueError naming the field."""
from __future__ import annotations

import math


def is_finite_number(x) -> bool:
    """A real number (not a bool) that is finite."""
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)


def positive(obj, *names) -> None:
    for name in names:
        v = getattr(obj, name)
        if not is_finite_number(v) or v <= 0:
            raise ValueError(f"{name} must be a positive finite number, got {v!r}")


def integer(obj, name, low) -> None:
    v = getattr(obj, name)
    if not is_finite_number(v) or int(v) != v or v < low:  # finite first: int() of inf or NaN raises its own error
        raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")


def probability(obj, name) -> None:
    v = getattr(obj, name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1:
        raise ValueError(f"{name} must lie in [0, 1], got {v!r}")
