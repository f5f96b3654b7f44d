"""Unlabelled clutter items: small things on surfaces, floor things, people, other furniture.

Models in the same local frame as :mod:`.furniture` (x front, y left, z up, floor at z = 0).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from . import textures as tx
from .furniture import cabinet_parts
from .parts import Model, frame_material


def _box(m: Model, rng: np.random.Generator) -> None:
    a, b, c = rng.uniform(0.15, 0.6, 3)
    mat = tx.Material(tx.PLAIN, tuple(np.clip(np.array([0.6, 0.45, 0.3]) * rng.uniform(0.7, 1.2), 0, 1)),
                      (0, 0, 0), 0.1, 0.0, 1.0, float(rng.uniform(0, 99))) if rng.random() < 0.6 else tx.colored(rng)
    m.add(-a / 2, a / 2, -b / 2, b / 2, 0, c, mat)
    if rng.random() < 0.4:
        a2, b2 = a * rng.uniform(0.5, 1), b * rng.uniform(0.5, 1)
        c2 = rng.uniform(0.1, 0.4)
        m.add(-a2 / 2, a2 / 2, -b2 / 2, b2 / 2, c, c + c2, tx.colored(rng))


def _small(m: Model, rng: np.random.Generator) -> None:
    """Cups, bottles, books, gadgets."""
    a, b = rng.uniform(0.04, 0.3, 2)
    c = rng.uniform(0.02, 0.3)
    m.add(-a / 2, a / 2, -b / 2, b / 2, 0, c, tx.colored(rng, spec=0.5) if rng.random() < 0.7 else tx.book(rng))


def _books(m: Model, rng: np.random.Generator) -> None:
    z = 0.0
    for _ in range(int(rng.integers(1, 6))):
        a, b, c = rng.uniform(0.15, 0.3), rng.uniform(0.1, 0.22), rng.uniform(0.01, 0.05)
        dx, dy = rng.normal(0, 0.02, 2)
        m.add(dx - a / 2, dx + a / 2, dy - b / 2, dy + b / 2, z, z + c, tx.book(rng))
        z += c


def _laptop(m: Model, rng: np.random.Generator) -> None:
    a, b = rng.uniform(0.22, 0.28), rng.uniform(0.3, 0.38)
    mat = tx.metal(rng)
    m.add(-a / 2, a / 2, -b / 2, b / 2, 0, 0.02, mat)
    m.add(-a / 2 - 0.01, -a / 2 + 0.005, -b / 2, b / 2, 0.02, 0.02 + a, mat)


def _monitor(m: Model, rng: np.random.Generator) -> None:
    a, b = rng.uniform(0.3, 0.45), rng.uniform(0.45, 0.7)
    mat = tx.metal(rng)
    m.add(-0.1, 0.1, -0.1, 0.1, 0, 0.015, mat)
    m.add(-0.06, -0.03, -0.03, 0.03, 0.015, 0.12, mat)
    m.add(-0.03, 0.0, -b / 2, b / 2, 0.1, 0.1 + a, tx.Material(tx.PLAIN, (0.04, 0.04, 0.05), (0, 0, 0), 0.1, 0.8, 0.3, 0.0))


def _lamp(m: Model, rng: np.random.Generator) -> None:
    bh = rng.uniform(0.25, 0.5)
    bm = tx.metal(rng) if rng.random() < 0.5 else tx.ceramic(rng)
    m.add(-0.07, 0.07, -0.07, 0.07, 0, 0.03, bm)
    m.add(-0.015, 0.015, -0.015, 0.015, 0.03, bh, bm)
    s = rng.uniform(0.12, 0.25)
    m.add(-s, s, -s, s, bh, bh + rng.uniform(0.15, 0.3), tx.emissive(rng, 0.9) if rng.random() < 0.4 else tx.fabric(rng))


def _floor_lamp(m: Model, rng: np.random.Generator) -> None:
    bh = rng.uniform(1.3, 1.8)
    bm = tx.metal(rng)
    m.add(-0.15, 0.15, -0.15, 0.15, 0, 0.03, bm)
    m.add(-0.015, 0.015, -0.015, 0.015, 0.03, bh, bm)
    s = rng.uniform(0.15, 0.25)
    m.add(-s, s, -s, s, bh, bh + rng.uniform(0.2, 0.35), tx.fabric(rng))


def _plant(m: Model, rng: np.random.Generator) -> None:
    ph = rng.uniform(0.15, 0.4)
    pr = rng.uniform(0.1, 0.2)
    m.add(-pr, pr, -pr, pr, 0, ph, tx.colored(rng) if rng.random() < 0.5 else tx.ceramic(rng))
    g = np.array([0.15, 0.35, 0.12])
    for _ in range(int(rng.integers(3, 8))):
        s = rng.uniform(0.08, 0.25)
        c = rng.normal(0, pr, 2)
        z = ph + rng.uniform(0, 0.5)
        m.add(c[0] - s, c[0] + s, c[1] - s, c[1] + s, z, z + s * rng.uniform(0.5, 1.5),
              tx.Material(tx.FABRIC, tuple(np.clip(g * rng.uniform(0.5, 1.5), 0, 1)), (0, 0, 0), 0.1, 0.1, 0.8,
                          float(rng.uniform(0, 99))))


def _bin(m: Model, rng: np.random.Generator) -> None:
    s = rng.uniform(0.2, 0.35)
    m.add(-s / 2, s / 2, -s / 2, s / 2, 0, rng.uniform(0.25, 0.5), tx.colored(rng, spec=0.3))


def _bag(m: Model, rng: np.random.Generator) -> None:
    a, b, c = rng.uniform(0.15, 0.3), rng.uniform(0.25, 0.45), rng.uniform(0.2, 0.5)
    m.add(-a / 2, a / 2, -b / 2, b / 2, 0, c, tx.fabric(rng))


def _person(m: Model, rng: np.random.Generator) -> None:
    H = rng.uniform(1.5, 1.92)
    sw = H * rng.uniform(0.22, 0.26)
    cloth = tx.fabric(rng)
    pants = tx.fabric(rng)
    skin = tx.Material(tx.PLAIN, tuple(np.clip(np.array([0.8, 0.6, 0.5]) * rng.uniform(0.35, 1.1), 0, 1)), (0, 0, 0),
                       0.1, 0.1, 0.6, 0.0)
    hair = tx.colored(rng, 0.02, 0.4)
    lh = H * 0.47
    m.add(-0.07, 0.07, -sw / 2 + 0.02, -0.02, 0, lh, pants)
    m.add(-0.07, 0.07, 0.02, sw / 2 - 0.02, 0, lh, pants)
    m.add(-0.11, 0.11, -sw / 2, sw / 2, lh, H * 0.82, cloth)
    m.add(-0.05, 0.05, -sw / 2 - 0.09, -sw / 2, H * 0.45, H * 0.8, cloth)
    m.add(-0.05, 0.05, sw / 2, sw / 2 + 0.09, H * 0.45, H * 0.8, cloth)
    m.add(-0.1, 0.1, -0.08, 0.08, H * 0.85, H, skin)
    m.add(-0.105, 0.08, -0.085, 0.085, H * 0.95, H + 0.01, hair)


def _rug(m: Model, rng: np.random.Generator) -> None:
    a, b = rng.uniform(0.8, 2.4), rng.uniform(0.6, 2.0)
    m.add(-a / 2, a / 2, -b / 2, b / 2, 0, rng.uniform(0.004, 0.015), tx.fabric(rng) if rng.random() < 0.5 else tx.floor(rng))


def _cabinet(m: Model, rng: np.random.Generator) -> None:
    """Unlabelled furniture: cabinets, wardrobes, tv stands."""
    l, w, h = rng.uniform(0.35, 0.65), rng.uniform(0.5, 1.6), rng.choice([rng.uniform(0.4, 0.9), rng.uniform(1.6, 2.2)])
    cabinet_parts(m, l, w, h, rng, int(rng.integers(1, 3)), int(rng.integers(1, 4)), frame_material(rng))
    m.labelled = False


def _tv(m: Model, rng: np.random.Generator) -> None:
    a, b = rng.uniform(0.5, 0.9), rng.uniform(0.8, 1.5)
    m.add(-0.15, 0.15, -0.25, 0.25, 0, 0.02, tx.metal(rng))
    m.add(-0.04, 0.0, -b / 2, b / 2, 0.05, 0.05 + a, tx.Material(tx.PLAIN, (0.03, 0.03, 0.035), (0, 0, 0), 0.1, 0.9, 0.15, 0.0))


def _ottoman(m: Model, rng: np.random.Generator) -> None:
    a, b, c = rng.uniform(0.4, 0.8), rng.uniform(0.4, 1.2), rng.uniform(0.35, 0.48)
    m.add(-a / 2, a / 2, -b / 2, b / 2, 0, c, tx.fabric(rng) if rng.random() < 0.6 else tx.leather(rng))


def _clothes(m: Model, rng: np.random.Generator) -> None:
    for _ in range(int(rng.integers(1, 4))):
        a, b = rng.uniform(0.2, 0.6, 2)
        dx, dy = rng.normal(0, 0.15, 2)
        m.add(dx - a / 2, dx + a / 2, dy - b / 2, dy + b / 2, 0, rng.uniform(0.02, 0.12), tx.fabric(rng))


def _sink(m: Model, rng: np.random.Generator) -> None:
    l, w, h = rng.uniform(0.4, 0.6), rng.uniform(0.5, 1.0), rng.uniform(0.78, 0.9)
    mat = frame_material(rng)
    m.add(-l / 2, l / 2 - 0.02, -w / 2, w / 2, 0, h - 0.04, mat)
    cer = tx.ceramic(rng)
    m.add(-l / 2, l / 2, -w / 2, w / 2, h - 0.04, h, cer)
    m.add(-l / 2, -l / 2 + 0.05, -0.02, 0.02, h, h + 0.25, tx.metal(rng))


def _radiator(m: Model, rng: np.random.Generator) -> None:
    w, h = rng.uniform(0.6, 1.4), rng.uniform(0.4, 0.7)
    mat = tx.paint(rng)
    for i in range(int(w / 0.06)):
        m.add(-0.05, 0.05, -w / 2 + i * 0.06, -w / 2 + i * 0.06 + 0.045, 0.1, 0.1 + h, mat)


_BUILDERS: dict[str, Callable[[Model, np.random.Generator], None]] = {
    "box": _box,
    "small": _small,
    "books": _books,
    "laptop": _laptop,
    "monitor": _monitor,
    "lamp": _lamp,
    "floor_lamp": _floor_lamp,
    "plant": _plant,
    "bin": _bin,
    "bag": _bag,
    "person": _person,
    "rug": _rug,
    "cabinet": _cabinet,
    "tv": _tv,
    "ottoman": _ottoman,
    "clothes": _clothes,
    "sink": _sink,
    "radiator": _radiator,
}

SURFACE_CLUTTER = ("small", "small", "small", "books", "laptop", "monitor", "lamp", "plant", "box", "clothes")
FLOOR_CLUTTER = ("box", "box", "bin", "bag", "person", "floor_lamp", "plant", "ottoman", "cabinet", "cabinet", "tv")


def clutter(kind: str, rng: np.random.Generator) -> Model:
    """An unlabelled item of ``kind`` (a key of the builders: ``box``, ``small``, ``rug`` ...)."""
    if kind not in _BUILDERS:
        raise ValueError(kind)
    m = Model(kind, labelled=False)
    _BUILDERS[kind](m, rng)
    return m
