"""Checks of values from outside (a browser, a script): each returns the value the scene takes, or raises Refused
saying why. NaN and inf are refused everywhere."""
import math

import numpy as np

from sims.core.quoting import quote
from sims.scene import params


class Refused(ValueError):
    """A value from outside (a browser, a script) that the scene does not accept; the message says why."""


def finite_vector(value, length: int = 3, name: str = "value") -> np.ndarray:
    """value as a float64 vector of `length` finite numbers, or Refused."""
    try:
        vector = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise Refused(f"{name}: expected {length} numbers, got {quote(value)}") from None
    if vector.shape != (length,) or not np.isfinite(vector).all():
        raise Refused(f"{name}: expected {length} finite numbers, got {quote(value)}")
    return vector


def unit_direction(value, name: str = "direction") -> np.ndarray:
    """value as a unit vector of 3 finite numbers, or Refused (the zero vector too)."""
    vector = finite_vector(value, 3, name)
    length = float(np.linalg.norm(vector))
    if not length > 1e-9 or not math.isfinite(length):
        raise Refused(f"{name}: must be a finite, non-zero vector, got {quote(value)}")
    return vector / length


def checked_flag(value, name: str) -> bool:
    """value if it is true or false (a checkbox's value), or Refused (bool() would take any text or dict as true)."""
    if not isinstance(value, (bool, np.bool_)):
        raise Refused(f"{name}: must be true or false, got {quote(value)}")
    return bool(value)


def checked_number(spec: params.ParamSpec, value, clamp: bool = False) -> float | int:
    """value if the spec accepts it (clamped into its range with clamp=True; rounded for whole numbers), or Refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise Refused(f"{spec.name}: expected a number ({spec.unit}), got {quote(value)}")
    try:
        value = float(value)
    except OverflowError:  # an int beyond float's range (a 5,000-digit number from a browser)
        raise Refused(f"{spec.name}: must be finite, got {quote(value)}") from None
    if not math.isfinite(value):
        raise Refused(f"{spec.name}: must be finite, got {value}")
    if clamp:
        value = min(max(value, spec.min), spec.max)
    if spec.integer:
        value = int(round(value))
    problem = spec.check(value)
    if problem:
        raise Refused(f"{spec.name}: {problem}")
    return value
