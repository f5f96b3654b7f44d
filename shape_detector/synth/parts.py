"""Part models: furniture and clutter items as lists of axis-aligned cuboid parts.

The local frame of a model: x = the object's facing direction (front), y = left, z = up, the
footprint centred on the origin and the floor at ``z = 0``; lengths in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import textures as tx
from .textures import Material


@dataclass
class Part:
    """One axis-aligned cuboid part: min / max corners (3,) in the model's local frame (metres) and its material."""

    lo: np.ndarray  # (3,) min corner, local frame
    hi: np.ndarray  # (3,) max corner
    mat: Material


@dataclass
class Model:
    """A furniture / clutter model: parts in its local frame."""

    name: str
    parts: list[Part] = field(default_factory=list)
    labelled: bool = True
    #: heights (local z) of horizontal support surfaces that can carry clutter, with their
    #: x/y extents: (z, x0, x1, y0, y1)
    surfaces: list[tuple[float, float, float, float, float]] = field(default_factory=list)

    def add(self, x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, mat: Material) -> None:
        """Add the cuboid spanning the given local-frame ranges (metres, either order); degenerate (< 0.1 mm) parts are
        skipped."""
        lo = np.array([min(x0, x1), min(y0, y1), min(z0, z1)], dtype=np.float64)
        hi = np.array([max(x0, x1), max(y0, y1), max(z0, z1)], dtype=np.float64)
        if np.all(hi - lo > 1e-4):
            self.parts.append(Part(lo, hi, mat))
            self._bounds = None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Min / max corner of the parts (cached; call again after editing parts in place)."""
        b = getattr(self, "_bounds", None)
        if b is None or b[2] != len(self.parts):
            lo = np.min([p.lo for p in self.parts], axis=0)
            hi = np.max([p.hi for p in self.parts], axis=0)
            b = self._bounds = (lo, hi, len(self.parts))
        return b[0], b[1]


def frame_material(rng: np.random.Generator) -> Material:
    """A furniture frame material: mostly wood, else dull paint, metal or a flat colour."""
    r = rng.random()
    if r < 0.55:
        return tx.wood(rng)
    if r < 0.75:
        return tx.paint(rng, bright=False)
    if r < 0.9:
        return tx.metal(rng)
    return tx.colored(rng)


def legs4(m: Model, x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, t: float, mat: Material) -> None:
    """Add 4 square legs of side ``t`` (m) in the corners of the local rectangle ``[x0, x1] x [y0, y1]``, from z0 to z1."""
    for xa, xb in ((x0, x0 + t), (x1 - t, x1)):
        for ya, yb in ((y0, y0 + t), (y1 - t, y1)):
            m.add(xa, xb, ya, yb, z0, z1, mat)
