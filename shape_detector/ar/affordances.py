"""Horizontal top faces an agent can use: sit on, lie on, place things on.

World frame, z up, metres. A primitive offers its top face when one of its axes is within
``max_tilt`` of vertical, the face is large enough, and no other primitive of the same object
lies on most of it (a table's legs are covered by its top, a bed frame by its mattress).
Affordances come from the object's class, filtered by the face's height and size. Where the
object carries observed surface points on the face (the depth camera saw the top), the face's
height is the one measured (:func:`measured_height`), not the primitive's estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

from typing import Any

import numpy as np

from ..scene.types import SceneObject
from .scene_data import ArScene, load_scene

#: affordances per class, the first is the class's main use.
CLASS_AFFORDANCES: dict[str, tuple[str, ...]] = {
    "chair": ("sit",),
    "sofa": ("sit", "lie"),
    "bed": ("lie", "sit"),
    "table": ("place",),
    "desk": ("place",),
    "dresser": ("place",),
    "night_stand": ("place",),
    "bookshelf": ("place",),
}

#: (min height above floor, max height above floor, min side) in metres per affordance.
AFFORDANCE_LIMITS: dict[str, tuple[float, float, float]] = {
    "sit": (0.25, 0.8, 0.3),
    "lie": (0.15, 1.0, 0.6),
    "place": (0.15, 2.2, 0.1),
}


@dataclass
class Surface:
    """One usable top face: ``height`` (m, world z), ``polygon`` (K,2) world x, y corners
    counter-clockwise, ``affordance`` the main use, ``affordances`` all uses, ``area`` m²."""

    object_id: int
    class_name: str
    height: float
    polygon: np.ndarray
    affordance: str
    affordances: tuple[str, ...]
    primitive_index: int
    area: float


def _top_face(center: np.ndarray, half: np.ndarray, rot: np.ndarray, cos_tilt: float):
    """(height, polygon (4,2) ccw, side lengths (2,)) of a box's top face, or None if no axis is vertical."""
    up = rot[2, :]  # z component of each box axis
    k = int(np.argmax(np.abs(up)))
    if abs(up[k]) < cos_tilt:
        return None
    a, b = [i for i in range(3) if i != k]
    top = center + np.sign(up[k]) * half[k] * rot[:, k]
    ua, ub = rot[:, a] * half[a], rot[:, b] * half[b]
    poly = np.array([top + ua + ub, top - ua + ub, top - ua - ub, top + ua - ub])[:, :2]
    x, y = poly[:, 0], poly[:, 1]
    if np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)) < 0:
        poly = poly[::-1]
    return float(top[2]), poly, np.array([2 * half[a], 2 * half[b]])


def _covered_share(poly: np.ndarray, height: float, others: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                   gap: float, samples: int = 7, eps: float = 0.01) -> float:
    """Share of the face (sampled on a grid) under another box that reaches into the slab
    from ``eps`` to ``gap`` m above it (boxes merely level with the face do not cover it)."""
    s = (np.arange(samples) + 0.5) / samples
    u, v = np.meshgrid(s, s)
    p0, p1, p3 = poly[0], poly[1], poly[3]
    pts = p0 + u.reshape(-1, 1) * (p1 - p0) + v.reshape(-1, 1) * (p3 - p0)
    covered = np.zeros(len(pts), dtype=bool)
    for c, h, R in others:
        zext = float(np.abs(R[2]) @ h)
        if c[2] + zext <= height + eps or c[2] - zext >= height + gap:
            continue
        k = int(np.argmax(np.abs(R[2])))  # the box's most vertical axis; test the other two in the plane
        local = (pts - c[:2]) @ R[:2]
        covered |= np.all([np.abs(local[:, j]) <= h[j] for j in range(3) if j != k], axis=0)
    return float(covered.mean())


def measured_height(points: np.ndarray | None, polygon: np.ndarray, height: float, band: float = 0.08,
                    margin: float = 0.02, min_points: int = 8, layer: float = 0.02) -> float | None:
    """World z (m) of the horizontal face ``polygon`` (K,2, ccw) at about ``height`` as the
    observed ``points`` (M,3) show it: of the points over the polygon shrunk by ``margin``
    and within ``band`` of ``height``, the median of those within ``layer`` of their median
    (items standing on the face and edge points fall away); None with fewer than
    ``min_points`` of them."""
    if points is None or len(points) < min_points:
        return None
    c = polygon.mean(axis=0)
    inner = c + (polygon - c) * np.clip(1.0 - margin / np.maximum(np.linalg.norm(polygon - c, axis=1), 1e-9), 0, 1)[:, None]
    near = points[np.abs(points[:, 2] - height) <= band]
    z = near[_inside_convex(near[:, :2], inner), 2] if len(near) else near[:, 2]
    if len(z) < min_points:
        return None
    z = z[np.abs(z - np.median(z)) <= layer]
    return float(np.median(z)) if len(z) >= min_points else None


