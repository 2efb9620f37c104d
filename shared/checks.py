"""Range checks for SI parameters, one wording everywhere: ``NAME must be a finite number > 0``.

Used by the dataclasses and functions that take physical parameters (stiffness, periods, rates,
sizes); each returns the value as a float so a caller can check and convert in one step.
"""

from __future__ import annotations

import math


def positive(name: str, value: float) -> float:
    """``value`` as a float if it is finite and > 0.

    Raises
    ------
    ValueError
        ``NAME must be a finite number > 0, got VALUE`` otherwise.
    """
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def nonneg(name: str, value: float) -> float:
    """``value`` as a float if it is finite and >= 0.

    Raises
    ------
    ValueError
        ``NAME must be a finite number >= 0, got VALUE`` otherwise.
    """
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def whole(name: str, value: int, minimum: int = 0) -> int:
    """``value`` as an int if it is a whole number >= ``minimum`` (a bool is not a number).

    Raises
    ------
    ValueError
        ``NAME must be a whole number >= MINIMUM, got VALUE`` otherwise.
    """
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)
