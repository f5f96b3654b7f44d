"""Ray casts onto the surfaces the camera observed (world frame, z up, metres).

Each object may carry the depth points seen inside its box (``SceneObject.surface``, voxel
means from :class:`shape_detector.scene.surface.SurfaceMemory`). A ray's surface hit is where
it first passes within ``tube`` of such points: the median distance along the ray of the
points in the first ``cluster`` metres of that tube (noise along the ray averages out).

To stay vectorised and fast, each object's points go into a world-aligned grid of ``cell``-
sized cells holding one point each (the points are voxel means on a lattice of that size).
A ray first marches through a copy of the occupancy grown by one cell, in steps of one cell,
and only where it meets that shell are the points of the 3 x 3 x 3 cells around a few steps
tested against the tube. Normals come from the points around the hit (smallest principal
axis, facing the ray).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

#: objects whose surface grid would exceed this many cells are left to their primitives
MAX_CELLS = 8_000_000
_NEIGHBOURS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
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
    around: np.ndarray  # (K, 27) int: flat offsets of a cell's 3 x 3 x 3 neighbourhood in each grid
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
    around = (_NEIGHBOURS[None, :, 0] * sh[:, 1:2] + _NEIGHBOURS[None, :, 1]) * sh[:, 2:3] + _NEIGHBOURS[None, :, 2]
    return SurfaceIndex(float(cell), np.concatenate(pts), np.array(los), sh,
                        np.array(offs, np.int64), np.array(oids, np.int64), np.concatenate(pat),
                        np.concatenate(shells), around, np.array(frames), np.array(qlo), np.array(qhi), tube, float(cluster))


def _cells(index: SurfaceIndex, k: np.ndarray, pos: np.ndarray, margin: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of the cells of world positions ``pos`` (n,3) in object grids ``k`` (n,),
    and whether each lies at least ``margin`` cells inside its grid."""
    c = np.floor(pos / index.cell).astype(np.int64) - index.lo[k]
    sh = index.shape[k]
    inside = np.all((c >= margin) & (c < sh - margin), axis=1)
    return index.offset[k] + (c[:, 0] * sh[:, 1] + c[:, 1]) * sh[:, 2] + c[:, 2], inside


def _around(index: SurfaceIndex, k: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, point index) of the points in the 3 x 3 x 3 cells around each of ``pos`` (n,3)
    in grids ``k``; positions on a grid's outer cell have no points around (the margin)."""
    flat, inside = _cells(index, k, pos, margin=1)
    rows = np.flatnonzero(inside)
    idx = index.point_at[flat[rows, None] + index.around[k[rows]]]
    has = idx >= 0
    return np.broadcast_to(rows[:, None], idx.shape)[has], idx[has]