def _observed_near(scene: ArScene, obj: SceneObject, x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """The observed points to measure ``obj``'s faces on: its own (``SceneObject.surface``) or,
    from a live map, the map's points (columns ``x``, ``y``) over its box's footprint: a face's
    polygon and height band pick its share, so the split among all the boxes is not needed."""
    if obj.surface is not None or scene.observed is None:
        return obj.surface
    ext = 0.5 * np.abs(obj.rotation[:2]) @ obj.size
    (x0, y0), (x1, y1) = obj.center[:2] - ext, obj.center[:2] + ext
    return scene.observed[0][(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)]


def surfaces(scene: ArScene | Any, max_tilt_deg: float = 10.0, min_side: float = 0.1, cover_gap: float = 0.05,
             max_covered: float = 0.5, floor_z: float | None = None, measured: bool = True) -> list[Surface]:
    """Usable top faces of the scene's primitives (objects' boxes where they have none).

    A face is dropped when another box of the same object overlaps the thin slab from its
    top to ``cover_gap`` (m) above on more than ``max_covered`` of its area, when it lies
    mostly on a larger face of the object at the same height, when a side is under
    ``min_side`` (m), or when no affordance of its class fits its height and size. Heights
    count from ``floor_z`` (default: the scene's, see :class:`ArScene`); ``measured``: a face
    the camera saw takes its measured height (module doc). Sorted by object id, then height.
    """
    scene = load_scene(scene)
    b = scene.boxes
    if floor_z is None:
        floor_z = float(scene.floor_z or 0.0)
    cos_tilt = float(np.cos(np.radians(max_tilt_deg)))
    out: list[Surface] = []
    by_obj: dict[int, list[int]] = {}
    for i, oid in enumerate(b.object_ids):
        by_obj.setdefault(int(oid), []).append(i)
    seen: dict[int, np.ndarray | None] = {}
    shared = scene.observed[0] if measured and scene.observed is not None else np.zeros((0, 3))
    x, y = np.ascontiguousarray(shared[:, 0]), np.ascontiguousarray(shared[:, 1])
    for oid, idx in by_obj.items():
        obj = scene.object(oid)
        uses = CLASS_AFFORDANCES.get(obj.class_name if obj else "", ())
        if not uses:
            continue
        for i in idx:
            face = _top_face(b.centers[i], b.half[i], b.rot[i], cos_tilt)
            if face is None:
                continue
            height, poly, sides = face
            if sides.min() < min_side:
                continue
            if measured:
                if oid not in seen:
                    seen[oid] = _observed_near(scene, obj, x, y)
                z = measured_height(seen[oid], poly, height)
                height = height if z is None else z
            others = [(b.centers[j], b.half[j], b.rot[j]) for j in idx if j != i]
            if others and _covered_share(poly, height, others, cover_gap) > max_covered:
                continue
            above = height - floor_z
            fits = tuple(a for a in uses if AFFORDANCE_LIMITS[a][0] <= above <= AFFORDANCE_LIMITS[a][1]
                         and sides.min() >= AFFORDANCE_LIMITS[a][2])
            if not fits:
                continue
            out.append(Surface(oid, obj.class_name, height, poly, fits[0], fits, int(b.prim_index[i]),
                               float(sides[0] * sides[1])))
    out = _drop_level_duplicates(out)
    out.sort(key=lambda s: (s.object_id, s.height))
    return out


def _inside_convex(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(N,) bool: points (N,2) inside the counter-clockwise convex polygon (K,2)."""
    e = np.roll(poly, -1, axis=0) - poly
    rel = pts[:, None, :] - poly[None]
    return np.all(e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0] >= -1e-9, axis=1)


def _drop_level_duplicates(found: list[Surface], dz: float = 0.02, share: float = 0.5) -> list[Surface]:
    """Drop a face lying mostly (> ``share``) on a larger face of the same object within ``dz``
    m of its height (a pedestal level with the desk top above it is one surface)."""
    s = (np.arange(7) + 0.5) / 7
    u, v = (a.reshape(-1, 1) for a in np.meshgrid(s, s))
    keep = []
    for f in found:
        p0, p1, p3 = f.polygon[0], f.polygon[1], f.polygon[3]
        pts = p0 + u * (p1 - p0) + v * (p3 - p0)
        bigger = [g for g in found if g is not f and g.object_id == f.object_id and abs(g.height - f.height) <= dz
                  and (g.area, id(g)) > (f.area, id(f))]
        if not any(_inside_convex(pts, g.polygon).mean() > share for g in bigger):
            keep.append(f)
    return keep
