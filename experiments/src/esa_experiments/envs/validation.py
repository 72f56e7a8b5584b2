"""Argument checks that raise ``ValueError("expected ..., got ...")``."""

from __future__ import annotations

import math
import numbers


def require(condition: bool, expected: str, got: object) -> None:
    """Raise ``ValueError(f"expected {expected}, got {got!r}")`` unless ``condition`` holds."""
    if not condition:
        raise ValueError(f"expected {expected}, got {got!r}")


def is_real(value: object) -> bool:
    """Return whether ``value`` is a real number (numpy scalars included), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def require_positive(name: str, value: float) -> float:
    """Check that ``value`` is a finite number > 0 and return it as a float."""
    require(is_real(value) and math.isfinite(value) and value > 0, f"{name} > 0", value)
    return float(value)


def require_non_negative(name: str, value: float) -> float:
    """Check that ``value`` is a finite number >= 0 and return it as a float."""
    require(is_real(value) and math.isfinite(value) and value >= 0, f"{name} >= 0", value)
    return float(value)
