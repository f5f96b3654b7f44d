"""The room's walls: thin cuboids outside the room rectangle, split around doors, windows
and recesses, with trim, curtains, pictures and wall shelves.

Wall ``k`` (0..3) runs counter-clockwise from a room corner; along it ``s`` is the distance
from its origin, ``d`` the distance into the room along its inward normal (walls occupy
``d < 0``), ``z`` the height above the floor. Random draws happen in a fixed order, so a
seed gives the same room whatever code reads it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import textures as tx
from .scene_types import Scene, Static
from .textures import Material

#: wall thickness (m)
THICKNESS = 0.15

#: an opening in a wall: (s0, s1, z0, z1, kind) with kind "door", "window" or "recess"
Opening = tuple[float, float, float, float, str]


def wall_frame(k: int, rx: float, ry: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Wall ``k``'s origin (2,), direction along it (2,), inward normal (2,) and length (m)."""
    origin = [np.array([0.0, 0.0]), np.array([rx, 0.0]), np.array([rx, ry]), np.array([0.0, ry])][k]
    along = [np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), np.array([0.0, -1.0])][k]
    normal = np.array([-along[1], along[0]])
    length = rx if k % 2 == 0 else ry
    return origin, along, normal, length


def wall_box(k: int, rx: float, ry: float, s0: float, s1: float, d0: float, d1: float, z0: float, z1: float,
             mat: Material) -> Static:
    """The cuboid spanning ``[s0, s1] x [d0, d1] x [z0, z1]`` in wall ``k``'s coordinates."""
    origin, along, normal, _ = wall_frame(k, rx, ry)
    sc, dc, zc = 0.5 * (s0 + s1), 0.5 * (d0 + d1), 0.5 * (z0 + z1)
    c2 = origin + sc * along + dc * normal
    R = np.stack([np.array([along[0], along[1], 0.0]), np.array([normal[0], normal[1], 0.0]), np.array([0, 0, 1.0])],
                 axis=1)
    return Static(np.array([c2[0], c2[1], zc]), np.array([abs(s1 - s0), abs(d1 - d0), abs(z1 - z0)]), R, mat)


@dataclass
class _Wall:
    """One wall being built: where its boxes go and the materials shared along it."""

    sc: Scene
    k: int
    length: float
    mat: Material
    trim: Material

    def box(self, s0: float, s1: float, d0: float, d1: float, z0: float, z1: float, mat: Material) -> None:
        self.sc.structure.append(wall_box(self.k, self.sc.rx, self.sc.ry, s0, s1, d0, d1, z0, z1, mat))


def _openings(w: _Wall, rng: np.random.Generator, has_door: bool, has_windows: bool) -> list[Opening]:
    """The wall's door, windows and recess (non-overlapping), sorted along the wall."""
    L, H = w.length, w.sc.height
    ops: list[Opening] = []
    if has_door and L > 1.4:
        dw = rng.uniform(0.75, 1.0)
        s0 = rng.uniform(0.1, L - dw - 0.1)
        ops.append((s0, s0 + dw, 0.0, rng.uniform(2.0, min(2.2, H - 0.1)), "door"))
    if has_windows:
        for _ in range(int(rng.integers(1, 3))):
            ww = rng.uniform(0.6, min(2.2, L - 0.4))
            s0 = rng.uniform(0.2, L - ww - 0.2)
            z0 = rng.uniform(0.75, 1.1)
            z1 = min(H - 0.15, z0 + rng.uniform(0.9, 1.5))
            if all(s0 > o[1] + 0.15 or s0 + ww < o[0] - 0.15 for o in ops):
                ops.append((s0, s0 + ww, z0, z1, "window"))
    if rng.random() < 0.12 and L > 2.0:
        rw = rng.uniform(0.6, min(1.8, L - 0.6))
        s0 = rng.uniform(0.2, L - rw - 0.2)
        if all(s0 > o[1] + 0.1 or s0 + rw < o[0] - 0.1 for o in ops):
            ops.append((s0, s0 + rw, 0.0, H if rng.random() < 0.5 else rng.uniform(1.9, H - 0.1), "recess"))
    ops.sort(key=lambda o: o[0])
    return ops


