"""Option checks shared by the node's parameters and the command-line tools: each returns
an error text naming the option and the accepted values, or None when the value is fine."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any


def check_choice(name: str, value: Any, choices: Sequence[Any]) -> str | None:
    """``value`` must be one of ``choices``."""
    if value not in choices:
        return f"{name} must be one of {tuple(choices)}, got {value!r}"
    return None


def check_number(name: str, value: Any, lo: float | None = None, hi: float | None = None,
                 integer: bool = False) -> str | None:
    """``value`` must be a finite number (an integer if ``integer``) in ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        return f"{name} must be {'an integer' if integer else 'a number'}, got {value!r}"
    if not math.isfinite(value):
        return f"{name} must be finite, got {value!r}"
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        return f"{name} must be in [{lo}, {hi}], got {value!r}"
    return None


def check_vector(name: str, value: Any, length: int, nonzero: bool = True) -> str | None:
    """``value`` must be ``length`` finite numbers (not all zero if ``nonzero``)."""
    try:
        v = [float(x) for x in value]
    except (TypeError, ValueError):
        return f"{name} must be {length} numbers, got {value!r}"
    if len(v) != length or not all(math.isfinite(x) for x in v):
        return f"{name} must be {length} finite numbers, got {list(v)}"
    if nonzero and math.sqrt(sum(x * x for x in v)) < 1e-9:
        return f"{name} must not be all zero, got {list(v)}"
    return None
