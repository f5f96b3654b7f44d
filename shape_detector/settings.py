"""Declaring settings once: a dataclass field carries its default, valid values and doc.

:func:`setting` builds such a field; :func:`specs` reads them back as :class:`Spec` for the
node's parameter descriptors, the command-line flags, ``config/detector.yaml`` and
``docs/parameters.md``, and :func:`check` validates a value against its spec with the reason.
Pure Python: no ROS, no torch.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from .validation import check_choice, check_number, check_vector

#: how the live node treats a parameter: changed at run time, rebuilds the detector, fixed at start
NODE_MODES = ("dynamic", "rebuild", "read_only")


@dataclass(frozen=True)
class Spec:
    """One setting: ``name``, ``default``, one-line ``doc``, valid ``choices`` or numeric
    ``range`` (inclusive; ``hi_open`` excludes the upper end), ``length`` for vectors, and
    ``node``: how the live node treats it (one of :data:`NODE_MODES`)."""

    name: str
    default: Any
    doc: str
    choices: tuple[Any, ...] | None = None
    range: tuple[float, float] | None = None
    hi_open: bool = False
    length: int | None = None
    node: str = "read_only"

    @property
    def kind(self) -> type:
        """The value's Python type (bool, int, float, str, list)."""
        return type(self.default)


def setting(default: Any, doc: str, *, choices: tuple[Any, ...] | None = None,
            range: tuple[float, float] | None = None, hi_open: bool = False,  # noqa: A002
            length: int | None = None, node: str = "read_only") -> Any:
    """A dataclass field declaring a setting (see :class:`Spec`)."""
    if node not in NODE_MODES:
        raise ValueError(f"node must be one of {NODE_MODES}, got {node!r}")
    meta = {"doc": doc, "choices": choices, "range": range, "hi_open": hi_open, "length": length, "node": node}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


def specs(cls_or_obj: Any) -> dict[str, Spec]:
    """name -> :class:`Spec` of every setting of a dataclass declared with :func:`setting`;
    defaults are the instance's values when given an instance."""
    out: dict[str, Spec] = {}
    for f in dataclasses.fields(cls_or_obj):
        if "doc" not in f.metadata:
            continue
        if not isinstance(cls_or_obj, type):
            default = getattr(cls_or_obj, f.name)
        elif f.default is not dataclasses.MISSING:
            default = f.default
        else:
            default = f.default_factory()  # type: ignore[misc]
        out[f.name] = Spec(name=f.name, default=default, **dict(f.metadata))
    return out


def check(spec: Spec, value: Any) -> str | None:
    """Why ``value`` is not acceptable for ``spec``; None when it is."""
    if spec.choices is not None:
        return check_choice(spec.name, value, spec.choices)
    if spec.length is not None:
        return check_vector(spec.name, value, spec.length)
    if spec.kind is bool:
        return None if isinstance(value, bool) else f"{spec.name} must be true or false, got {value!r}"
    if spec.kind in (int, float):
        lo, hi = spec.range if spec.range is not None else (None, None)
        integer = spec.kind is int
        if not integer and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        problem = check_number(spec.name, value, lo, hi, integer=integer)
        if problem is None and spec.hi_open and hi is not None and value >= hi:
            problem = f"{spec.name} must be in [{lo}, {hi}), got {value!r}"
        return problem
    if spec.kind is str and not isinstance(value, str):
        return f"{spec.name} must be a string, got {value!r}"
    return None


def coerce(spec: Spec, value: Any) -> Any:
    """``value`` in the spec's type (ints for floats, lists for vectors) once :func:`check` passed."""
    if spec.kind is float and not isinstance(value, bool):
        return float(value)
    if spec.length is not None:
        return [float(v) for v in value]
    return value


def valid_values(spec: Spec) -> str:
    """The valid values in words, for docs and help texts."""
    if spec.choices is not None:
        return ", ".join(str(c) for c in spec.choices)
    if spec.range is not None:
        lo, hi = spec.range
        return f"[{lo}, {hi}{')' if spec.hi_open else ']'}"
    if spec.length is not None:
        return f"{spec.length} numbers"
    if spec.kind is bool:
        return "true, false"
    return "text"
