"""Sphere-versus-scene collision: which boxes a sphere of ``radius`` touches.

World frame, metres. A broad phase hashes the boxes' world AABBs (grown by the radius) into
square floor cells; each point is tested exactly (oriented-box distance) only against the
boxes of its own cell, so a batch of thousands of points costs about as much as the pairs
near furniture.

With ``surfaces`` (the default) a sphere also collides with an object where it comes within
``radius`` of the object's observed surface points inside its box (``ArScene.contact_points``):
the depth measured the object there, where its fused box and primitives may fall a few
centimetres short.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .scene_data import ArScene, BoxSet, load_scene

#: side (m) of the broad-phase floor cells.
CELL = 0.25
#: side (m) of the cubes the observed surface points are bucketed in (at least the radius)
CONTACT_CELL = 0.1


def box_distances(points: np.ndarray, centers: np.ndarray, half: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Euclidean distance (m) from each point to its paired oriented box (0 inside).

    All arrays are paired row by row: ``points`` (K,3), ``centers`` (K,3), ``half`` (K,3),
    ``rot`` (K,3,3) columns = box axes in the world.
    """
    v = points - centers
    sq = np.zeros(len(v))
    for j in range(3):  # local coordinate j = v . (box axis j)
        lj = v[:, 0] * rot[:, 0, j] + v[:, 1] * rot[:, 1, j] + v[:, 2] * rot[:, 2, j]
        out = np.maximum(np.abs(lj) - half[:, j], 0.0)
        sq += out * out
    return np.sqrt(sq)


@dataclass
class _CellHash:
    """Boxes per floor cell: cell ``(i, j)`` of the grid at ``origin`` holds
    ``boxes[start[k]:start[k] + count[k]]`` with ``k = i * ny + j``; z bounds checked per pair."""

    origin: np.ndarray
    nx: int
    ny: int
    start: np.ndarray
    count: np.ndarray
    boxes: np.ndarray


def _build_hash(b: BoxSet, radius: float) -> _CellHash:
    lo, hi = b.lo[:, :2] - radius, b.hi[:, :2] + radius
    origin = lo.min(axis=0)
    i0 = np.floor((lo - origin) / CELL).astype(np.int64)
    i1 = np.floor((hi - origin) / CELL).astype(np.int64)
    nx, ny = int(i1[:, 0].max()) + 1, int(i1[:, 1].max()) + 1
    keys, owners = [], []
    for p in range(len(b)):
        ii, jj = np.meshgrid(np.arange(i0[p, 0], i1[p, 0] + 1), np.arange(i0[p, 1], i1[p, 1] + 1), indexing="ij")
        keys.append((ii * ny + jj).ravel())
        owners.append(np.full(ii.size, p))
    k = np.concatenate(keys)
    own = np.concatenate(owners)
    order = np.argsort(k, kind="stable")
    count = np.bincount(k, minlength=nx * ny)
    return _CellHash(origin, nx, ny, np.cumsum(count) - count, count, own[order])


def _per_size(scene: ArScene, name: str, size: float, build: Callable[[], Any]) -> Any:
    """``build()``'s result cached on ``scene`` under ``name`` per ``size`` (a radius or a cube
    side, metres; a few sizes kept)."""
    cache: dict[float, Any] = scene.__dict__.setdefault(name, {})
    key = round(float(size), 6)
    if key not in cache:
        if len(cache) > 8:
            cache.clear()
        cache[key] = build()
    return cache[key]


def _hash_for(scene: ArScene, radius: float) -> _CellHash:
    return _per_size(scene, "_collision_hash", radius, lambda: _build_hash(scene.boxes, radius))