def _door(w: _Wall, rng: np.random.Generator, s0: float, s1: float, z1: float) -> None:
    T, H = THICKNESS, w.sc.height
    if rng.random() < 0.75:  # closed door
        dm = tx.wood(rng) if rng.random() < 0.5 else tx.paint(rng)
        w.box(s0, s1, -0.08, -0.04, 0.0, z1, dm)
        hs = s0 + 0.08 if rng.random() < 0.5 else s1 - 0.08
        w.box(hs - 0.06, hs + 0.06, -0.04, 0.02, 0.95, 1.0, tx.metal(rng))
    else:  # open: a corridor behind
        cd = rng.uniform(1.0, 3.0)
        cm = tx.wall(rng)
        w.box(s0 - 1.0, s1 + 1.0, -T - cd - 0.1, -T - cd, 0.0, H, cm)
        w.box(s0 - 0.1, s0, -T - cd, -T, 0.0, H, cm)
        w.box(s1, s1 + 0.1, -T - cd, -T, 0.0, H, cm)
    fw = rng.uniform(0.04, 0.09)
    w.box(s0 - fw, s0, 0.0, 0.015, 0.0, z1 + fw, w.trim)
    w.box(s1, s1 + fw, 0.0, 0.015, 0.0, z1 + fw, w.trim)
    w.box(s0, s1, 0.0, 0.015, z1, z1 + fw, w.trim)


def _curtains(w: _Wall, rng: np.random.Generator, s0: float, s1: float, z0: float, z1: float) -> None:
    cm = tx.fabric(rng)
    cw = rng.uniform(0.2, 0.5)
    ctop = min(w.sc.height - 0.02, z1 + rng.uniform(0.05, 0.3))
    cbot = rng.uniform(0.02, z0) if rng.random() < 0.5 else z0 - 0.05
    for a in (s0 - cw * 0.5, s1 - cw * 0.5):
        nf = int(rng.integers(2, 5))
        for i in range(nf):
            dd = 0.03 + 0.03 * (i % 2)
            w.box(a + i * cw / nf, a + (i + 1) * cw / nf, dd, dd + 0.02, cbot, ctop, cm)


def _window(w: _Wall, rng: np.random.Generator, s0: float, s1: float, z0: float, z1: float) -> None:
    T = THICKNESS
    w.box(s0, s1, -T * 0.6, -T * 0.5, z0, z1, tx.glass(rng))
    fm = tx.paint(rng) if rng.random() < 0.7 else tx.metal(rng)
    f = 0.05
    for a, b, c, d in ((s0, s1, z0, z0 + f), (s0, s1, z1 - f, z1), (s0, s0 + f, z0, z1), (s1 - f, s1, z0, z1)):
        w.box(a, b, -T * 0.7, -T * 0.4, c, d, fm)
    if s1 - s0 > 1.0:
        sm = 0.5 * (s0 + s1)
        w.box(sm - f / 2, sm + f / 2, -T * 0.7, -T * 0.4, z0, z1, fm)
    w.box(s0 - 0.05, s1 + 0.05, -0.02, rng.uniform(0.02, 0.07), z0 - 0.03, z0, w.trim)
    if rng.random() < 0.5:
        _curtains(w, rng, s0, s1, z0, z1)
    if w.sc.sun is None and rng.random() < 0.6:
        n = wall_frame(w.k, w.sc.rx, w.sc.ry)[2]
        sun_dir = np.array([n[0] + rng.normal(0, 0.4), n[1] + rng.normal(0, 0.4), -rng.uniform(0.3, 1.0)])
        w.sc.sun = (sun_dir / np.linalg.norm(sun_dir), float(rng.uniform(0.2, 0.6)))


def _recess(w: _Wall, rng: np.random.Generator, s0: float, s1: float, z1: float) -> None:
    T, H = THICKNESS, w.sc.height
    dep = rng.uniform(0.3, 0.8)
    rm = w.mat if rng.random() < 0.7 else tx.wall(rng)
    w.box(s0 - T, s1 + T, -dep - T, -dep, 0.0, H, rm)
    w.box(s0 - T, s0, -dep, 0.0, 0.0, H, w.mat)
    w.box(s1, s1 + T, -dep, 0.0, 0.0, H, w.mat)
    if z1 < H:
        w.box(s0, s1, -dep, 0.0, z1, z1 + 0.02, w.mat)


