"""Ray casts onto the surfaces the camera observed (world frame, z up, metres).

Each object may carry the depth points seen inside its box (``SceneObject.surface``, voxel
means from :class:`shape_detector.scene.surface.SurfaceMemory`). A ray's surface hit is where
it first passes within ``tube`` of such points: the median distance along the ray of the
points in the first ``cluster`` metres of that tube (noise along the ray averages out).

Each object's points go into a world-aligned grid of ``cell``-sized cells holding one point
each (the points are voxel means on a lattice of that size). A ray visits the objects whose
points' box (in the object's own axes) it crosses, nearest first, and marches through a copy
of the occupancy grown by one cell, in steps of one cell; only where it meets that shell are
the points of the 3 x 3 x 3 cells around a few steps tested against the tube. Normals come
from the points around the hit (smallest principal axis, facing the ray).

The per-ray loop is compiled with numba (cached on disk after the first call): a ray's march
stops at its first surface, which array code cannot do without many small passes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage

from .row_split import run_rows

#: objects whose surface grid would exceed this many cells are left to their primitives
MAX_CELLS = 8_000_000
_PASSES = 6  # shells met without a surface in the tube, before a ray gives up on a grid


@dataclass
class SurfaceIndex:
    """The surface points of a scene's objects arranged for ray casts (module doc)."""

    cell: float
    points: np.ndarray  # (M, 3) world
    lo: np.ndarray  # (K, 3) int: first cell of each object's grid
    shape: np.ndarray  # (K, 3) int: cells per axis
    offset: np.ndarray  # (K,) int: start of each grid in the flat arrays
    object_ids: np.ndarray  # (K,)
    point_at: np.ndarray  # flat int32: point index of each cell, -1 empty
    shell: np.ndarray  # flat bool: occupancy grown by one cell
    frames: np.ndarray  # (K, 3, 3) columns = the axes of each object's box (world)
    qlo: np.ndarray  # (K, 3) its points' extent along those axes, grown by two cells
    qhi: np.ndarray
    tube: float
    cluster: float

    def __len__(self) -> int:
        return int(len(self.points))


def build_index(surfaces: Sequence[tuple[int, np.ndarray, np.ndarray]], cell: float = 0.02, tube: float | None = None,
                cluster: float = 0.03) -> SurfaceIndex | None:
    """A :class:`SurfaceIndex` of ``(object id, (M,3) world points, (3,3) box axes)`` triples
    (the axes bound the rays' march tightly); None without points.
    ``cell``: grid cell (m), the surface voxel size; ``tube``: ray radius (default 0.75 ``cell``:
    wider lets rays that pass beside thin parts stop on them, narrower lets them slip through
    gaps between the voxels); ``cluster``: depth (m) of the first surface cluster whose median
    is the hit."""
    tube = 0.75 * cell if tube is None else float(tube)
    if not 0.0 < tube <= 0.85 * cell:
        raise ValueError(f"tube must be in (0, 0.85 cell], got {tube} for cell {cell}")
    pts, los, shapes, offs, oids, pat, shells, frames, qlo, qhi = ([] for _ in range(10))
    start, total = 0, 0
    for oid, p, R in surfaces:
        p = np.asarray(p, np.float64).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p) == 0:
            continue
        ijk = np.floor(p / cell).astype(np.int64)
        lo = ijk.min(0) - 2  # two empty cells around: every cell next to a point has all its neighbours
        shape = ijk.max(0) - lo + 3
        n = int(np.prod(shape))
        if n > MAX_CELLS:
            continue
        grid = np.full(n, -1, np.int32)
        local = np.ravel_multi_index(tuple((ijk - lo).T), tuple(shape))
        grid[local] = np.arange(len(p), dtype=np.int32) + start
        occ = (grid >= 0).reshape(tuple(shape))
        shells.append(ndimage.binary_dilation(occ, np.ones((3, 3, 3), bool)).ravel())
        pat.append(grid)
        pts.append(p)
        los.append(lo)
        shapes.append(shape)
        offs.append(total)
        oids.append(int(oid))
        R = np.asarray(R, np.float64).reshape(3, 3)
        q = p @ R
        frames.append(R)
        qlo.append(q.min(0) - 2 * cell)
        qhi.append(q.max(0) + 2 * cell)
        start += len(p)
        total += n
    if not pts:
        return None
    sh = np.array(shapes)
    return SurfaceIndex(float(cell), np.concatenate(pts), np.array(los), sh,
                        np.array(offs, np.int64), np.array(oids, np.int64), np.concatenate(pat),
                        np.concatenate(shells), np.array(frames), np.array(qlo), np.array(qhi), tube, float(cluster))