def _candidates(scene: ArScene, pts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(point index, box index) pairs whose AABB grown by ``radius`` contains the point."""
    h = _hash_for(scene, radius)
    ij = np.floor((pts[:, :2] - h.origin) / CELL)
    inside = np.all(np.isfinite(ij), axis=1) & np.all(ij >= 0, axis=1) & (ij[:, 0] < h.nx) & (ij[:, 1] < h.ny)
    idx = np.nonzero(inside)[0]
    key = (ij[idx, 0] * h.ny + ij[idx, 1]).astype(np.int64)
    cnt = h.count[key]
    pi = np.repeat(idx, cnt)
    first = np.repeat(h.start[key] - (np.cumsum(cnt) - cnt), cnt)
    bi = h.boxes[first + np.arange(len(pi))]
    b = scene.boxes
    p = pts[pi]
    keep = np.all((p >= b.lo[bi] - radius) & (p <= b.hi[bi] + radius), axis=1)
    return pi[keep], bi[keep]


def _check(points: np.ndarray, radius: float) -> tuple[np.ndarray, float]:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 1:
        pts = pts[None]
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {np.shape(points)}")
    r = float(radius)
    if not np.isfinite(r) or r < 0:
        raise ValueError(f"radius={radius} must be finite and >= 0 (metres)")
    return pts, r


def touching_pairs(scene: ArScene | Any, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All (point index, box index) pairs with the sphere (``points`` (N,3), ``radius`` m)
    touching or overlapping the box; box indices refer to ``scene.boxes``."""
    scene = load_scene(scene)
    pts, r = _check(points, radius)
    boxes = scene.boxes
    if len(boxes) == 0 or len(pts) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pi, bi = _candidates(scene, pts, r)
    d = box_distances(pts[pi], boxes.centers[bi], boxes.half[bi], boxes.rot[bi])
    keep = d <= r
    return pi[keep], bi[keep]


def surface_contacts(scene: ArScene | Any, points: np.ndarray, radius: float) -> np.ndarray:
    """(N,) the id of an object whose observed surface points (inside its box) lie within
    ``radius`` (m) of each point, -1 where none does or the scene has none."""
    scene = load_scene(scene)
    pts, r = _check(points, radius)
    if scene.contact_points is None or len(pts) == 0:
        return np.full(len(pts), -1, np.int64)
    from .surface_contacts import build_contact_index, nearest_owner

    # cubes at least as large as the radius: a query looks into 27 of them, whatever the radius
    cell = max(CONTACT_CELL, r)
    index = _per_size(scene, "_contact_index", cell, lambda: build_contact_index(*scene.contact_points, cell=cell))
    return nearest_owner(index, pts, r)


def collides_many(scene: ArScene | Any, points: np.ndarray, radius: float = 0.0, surfaces: bool = True) -> np.ndarray:
    """(N,) bool: does a sphere of ``radius`` (m) at each world point touch any primitive (or,
    with ``surfaces``, come within ``radius`` of an object's observed surface)? Non-finite
    points never collide."""
    scene = load_scene(scene)
    pts, r = _check(points, radius)
    out = np.zeros(len(pts), dtype=bool)
    pi, _ = touching_pairs(scene, pts, r)
    out[pi] = True
    if surfaces and scene.contact_points is not None:
        rest = np.flatnonzero(~out)
        out[rest] = surface_contacts(scene, pts[rest], r) >= 0
    return out


def collides(scene: ArScene | Any, point: np.ndarray, radius: float = 0.0, surfaces: bool = True) -> bool:
    """Does a sphere of ``radius`` (m) at the world ``point`` (3,) touch any primitive (or, with
    ``surfaces``, an object's observed surface)?"""
    p = np.asarray(point, dtype=np.float64).reshape(-1)
    if p.shape != (3,):
        raise ValueError(f"point must have 3 coordinates, got {p.shape}")
    return bool(collides_many(scene, p[None], radius, surfaces)[0])


def contacts(scene: ArScene | Any, points: np.ndarray, radius: float = 0.0,
             surfaces: bool = True) -> list[tuple[int, int]]:
    """Distinct ``(object_id, primitive_index)`` the spheres touch, sorted; ``primitive_index``
    is -1 for an object without primitives (its box was tested) and, with ``surfaces``, for an
    object touched only at its observed surface."""
    scene = load_scene(scene)
    pts, r = _check(points, radius)
    pi, bi = touching_pairs(scene, pts, r)
    b = scene.boxes
    pairs = {(int(o), int(i)) for o, i in zip(b.object_ids[bi], b.prim_index[bi])}
    if surfaces:
        touched = set(np.unique(b.object_ids[bi]).tolist())
        found = surface_contacts(scene, pts, r)
        pairs |= {(int(o), -1) for o in np.unique(found[found >= 0]) if int(o) not in touched}
    return sorted(pairs)


def distance_to_scene(scene: ArScene | Any, points: np.ndarray, max_distance: float = 1.0) -> np.ndarray:
    """(N,) distance (m) from each point to the nearest box, capped at ``max_distance``."""
    scene = load_scene(scene)
    pts, cap = _check(points, max_distance)
    out = np.full(len(pts), cap)
    if len(scene.boxes) and len(pts):
        pi, bi = _candidates(scene, pts, cap)
        b = scene.boxes
        d = box_distances(pts[pi], b.centers[bi], b.half[bi], b.rot[bi])
        np.minimum.at(out, pi, d)
    return out
