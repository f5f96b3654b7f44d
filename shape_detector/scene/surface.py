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

import numba
import numpy as np

from ..geometry import points_in_box

#: bits per axis of a voxel key: +-2**20 voxels (+-21 km at 2 cm) packed into one int64
KEY_BITS = 21
#: added to each integer coordinate so that it is packed non-negative
KEY_OFFSET = 1 << (KEY_BITS - 1)
#: frames' voxels held back before they are merged into the memory: at least the first, at
#: most the second (40 bytes each), else twice the voxels held
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
        # frames' voxels not merged yet: sorted runs one after another in growing buffers (kept
        # between merges: fresh large arrays cost page faults on every frame)
        self._run_keys = np.zeros(0, np.int64)
        self._run_sums = np.zeros((0, 3))
        self._run_counts = np.zeros(0, np.int64)
        self._run_starts = [0]
        self._scratch = np.zeros((2, 0), np.int64)  # one frame's keys and rows

    def __len__(self) -> int:
        self._consolidate()
        return int(self._keys.size)

    def add(self, points: np.ndarray, weight: int = 1) -> None:
        """Add world points (N,3); non-finite rows are ignored. ``weight``: how many
        observations each point stands for (1 for depth samples)."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        at = self._run_starts[-1]
        if at + len(p) > self._run_keys.size:
            cap = max(2 * self._run_keys.size, at + len(p), 1024)
            self._run_keys = np.resize(self._run_keys, cap)
            self._run_sums = np.resize(self._run_sums, (cap, 3))
            self._run_counts = np.resize(self._run_counts, cap)
        if len(p) > self._scratch.shape[1]:
            self._scratch = np.empty((2, len(p)), np.int64)
        keys, rows = self._scratch
        n = _frame_keys(p, self.voxel, keys, rows)
        # one frame's points are few enough to sort in cache; a merge then only streams
        order = np.argsort(keys[:n], kind="stable")
        end = _write_run(keys, rows, order, p, int(weight), self._run_keys, self._run_sums, self._run_counts, at)
        if end == at:
            return
        self._run_starts.append(end)
        # a merge passes over the whole memory: batching the runs keeps its cost per point small
        if end > max(PENDING_MIN, min(2 * self._keys.size, PENDING_MAX)):
            self._consolidate()

    def _consolidate(self) -> None:
        if len(self._run_starts) == 1:
            return
        starts = np.asarray(self._run_starts, np.int64)
        self._run_starts = [0]
        self._keys, self._sums, self._counts = _merge_runs(self._keys, self._sums, self._counts, self._run_keys,
                                                           self._run_sums, self._run_counts, starts)
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


@numba.njit(cache=True, nogil=True)
def _frame_keys(points, voxel, keys, rows):  # pragma: no cover - compiled
    """:func:`voxel_keys` of the finite rows of ``points`` (N,3) into ``keys``, those rows' indices into
    ``rows``; returns how many."""
    j = 0
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
            qx = np.int64(np.floor(x / voxel)) + KEY_OFFSET
            qy = np.int64(np.floor(y / voxel)) + KEY_OFFSET
            qz = np.int64(np.floor(z / voxel)) + KEY_OFFSET
            keys[j] = (qx << (2 * KEY_BITS)) | (qy << KEY_BITS) | qz
            rows[j] = i
            j += 1
    return j


@numba.njit(cache=True, nogil=True)
def _write_run(keys, rows, order, points, weight, out_k, out_s, out_c, at):  # pragma: no cover - compiled
    """Write one sorted run into the buffers from row ``at``: the distinct ``keys`` in the
    ascending ``order``, with the sums of their ``points[rows]`` and their counts, each point
    standing for ``weight``. Returns the row after the run."""
    m = at - 1
    for t in range(order.shape[0]):
        k = keys[order[t]]
        if m < at or k != out_k[m]:
            m += 1
            out_k[m] = k
            out_s[m, 0] = out_s[m, 1] = out_s[m, 2] = 0.0
            out_c[m] = 0
        r = rows[order[t]]
        for a in range(3):
            out_s[m, a] += weight * points[r, a]
        out_c[m] += weight
    return m + 1


@numba.njit(cache=True, nogil=True)
def _merge_runs(mem_k, mem_s, mem_c, keys, sums, counts, starts):  # pragma: no cover - compiled
    """The sorted memory (``mem_*``) and the sorted runs ``keys[starts[r]:starts[r + 1]]`` (with
    their sums and counts) merged into one sorted run, equal keys added up: a k-way merge over
    a heap of the runs' heads, so every row is read once, in order."""
    nr = starts.shape[0] - 1
    total = mem_k.shape[0] + starts[nr]
    out_k = np.empty(total, np.int64)
    out_s = np.empty((total, 3))
    out_c = np.empty(total, np.int64)
    # stream nr is the memory; heap entries are streams ordered by their head key
    pos = np.empty(nr + 1, np.int64)
    end = np.empty(nr + 1, np.int64)
    pos[:nr], end[:nr] = starts[:nr], starts[1:]
    pos[nr], end[nr] = 0, mem_k.shape[0]
    heap = np.empty(nr + 1, np.int64)
    head = np.empty(nr + 1, np.int64)
    h = 0
    for r in range(nr + 1):
        if pos[r] < end[r]:
            k = mem_k[pos[r]] if r == nr else keys[pos[r]]
            i = h  # sift up
            h += 1
            while i > 0 and head[(i - 1) // 2] > k:
                heap[i], head[i] = heap[(i - 1) // 2], head[(i - 1) // 2]
                i = (i - 1) // 2
            heap[i], head[i] = r, k
    m = -1
    while h > 0:
        r, k = heap[0], head[0]
        p = pos[r]
        if m < 0 or out_k[m] != k:
            m += 1
            out_k[m] = k
            out_s[m, 0] = out_s[m, 1] = out_s[m, 2] = 0.0
            out_c[m] = 0
        if r == nr:
            for a in range(3):
                out_s[m, a] += mem_s[p, a]
            out_c[m] += mem_c[p]
        else:
            for a in range(3):
                out_s[m, a] += sums[p, a]
            out_c[m] += counts[p]
        pos[r] = p + 1
        if pos[r] < end[r]:
            k = mem_k[p + 1] if r == nr else keys[p + 1]
        else:  # stream done: the last heap entry takes its place
            h -= 1
            r, k = heap[h], head[h]
        i = 0  # sift down
        while True:
            c = 2 * i + 1
            if c >= h:
                break
            if c + 1 < h and head[c + 1] < head[c]:
                c += 1
            if head[c] >= k:
                break
            heap[i], head[i] = heap[c], head[c]
            i = c
        if h > 0:
            heap[i], head[i] = r, k
    n = m + 1
    return out_k[:n].copy(), out_s[:n].copy(), out_c[:n].copy()


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