def _window(index: SurfaceIndex) -> np.ndarray:
    """Steps (m) relative to where a ray met the grown occupancy whose tube points are tested."""
    return np.arange(-index.cell, index.cluster + 2 * index.cell + 1e-9, index.cell)


def cast(index: SurfaceIndex, o: np.ndarray, d: np.ndarray, limit: np.ndarray, t_min: float = 0.05) \
        -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface hits of rays ``o`` (n,3) + t ``d`` (n,3, unit, finite) with ``t_min < t <= limit`` (n,):
    distance (n,) (inf: none), object id (n,) (-1: none), unit normal (n,3) facing the ray."""
    n = len(o)
    dist, best_k, normal = np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 3))
    window = _window(index)
    o, d = np.ascontiguousarray(o, np.float64), np.ascontiguousarray(d, np.float64)
    limit = np.ascontiguousarray(limit, np.float64)

    def rows(a: int, b: int) -> None:
        _cast_rays(o[a:b], d[a:b], limit[a:b], float(t_min), index.cell, index.frames, index.qlo, index.qhi,
                   index.lo, index.shape, index.offset, index.point_at, index.shell, index.points, index.tube,
                   index.cluster, float(window[0]), len(window), _PASSES, dist[a:b], best_k[a:b], normal[a:b])

    run_rows(rows, n)
    oid = np.where(best_k >= 0, index.object_ids[np.maximum(best_k, 0)], -1)
    return dist, oid, normal


@numba.njit(cache=True, nogil=True)
def _cast_rays(o, d, limit, t_min, h, frames, qlo, qhi, lo, shape, offset, point_at, shell, points, tube,
               cluster, w0, n_window, passes, dist, best_k, normal):
    """``cast`` for every ray: writes ``dist``, ``best_k`` (grid index) and ``normal`` in place."""
    n_grids = frames.shape[0]
    tin = np.empty(n_grids)
    tout = np.empty(n_grids)
    grids = np.empty(n_grids, np.int64)
    n_again = int(np.ceil(cluster / h)) + 1  # steps from the nearest point that hold its cluster
    buf_t = np.empty(27 * (n_window + n_again))  # a ray's tube points in one grid
    buf_i = np.empty(27 * (n_window + n_again), np.int64)
    w_end = w0 + (n_window - 1) * h
    for i in range(o.shape[0]):
        oi, di = o[i], d[i]
        m = _grids_crossed(oi, di, t_min, limit[i] + h, frames, qlo, qhi, tin, tout, grids)
        best, bk = np.inf, -1
        for p in range(m):
            if tin[p] >= best:
                break  # the grids come nearest first: the rest lie beyond the surface found
            k = grids[p]
            t, te = tin[p], min(tout[p], best)
            for _ in range(passes):  # a shell met without points in the tube: march on past it
                first = _march(oi, di, k, t, te, h, lo, shape, offset, shell)
                if first == np.inf:
                    break
                nb = _tube(oi, di, k, first + w0, n_window, h, lo, shape, offset, point_at, points, tube, t_min,
                           limit[i] + h, buf_t, buf_i, 0)
                if nb == 0:
                    t = first + w_end
                    if t > te:
                        break
                    continue
                t0 = buf_t[0]  # the nearest point in the tube: the window holds all before it
                for q in range(1, nb):
                    t0 = min(t0, buf_t[q])
                if t0 + cluster > first + w_end + 0.5 * h - 1e-9:  # the window ends half a cell past its last step
                    nb = _tube(oi, di, k, t0, n_again, h, lo, shape, offset, point_at, points, tube, t_min, limit[i] + h,
                               buf_t, buf_i, nb)
                cnt = 0
                for q in range(nb):
                    if t0 - 1e-9 <= buf_t[q] <= t0 + cluster:
                        buf_t[cnt] = buf_t[q]
                        cnt += 1
                _sort_head(buf_t, cnt)
                est = 0.5 * (buf_t[(cnt - 1) // 2] + buf_t[cnt // 2])
                if est < best:
                    best, bk = est, k
                break
        dist[i] = best
        best_k[i] = bk
        if bk >= 0:
            _normal(oi + best * di, di, bk, h, lo, shape, offset, point_at, points, normal[i])


@numba.njit(cache=True, nogil=True)
def _sort_head(a, n):
    """Sorts ``a[:n]`` in place (insertion: a ray's cluster holds a few points)."""
    for i in range(1, n):
        v, j = a[i], i
        while j > 0 and a[j - 1] > v:
            a[j] = a[j - 1]
            j -= 1
        a[j] = v


@numba.njit(cache=True, nogil=True)
def _grids_crossed(o, d, t_lo, t_hi, frames, qlo, qhi, tin, tout, grids):
    """Slab test against each grid's points' box in its own axes: the grids the ray crosses
    within ``[t_lo, t_hi]``, written to ``tin`` / ``tout`` / ``grids`` sorted by entry; their count."""
    m = 0
    for k in range(frames.shape[0]):
        a_in, a_out = t_lo, t_hi
        for a in range(3):
            ol = o[0] * frames[k, 0, a] + o[1] * frames[k, 1, a] + o[2] * frames[k, 2, a]
            dl = d[0] * frames[k, 0, a] + d[1] * frames[k, 1, a] + d[2] * frames[k, 2, a]
            if abs(dl) < 1e-12:
                if ol < qlo[k, a] or ol > qhi[k, a]:
                    a_in = np.inf
                    break
                continue
            t1, t2 = (qlo[k, a] - ol) / dl, (qhi[k, a] - ol) / dl
            a_in, a_out = max(a_in, min(t1, t2)), min(a_out, max(t1, t2))
        if a_in > a_out:
            continue
        j = m
        while j > 0 and tin[j - 1] > a_in:  # insertion: a ray crosses a few grids
            tin[j], tout[j], grids[j] = tin[j - 1], tout[j - 1], grids[j - 1]
            j -= 1
        tin[j], tout[j], grids[j] = a_in, a_out, k
        m += 1
    return m


@numba.njit(cache=True, nogil=True)
def _cell(o, d, t, h, lo, k):
    """Cell coordinates in grid ``k`` of the point ``o + t d``."""
    return (int(np.floor((o[0] + t * d[0]) / h)) - lo[k, 0], int(np.floor((o[1] + t * d[1]) / h)) - lo[k, 1],
            int(np.floor((o[2] + t * d[2]) / h)) - lo[k, 2])


@numba.njit(cache=True, nogil=True)
def _march(o, d, k, t, te, h, lo, shape, offset, shell):
    """The first step ``t + j h <= te`` where the ray is in the grown occupancy of grid ``k``
    (the shell is three cells thick, so one-cell steps cannot jump it); inf: none."""
    s0, s1, s2 = shape[k, 0], shape[k, 1], shape[k, 2]
    for j in range(int(np.floor((te - t) / h)) + 1):
        c0, c1, c2 = _cell(o, d, t + j * h, h, lo, k)
        if 0 <= c0 < s0 and 0 <= c1 < s1 and 0 <= c2 < s2 and shell[offset[k] + (c0 * s1 + c1) * s2 + c2]:
            return t + j * h
    return np.inf


@numba.njit(cache=True, nogil=True)
def _tube(o, d, k, t, n_steps, h, lo, shape, offset, point_at, points, tube, t_min, t_max, buf_t, buf_i,
          nb):
    """Adds to ``buf_t`` / ``buf_i`` (``nb`` used) the distance along the ray and index of the
    distinct points of grid ``k`` within ``tube`` of the ray, ``t_min < distance <= t_max``,
    near the steps ``t + j h``; returns the new count.

    Steps a cell apart suffice: one lies within half a cell of the ray's nearest approach to a
    point in the tube, so (tube <= 0.85 cell) within one cell of the point along every axis."""
    s0, s1, s2 = shape[k, 0], shape[k, 1], shape[k, 2]
    for j in range(n_steps):
        c0, c1, c2 = _cell(o, d, t + j * h, h, lo, k)
        if not (1 <= c0 < s0 - 1 and 1 <= c1 < s1 - 1 and 1 <= c2 < s2 - 1):
            continue  # a grid's outer cells hold no points, nor do their neighbours beyond
        for a in range(-1, 2):
            for b in range(-1, 2):
                row = offset[k] + ((c0 + a) * s1 + c1 + b) * s2 + c2
                for c in range(-1, 2):
                    idx = point_at[row + c]
                    if idx < 0:
                        continue
                    v0, v1, v2 = points[idx, 0] - o[0], points[idx, 1] - o[1], points[idx, 2] - o[2]
                    tc = v0 * d[0] + v1 * d[1] + v2 * d[2]
                    if v0 * v0 + v1 * v1 + v2 * v2 - tc * tc > tube * tube or tc <= t_min or tc > t_max:
                        continue
                    seen = False
                    for q in range(nb):
                        if buf_i[q] == idx:
                            seen = True
                            break
                    if not seen:
                        buf_t[nb], buf_i[nb] = tc, idx
                        nb += 1
    return nb


@numba.njit(cache=True, nogil=True)
def _normal(hit, d, k, h, lo, shape, offset, point_at, points, out):
    """Writes to ``out`` the unit normal at ``hit`` on grid ``k``: the smallest principal axis of
    the points in the 3 x 3 x 3 cells around it (``-d`` with fewer than 3), facing ``-d``.
    Scalar loops only: numba takes seconds to compile array slicing and axis reductions."""
    s0, s1, s2 = shape[k, 0], shape[k, 1], shape[k, 2]
    c0, c1, c2 = _cell(hit, d, 0.0, h, lo, k)
    for a in range(3):
        out[a] = -d[a]
    if not (1 <= c0 < s0 - 1 and 1 <= c1 < s1 - 1 and 1 <= c2 < s2 - 1):
        return
    cnt = 0
    first = np.zeros(3)  # sums of the points' offsets from the hit
    second = np.zeros((3, 3))
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                idx = point_at[offset[k] + ((c0 + a) * s1 + c1 + b) * s2 + c2 + c]
                if idx < 0:
                    continue
                cnt += 1
                for i in range(3):
                    first[i] += points[idx, i] - hit[i]
                    for j in range(3):
                        second[i, j] += (points[idx, i] - hit[i]) * (points[idx, j] - hit[j])
    if cnt < 3:
        return
    cov = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            cov[i, j] = second[i, j] - first[i] * first[j] / cnt + (1e-12 if i == j else 0.0)
    _, vec = np.linalg.eigh(cov)
    flip = vec[0, 0] * d[0] + vec[1, 0] * d[1] + vec[2, 0] * d[2] > 0
    for i in range(3):
        out[i] = -vec[i, 0] if flip else vec[i, 0]