def _solid_and_openings(w: _Wall, rng: np.random.Generator, ops: list[Opening]) -> None:
    """The wall's solid segments, the lintels and sills around each opening, and the opening."""
    T, H = THICKNESS, w.sc.height
    s = -T
    for s0, s1, z0, z1, kind in ops:
        w.box(s, s0, -T, 0.0, 0.0, H, w.mat)
        if z0 > 0:
            w.box(s0, s1, -T, 0.0, 0.0, z0, w.mat)
        if z1 < H:
            w.box(s0, s1, -T, 0.0, z1, H, w.mat)
        w.sc.openings.append((w.k, s0, s1, z0, z1, kind))
        if kind == "door":
            _door(w, rng, s0, s1, z1)
        elif kind == "window":
            _window(w, rng, s0, s1, z0, z1)
        elif kind == "recess":
            _recess(w, rng, s0, s1, z1)
        s = s1
    w.box(s, w.length + T, -T, 0.0, 0.0, H, w.mat)


def _baseboards(w: _Wall, rng: np.random.Generator, ops: list[Opening]) -> None:
    """Baseboards along the solid parts (interrupted by doors and recesses)."""
    if rng.random() < 0.7:
        bh = rng.uniform(0.05, 0.12)
        s = 0.0
        for s0, s1, _z0, _z1, kind in [*ops, (w.length, w.length, 0, 0, "end")]:
            if kind in ("door", "recess", "end"):
                if s0 > s + 0.01:
                    w.box(s, s0, 0.0, 0.012, 0.0, bh, w.trim)
                s = s1


def _shelf_with_books(w: _Wall, rng: np.random.Generator, s0: float, pw: float, zc: float) -> None:
    sm = tx.wood(rng)
    w.box(s0, s0 + pw, 0.0, 0.25, zc, zc + 0.025, sm)
    b = s0 + 0.05
    while b < s0 + pw - 0.1:
        bt = rng.uniform(0.02, 0.05)
        w.box(b, b + bt, 0.02, rng.uniform(0.15, 0.22), zc + 0.025, zc + 0.025 + rng.uniform(0.15, 0.25), tx.book(rng))
        b += bt + rng.uniform(0.0, 0.1)


def _decor(w: _Wall, rng: np.random.Generator, ops: list[Opening]) -> None:
    """Pictures, boards and shelves hung on the wall, clear of its openings."""
    L, H = w.length, w.sc.height
    for _ in range(int(rng.integers(0, 4))):
        pw, ph = rng.uniform(0.25, 1.2), rng.uniform(0.25, 0.9)
        if L < pw + 0.4:
            continue
        s0 = rng.uniform(0.2, L - pw - 0.2)
        zc = rng.uniform(1.2, min(1.9, H - ph / 2 - 0.1))
        if any(s0 < o[1] + 0.05 and s0 + pw > o[0] - 0.05 for o in ops):
            continue
        r = rng.random()
        if r < 0.6:  # a framed picture
            frame = tx.wood(rng) if rng.random() < 0.5 else tx.colored(rng)
            w.box(s0, s0 + pw, 0.0, 0.02, zc - ph / 2, zc + ph / 2, frame)
            w.box(s0 + 0.04, s0 + pw - 0.04, 0.02, 0.025, zc - ph / 2 + 0.04, zc + ph / 2 - 0.04, tx.colored(rng))
        elif r < 0.8:  # a white board
            w.box(s0, s0 + pw * 1.5 if s0 + pw * 1.5 < L else s0 + pw, 0.0, 0.02, zc - ph / 2, zc + ph / 2,
                  tx.Material(tx.PLAIN, (0.95, 0.95, 0.95), (0, 0, 0), 0.1, 0.6, 0.9, 0.0))
        else:
            _shelf_with_books(w, rng, s0, pw, zc)


def build_walls(sc: Scene, rng: np.random.Generator, bathroom: bool) -> None:
    """Add the four walls with their openings and decoration to ``sc.structure``
    (openings to ``sc.openings``, sunlight through a window to ``sc.sun``)."""
    wall_mat = tx.wall(rng, bathroom)
    accent = tx.wall(rng, bathroom) if rng.random() < 0.25 else wall_mat
    trim = tx.paint(rng) if rng.random() < 0.7 else tx.wood(rng)
    door_wall = int(rng.integers(4)) if rng.random() < 0.8 else -1
    win_walls = [k for k in range(4) if rng.random() < 0.35]
    for k in range(4):
        w = _Wall(sc, k, wall_frame(k, sc.rx, sc.ry)[3], accent if k == 1 else wall_mat, trim)
        ops = _openings(w, rng, k == door_wall, k in win_walls)
        _solid_and_openings(w, rng, ops)
        _baseboards(w, rng, ops)
        _decor(w, rng, ops)
