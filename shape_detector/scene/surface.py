"""Observed surfaces of the scene: depth points averaged into voxels, world frame (z up, metres).

The detector's boxes and primitives are a few centimetres off; the depth the camera measured
is not. :class:`SurfaceMemory` keeps the mean of the depth points that fall into each
``voxel``-sized cube (one point per occupied voxel), over every frame, so that ray casts can
land on the surface the camera saw (:mod:`shape_detector.ar.surface_rays`). What belongs to an
object is decided when asked (:func:`points_in_boxes`), with the boxes of that moment, so
points seen before a track was confirmed count too; what no box claims is the scene's
*structure* (:func:`split_points`: walls, clutter, furniture not mapped yet).

Memory is bounded: beyond ``max_voxels`` the voxels seen by the fewest points are dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..geometry import points_in_box

#: bits per axis of a voxel key: +-2**20 voxels (+-21 km at 2 cm) packed into one int64
KEY_BITS = 21
#: added to each integer coordinate so that it is packed non-negative
KEY_OFFSET = 1 << (KEY_BITS - 1)
#: points held back before they are merged into the memory: at least the first, at most the
#: second (40 bytes each), else twice the voxels held
PENDING_MIN, PENDING_MAX = 100_000, 500_000


def voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """int64 keys of integer voxel coordinates ``ijk`` (N,3)."""
    q = np.asarray(ijk, np.int64) + KEY_OFFSET
    return (q[:, 0] << (2 * KEY_BITS)) | (q[:, 1] << KEY_BITS) | q[:, 2]


class SurfaceMemory:
    """Voxel means of observed surface points (world frame, metres); see the module doc."""

    def __init__(self, voxel: float = 0.02, max_voxels: int = 500_000) -> None:
        if voxel <= 0:
            raise ValueError(f"voxel must be > 0, got {voxel}")
        self.voxel = float(voxel)
        self.max_voxels = int(max_voxels)
        self._keys = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 3))
        self._counts = np.zeros(0, np.int64)
        self._pending: list[tuple[np.ndarray, np.ndarray, int]] = []  # keys, weighted points, weight
        self._pending_rows = 0

    def __len__(self) -> int:
        self._consolidate()
        return int(self._keys.size)

    def add(self, points: np.ndarray, weight: int = 1) -> None:
        """Add world points (N,3); non-finite rows are ignored. ``weight``: how many
        observations each point stands for (1 for depth samples)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        p = np.compress(np.isfinite(p).all(axis=1), p, axis=0)  # a copy: weighted in place below
        if len(p) == 0:
            return
        keys = voxel_keys(np.floor(p / self.voxel))
        p *= int(weight)
        self._pending.append((keys, p, int(weight)))
        self._pending_rows += len(p)
        # a merge passes over the whole memory: batching the points keeps its cost per point small
        if self._pending_rows > max(PENDING_MIN, min(2 * self._keys.size, PENDING_MAX)):
            self._consolidate()

    def _consolidate(self) -> None:
        if not self._pending:
            return
        keys, pts = (np.concatenate([blk[i] for blk in self._pending]) for i in range(2))
        weights = np.repeat([w for _, _, w in self._pending], [len(k) for k, _, _ in self._pending])
        self._pending, self._pending_rows = [], 0
        keys, inv = np.unique(keys, return_inverse=True)
        inv = inv.ravel()
        sums = np.stack([np.bincount(inv, pts[:, k], len(keys)) for k in range(3)], axis=1)
        counts = np.bincount(inv, weights, len(keys)).astype(np.int64)
        # merge into the sorted keys held: known voxels add up in place, new ones are inserted
        # where they belong (no sort of the whole memory)
        pos = np.searchsorted(self._keys, keys)
        known = pos < self._keys.size
        known[known] = self._keys[pos[known]] == keys[known]
        self._sums[pos[known]] += sums[known]
        self._counts[pos[known]] += counts[known]
        new = ~known
        self._keys = np.insert(self._keys, pos[new], keys[new])
        self._sums = np.insert(self._sums, pos[new], sums[new], axis=0)
        self._counts = np.insert(self._counts, pos[new], counts[new])
        if self._keys.size > self.max_voxels:
            keep = np.sort(np.argsort(-self._counts, kind="stable")[: self.max_voxels])
            self._keys, self._sums, self._counts = self._keys[keep], self._sums[keep], self._counts[keep]

    def points(self, min_count: int = 1) -> np.ndarray:
        """(M,3) the mean point of every voxel that at least ``min_count`` points fell into, world frame."""
        self._consolidate()
        seen = self._counts >= min_count
        return self._sums[seen] / self._counts[seen, None]

    def counts(self) -> np.ndarray:
        """(M,) how many points fell into each voxel (same order as :meth:`points`)."""
        self._consolidate()
        return self._counts.copy()


def points_in_boxes(points: np.ndarray, boxes: Sequence[Any], pad: float = 0.05) -> list[np.ndarray]:
    """For each box (``center`` (3,), ``size`` (3,), ``rotation`` (3,3) columns = axes, world
    frame) the rows of ``points`` (M,3) inside it grown by ``pad`` m on every side; a point
    inside several boxes goes to the first (the detector's boxes seldom overlap by more)."""
    return split_points(points, boxes, pad)[0]


def split_points(points: np.ndarray, boxes: Sequence[Any], pad: float = 0.05) -> tuple[list[np.ndarray], np.ndarray]:
    """:func:`points_in_boxes`, and the (K,3) rows of ``points`` that no box claims (walls,
    clutter, furniture not mapped yet)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    taken = np.zeros(len(p), bool)
    # sorted by x once (the memory's points nearly are: its keys are x-major), each box then
    # looks only at the slab of points within its x extent
    order = np.argsort(p[:, 0], kind="stable")
    xs = p[order, 0]
    out = []
    for b in boxes:
        R = np.asarray(b.rotation, np.float64)
        c = np.asarray(b.center, np.float64)
        ext = np.abs(R) @ (0.5 * np.abs(np.asarray(b.size, np.float64)) + pad)  # world half extents: a cheap pre-filter
        slab = order[np.searchsorted(xs, c[0] - ext[0], "left"):np.searchsorted(xs, c[0] + ext[0], "right")]
        slab = slab[~taken[slab]]
        near = slab[np.all(np.abs(p[slab] - c) <= ext, axis=1)]
        inside = np.sort(near[points_in_box(p[near], c, np.abs(np.asarray(b.size, np.float64)), R, pad)])
        taken[inside] = True
        out.append(p[inside])
    return out, p[~taken]
