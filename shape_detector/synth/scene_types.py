"""The generated room's data: placed models, static structure (walls, doors, windows), lights.

World frame: z up, floor at ``z = 0``, the room spans ``[0, rx] x [0, ry]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .furniture import Model
from .textures import Material


def rotz(a: float) -> np.ndarray:
    """3x3 rotation about z by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Placed:
    """A model at a world pose (yaw about z, local origin at ``pos``)."""

    model: Model
    pos: np.ndarray
    yaw: float

    def footprint(self) -> tuple[np.ndarray, np.ndarray, float]:
        """World footprint rectangle: centre (x, y) m, half extents (2,) m along the model's axes, yaw (rad)."""
        lo, hi = self.model.bounds()
        c_local = 0.5 * (lo + hi)
        c = self.pos + rotz(self.yaw) @ c_local
        return c[:2], 0.5 * (hi - lo)[:2], self.yaw

    def top(self) -> float:
        """World height (z, m) of the model's top."""
        return float(self.pos[2] + self.model.bounds()[1][2])

    def cuboids(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Material]]:
        """World cuboids of the parts: centres (n,3), sizes (n,3), rotation (3,3), materials."""
        R = rotz(self.yaw)
        lo = np.array([p.lo for p in self.model.parts])
        hi = np.array([p.hi for p in self.model.parts])
        centers = (0.5 * (lo + hi)) @ R.T + self.pos
        return centers, hi - lo, R, [p.mat for p in self.model.parts]


@dataclass
class Static:
    """A static structure cuboid (wall, door, window, ...): world centre (3,) m, full size (3,) m, rotation (3,3),
    material."""

    center: np.ndarray
    size: np.ndarray
    R: np.ndarray
    mat: Material


@dataclass
class Scene:
    """A generated room: extent ``rx x ry`` m, ceiling height m, room type, structure, labelled objects, clutter,
    lights."""

    rx: float
    ry: float
    height: float
    room_type: str
    structure: list[Static] = field(default_factory=list)
    objects: list[Placed] = field(default_factory=list)  # labelled
    clutter: list[Placed] = field(default_factory=list)
    #: point lights: (position (3,), intensity, rgb (3,))
    lights: list[tuple[np.ndarray, float, np.ndarray]] = field(default_factory=list)
    ambient: float = 0.35
    sun: tuple[np.ndarray, float] | None = None  # (direction the light travels, intensity)
    openings: list[tuple[int, float, float, float, float, str]] = field(default_factory=list)
