"""Which object's observed surface points lie within a radius of a point (world frame, metres).

The points are bucketed in cubes of ``cell`` metres (sorted by the scene's voxel key); a query looks in
the cubes within the radius of the point and stops at the first point within it. The loop is
compiled with numba like :mod:`.surface_rays` (a query stops early, which array code cannot do
without testing every nearby point), and a batch is split over two cores (:mod:`.row_split`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..scene.surface import KEY_BITS, KEY_OFFSET, voxel_keys
from .row_split import run_rows


@dataclass
class ContactIndex:
    """Points (M,3) sorted by cube, their object ids (M,), the distinct cube keys (K,), where
    each cube's points start (K+1,) and the corners of their bounding box in it (K,3) x 2."""

    cell: float
    points: np.ndarray
    ids: np.ndarray
    keys: np.ndarray
    starts: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def build_contact_index(points: np.ndarray, ids: np.ndarray, cell: float) -> ContactIndex:
    """A :class:`ContactIndex` of world ``points`` (M,3, finite) owned by objects ``ids`` (M,)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    key = voxel_keys(np.floor(p / cell))
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else np.zeros(0, np.int64)
    p = np.ascontiguousarray(p[order])
    # each cube's points' bounding box: a query skips the cubes whose box lies beyond its radius
    lo = np.minimum.reduceat(p, first, axis=0) if len(first) else np.zeros((0, 3))
    hi = np.maximum.reduceat(p, first, axis=0) if len(first) else np.zeros((0, 3))
    return ContactIndex(float(cell), p, np.asarray(ids, np.int64)[order], key[first],
                        np.r_[first, len(key)].astype(np.int64), lo, hi)


def nearest_owner(index: ContactIndex, points: np.ndarray, radius: float) -> np.ndarray:
    """(N,) the object id of a point of ``index`` within ``radius`` (m) of each world point
    (N,3), -1 where none is (or the point is not finite). Looks into (2 ceil(radius / cell) +
    1)**3 cubes a point: keep the cubes at least as large as the radius."""
    pts = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    out = np.full(len(pts), -1, np.int64)
    reach = int(np.ceil(radius / index.cell))
    run_rows(lambda a, b: _owners(pts[a:b], float(radius), reach, index.cell, index.points, index.ids, index.keys,
                                  index.starts, index.lo, index.hi, out[a:b]), len(pts))
    return out


@numba.njit(cache=True, nogil=True)
def _owners(pts, r, reach, cell, points, ids, keys, starts, lo, hi, out):
    r2 = r * r
    for i in range(pts.shape[0]):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        ci, cj, ck = int(np.floor(x / cell)), int(np.floor(y / cell)), int(np.floor(z / cell))
        found = -1
        for di in range(-reach, reach + 1):
            for dj in range(-reach, reach + 1):
                # the cubes of one (i, j) column are consecutive keys: one search, then a walk up
                column = ((ci + di + KEY_OFFSET) << (2 * KEY_BITS)) | ((cj + dj + KEY_OFFSET) << KEY_BITS)
                last = column | (ck + reach + KEY_OFFSET)
                j = np.searchsorted(keys, column | (ck - reach + KEY_OFFSET))
                while j < keys.shape[0] and keys[j] <= last and found < 0:
                    gap = 0.0
                    for a, v in ((0, x), (1, y), (2, z)):
                        g = max(lo[j, a] - v, v - hi[j, a], 0.0)
                        gap += g * g
                    if gap <= r2:
                        for q in range(starts[j], starts[j + 1]):
                            dx, dy, dz = points[q, 0] - x, points[q, 1] - y, points[q, 2] - z
                            if dx * dx + dy * dy + dz * dz <= r2:
                                found = ids[q]
                                break
                    j += 1
                if found >= 0:
                    break
            if found >= 0:
                break
        out[i] = found