def cast(index: SurfaceIndex, o: np.ndarray, d: np.ndarray, limit: np.ndarray, t_min: float = 0.05) \
        -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface hits of rays ``o`` (n,3) + t ``d`` (n,3, unit) with ``t_min < t <= limit`` (n,):
    distance (n,) (inf: none), object id (n,) (-1: none), unit normal (n,3) facing the ray."""
    n = len(o)
    dist, oid, normal = np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 3))
    h = index.cell
    # rays x objects: the slab test against each object's points' box (its own axes)
    ol = np.einsum("ni,kij->nkj", o, index.frames)
    dl = np.einsum("ni,kij->nkj", d, index.frames)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dl) < 1e-12, 1e-12, dl)
        t1 = (index.qlo[None] - ol) * inv
        t2 = (index.qhi[None] - ol) * inv
    tin = np.maximum(np.minimum(t1, t2).max(axis=2), t_min)
    tout = np.minimum(np.maximum(t1, t2).min(axis=2), (limit + h)[:, None])
    r, k = np.nonzero((tin <= tout) & np.isfinite(tin))
    if len(r) == 0:
        return dist, oid, normal
    tin, tout = tin[r, k], tout[r, k]
    # nearest grid first: a ray whose surface is found skips the grids it enters beyond it
    order = np.lexsort((tin, r))
    r, k, tin, tout = r[order], k[order], tin[order], tout[order]
    starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
    rank = np.arange(len(r)) - np.repeat(starts, np.diff(np.r_[starts, len(r)]))
    best_k = np.full(n, -1, np.int64)
    for level in range(int(rank.max()) + 1):
        sel = np.flatnonzero(rank == level)
        sel = sel[tin[sel] < dist[r[sel]]]
        if len(sel) == 0:
            break  # tin grows with rank: every later grid lies beyond a found surface
        rs = r[sel]
        est = _pair_hits(index, o[rs], d[rs], k[sel], tin[sel], np.minimum(tout[sel], dist[rs]), limit[rs], t_min)
        better = est < dist[rs]
        dist[rs[better]], best_k[rs[better]] = est[better], k[sel][better]
    rays = np.flatnonzero(best_k >= 0)
    oid[rays] = index.object_ids[best_k[rays]]
    normal[rays] = _normals(index, best_k[rays], o[rays] + dist[rays, None] * d[rays], d[rays])
    return dist, oid, normal


def _pair_hits(index: SurfaceIndex, o: np.ndarray, d: np.ndarray, k: np.ndarray, tin: np.ndarray, tout: np.ndarray,
               limit: np.ndarray, t_min: float) -> np.ndarray:
    """Surface distance of each ray in object grid ``k`` between ``tin`` and ``tout`` (inf: none)."""
    est = np.full(len(k), np.inf)
    todo = np.arange(len(k))
    tin = tin.copy()
    for _ in range(_PASSES):  # a shell met without points in the tube: march on past it
        if len(todo) == 0:
            break
        first = _march(index, o[todo], d[todo], k[todo], tin[todo], tout[todo])
        met = np.isfinite(first)
        todo, first = todo[met], first[met]
        if len(todo) == 0:
            break
        est[todo] = _tube_hit(index, o[todo], d[todo], k[todo], first, limit[todo], t_min)
        miss = ~np.isfinite(est[todo])
        todo, first = todo[miss], first[miss]
        tin[todo] = first + _window(index)[-1]  # where the tested window ended
        todo = todo[tin[todo] <= tout[todo]]
    return est


def _march(index: SurfaceIndex, o: np.ndarray, d: np.ndarray, k: np.ndarray, tin: np.ndarray, tout: np.ndarray) \
        -> np.ndarray:
    """Phase 1: the first distance in ``[tin, tout]`` (per ray / object grid pair) where each
    ray meets the grown occupancy of grid ``k``, in steps of a cell (the grown shell is three
    cells thick) (inf: never)."""
    h = index.cell
    steps = np.floor((tout - tin) / h).astype(np.int64) + 1
    starts = np.cumsum(steps) - steps
    j = np.arange(int(steps.sum()), dtype=np.float32) - np.repeat(starts.astype(np.float32), steps)
    c0 = ((o + tin[:, None] * d) / h - index.lo[k]).astype(np.float32)  # cell coordinates; a step adds d
    c = np.floor(np.repeat(c0, steps, axis=0) + j[:, None] * np.repeat(d.astype(np.float32), steps, axis=0))
    c = c.astype(np.int64)
    sh = np.repeat(index.shape[k], steps, axis=0)
    inside = np.all((c >= 0) & (c < sh), axis=1)
    flat = np.repeat(index.offset[k], steps) + (c[:, 0] * sh[:, 1] + c[:, 1]) * sh[:, 2] + c[:, 2]
    on = np.zeros(len(j), bool)
    on[inside] = index.shell[flat[inside]]
    t = np.repeat(tin, steps) + h * j
    return np.minimum.reduceat(np.where(on, t, np.inf), starts)


def _window(index: SurfaceIndex) -> np.ndarray:
    """Phase-2 steps (m) relative to where a ray met the grown occupancy."""
    return np.arange(-index.cell, index.cluster + 2 * index.cell + 1e-9, index.cell)


def _tube_points(index: SurfaceIndex, o: np.ndarray, d: np.ndarray, k: np.ndarray, steps: np.ndarray,
                 limit: np.ndarray, t_min: float) -> tuple[np.ndarray, np.ndarray]:
    """(ray row, distance along the ray) of the distinct points of grids ``k`` within the tube of
    each ray near its ``steps`` (n, s) (m along the ray), sorted by row then distance.

    Steps a cell apart suffice: one lies within half a cell of the ray's nearest approach to a
    point in the tube, so (tube <= 0.85 cell) within one cell of the point along every axis."""
    pw = np.repeat(np.arange(len(k)), steps.shape[1])
    rows, idx = _around(index, k[pw], o[pw] + steps.reshape(-1, 1) * d[pw])
    pp = pw[rows]
    v = index.points[idx] - o[pp]
    tc = np.einsum("ij,ij->i", v, d[pp])
    perp2 = np.einsum("ij,ij->i", v, v) - tc * tc
    ok = (perp2 <= index.tube ** 2) & (tc > t_min) & (tc <= limit[pp] + index.cell)
    pp, tc, idx = pp[ok], tc[ok], idx[ok]
    order = np.lexsort((idx, tc, pp))
    pp, tc, idx = pp[order], tc[order], idx[order]
    once = np.r_[True, (pp[1:] != pp[:-1]) | (idx[1:] != idx[:-1])][: len(pp)]  # a point seen from two steps
    return pp[once], tc[once]


def _tube_hit(index: SurfaceIndex, o: np.ndarray, d: np.ndarray, k: np.ndarray, first: np.ndarray,
              limit: np.ndarray, t_min: float) -> np.ndarray:
    """Phase 2: from where each ray met the grown occupancy (``first``), the median distance
    of the points of grid ``k`` in its tube within ``cluster`` of the nearest one (inf: none)."""
    h = index.cell
    out = np.full(len(k), np.inf)
    pp, tc = _tube_points(index, o, d, k, first[:, None] + _window(index)[None], limit, t_min)
    if len(pp) == 0:
        return out
    gstart = np.flatnonzero(np.r_[True, pp[1:] != pp[:-1]])
    near, t0 = pp[gstart], tc[gstart]  # the nearest point in the tube: the window holds all before it
    # the cluster behind it may reach past the window: gather it from the nearest point on
    pp, tc = _tube_points(index, o[near], d[near], k[near], t0[:, None] + h * np.arange(3.0)[None], limit[near],
                          t_min)
    keep = tc >= t0[pp] - 1e-9
    pp, tc = pp[keep], tc[keep]
    gstart = np.flatnonzero(np.r_[True, pp[1:] != pp[:-1]])
    gid = np.repeat(np.arange(len(gstart)), np.diff(np.r_[gstart, len(pp)]))
    inside = tc <= t0[pp] + index.cluster  # contiguous at each group's start
    count = np.bincount(gid[inside], minlength=len(gstart))
    out[near[pp[gstart]]] = 0.5 * (tc[gstart + (count - 1) // 2] + tc[gstart + count // 2])
    return out


def _normals(index: SurfaceIndex, k: np.ndarray, hit: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Unit normals (n,3) at world points ``hit`` on object grids ``k``: the smallest principal
    axis of the points in the 3 x 3 x 3 cells around each (``-d`` with fewer than 3), facing ``-d``."""
    n = len(hit)
    flat, inside = _cells(index, k, hit, margin=1)
    idx = np.full((n, len(_NEIGHBOURS)), -1, np.int64)
    idx[inside] = index.point_at[flat[inside, None] + index.around[k[inside]]]
    valid = idx >= 0
    pts = index.points[np.where(valid, idx, 0)]
    cnt = valid.sum(1)
    mean = (pts * valid[..., None]).sum(1) / np.maximum(cnt, 1)[:, None]
    q = (pts - mean[:, None]) * valid[..., None]
    cov = np.matmul(q.transpose(0, 2, 1), q)
    _, vec = np.linalg.eigh(cov + 1e-12 * np.eye(3))
    nrm = vec[:, :, 0]
    nrm = np.where((cnt >= 3)[:, None], nrm, -d)
    return nrm * np.where(np.einsum("ij,ij->i", nrm, d) > 0, -1.0, 1.0)[:, None]
