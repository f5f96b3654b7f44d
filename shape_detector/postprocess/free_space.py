"""Shrink amodal boxes out of space the camera sees through (free-space carving).

The network guesses an object's hidden extent, and sometimes guesses too much: a dresser
0.53 m deep predicted 0.62 m, its far face 9 cm behind the real one. Where the camera sees
*past* a part of such a box -- the measured depth at a pixel lies behind a point of the box
that projects there -- that part is observed to be empty. :func:`carve_free_space` walks
each side face (``±x``, ``±y``) of the box inwards in thin layers, and removes a layer when

* at least ``min_free`` of its lattice samples are seen through: the measured depth exceeds
  the sample's own depth by more than ``margin + margin_per_m * z`` (optical frame, z
  forward, metres), with at most ``max_surface_ratio`` samples per seen-through one lying
  on a measured surface (within that margin);
* at least ``min_top_free`` of them lie in the layer's top rows: the box's upper edge there
  is seen past. The air under a table top or a chair seat is seen through too, but not
  their top edge;
* it holds at most ``max_occupied`` measured points (of any pixel, not only the object's
  own; points within ``floor_band`` of the box bottom are floor);
* the face stays outside the ``fg_quantile`` / ``1 - fg_quantile`` range of the object's own
  segmented points along that axis, and moves by at most ``max_frac`` of the box's size.

The top face is carved the same way for the classes of ``top_classes`` (flat-topped
furniture: a table top, a dresser's or a bookshelf's top board spans the footprint); the
thin upper parts of others (chair backs, headboards) often drop out of noisy depth at range,
and carving would cut them off. Chairs are not carved at all (``classes``): the camera sees
through their open backs and between their rails and legs. The bottom is left to the floor snap
(:mod:`shape_detector.floor`).

A camera *below* a flat top cannot see past it, but it sees the top board's front edge, which is
then the highest part of the object in view: when the object's 2D box does not touch the image's
top border, the top of a ``top_classes`` box is capped at the ``top_cap_quantile`` of the
object's own points' heights plus ``top_cap_margin``. It matters for tall furniture seen from
below (bookshelves); tables and desks are seen from above and are not affected.

Faces are carved in rounds, the face whose outer layer is seen through most first: a face
too far out makes its neighbours' layers look seen through where they overlap its excess.
Space hidden behind something nearer (another object, the object itself) is never seen
through, so occluded parts are never carved: only guesses the image contradicts are.

:func:`carve_all` runs the rounds of a frame's boxes side by side, so that each round's
seen-through tests of all of them share one projection and one depth lookup.

Its measured effect is in docs/experiments/code-comment-numbers.md. Pure numpy; boxes
change through :meth:`Object3D.set_extent`, so primitives stretch with them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..classes import CLASSES
from ..geometry import box_corners, measured_depth, project_points
from .point_fit import PointSource, segmented_points, sorted_quantile
from ..types import Object3D


#: flat-topped furniture: the top surface spans the footprint
FLAT_TOPPED = frozenset({"table", "desk", "dresser", "night_stand", "bookshelf"})
#: classes carved at all: not chairs, whose open backs and thin rails the depth map sees
#: through (carving them made more chairs worse at 3D IoU >= 0.5 than it made better)
CARVED = frozenset(CLASSES) - {"chair"}


#: metres of slack of the depth-range cut of :func:`_box_points`: far above the rounding of
#: the box-frame transform and of a float32 depth map, so the cut keeps every point it must
_DEPTH_SLACK = 0.02


@dataclass(frozen=True)
class CarveParams:
    """Settings of :func:`carve_free_space` (metres unless said)."""

    #: thickness of one carved layer
    step: float = 0.02
    #: a face moves inwards by at most this share of the box's size along its axis
    max_frac: float = 0.4
    #: samples per layer along each of the face's two axes
    grid: int = 12
    #: seen-through test: measured depth > point depth + margin + margin_per_m * depth
    margin: float = 0.03
    margin_per_m: float = 0.01
    #: a layer needs at least this many seen-through samples ...
    min_free: int = 4
    #: ... and at most this many samples on an observed surface per seen-through one
    max_surface_ratio: float = 0.5
    #: the face stops at this quantile of the object's own points along its axis
    fg_quantile: float = 0.02
    #: a layer holding more than this many measured points (any pixel's, not only the
    #: object's segmented ones) is occupied and stops its face
    max_occupied: int = 1
    #: measured points this close above the box bottom (the floor) do not count as occupying
    floor_band: float = 0.05
    #: classes whose boxes are carved (others are returned unchanged)
    classes: frozenset[str] = CARVED
    #: classes whose top face is carved too (the bottom is left to the floor snap)
    top_classes: frozenset[str] = FLAT_TOPPED
    #: a side layer also needs this many seen-through samples in its top ``top_rows`` rows
    #: of the sample lattice: the box's upper edge there is seen past (air under a table
    #: top or a chair seat is seen through too, its top edge is not)
    min_top_free: int = 2
    top_rows: int = 2
    #: at most about this many pixels of the box's image rectangle are back-projected
    max_pixels: int = 6000
    #: with the camera below a ``top_classes`` box's top and the 2D box's top edge more than
    #: ``top_cap_border`` pixels inside the image, the top is capped at this quantile of the
    #: object's points' heights plus ``top_cap_margin`` (metres); quantile 1.0 or more = off
    top_cap_quantile: float = 0.99
    top_cap_margin: float = 0.01
    top_cap_border: float = 2.0


@lru_cache(maxsize=8)
def _face_lattices(grid: int) -> np.ndarray:
    """(3, grid*grid, 3) read-only: for a face on axis ``a``, ``[a]`` holds each lattice
    sample's fraction of the box along the face's two other axes (the second varying
    fastest) and 0 along ``a``, so ``lo + lattice * (hi - lo)`` spans the face."""
    t = (np.arange(grid) + 0.5) / grid
    t1, t2 = np.repeat(t, grid), np.tile(t, grid)
    out = np.zeros((3, grid * grid, 3))
    for axis in range(3):
        o1, o2 = [a for a in range(3) if a != axis]
        out[axis, :, o1], out[axis, :, o2] = t1, t2
    out.flags.writeable = False
    return out


def _seen_through(cam: np.ndarray, depth: np.ndarray, K: np.ndarray, p: CarveParams) -> tuple[np.ndarray, np.ndarray]:
    """(free, surface) bool arrays for camera-frame points ``cam`` (..., 3) that project
    inside the image onto valid depth: ``free`` = the measured depth lies behind the point
    by more than the margin (seen through), ``surface`` = within the margin of it (an
    observed surface there). Points with something nearer in front are neither."""
    z = cam[..., 2]
    d = measured_depth(cam, depth, K)
    with np.errstate(invalid="ignore"):
        known = np.isfinite(d)
        tol = p.margin + p.margin_per_m * z
        free = known & (d > z + tol)
        surface = known & (np.abs(d - z) <= tol)
    return free, surface


def _box_points(c: np.ndarray, R: np.ndarray, half: np.ndarray, depth: np.ndarray, K: np.ndarray, max_pixels: int,
                lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Box-frame coordinates (3, n), one row per axis, of the valid depth pixels in the image
    rectangle the box ``c``, ``R``, ``half`` projects into (every ``s``-th row and column,
    ``s`` chosen to keep about ``max_pixels``) that lie within ``[lower, upper]`` (box
    frame, metres). Empty when the box lies behind the camera."""
    h, w = depth.shape
    corners = box_corners(c, 2.0 * half, R)
    if corners[:, 2].min() <= 0.05:
        return np.zeros((3, 0))
    uv = project_points(corners, K)
    (umin, vmin), (umax, vmax) = uv.min(0).tolist(), uv.max(0).tolist()
    u0, u1 = min(max(math.floor(umin), 0), w), min(max(math.ceil(umax) + 1, 0), w)
    v0, v1 = min(max(math.floor(vmin), 0), h), min(max(math.ceil(vmax) + 1, 0), h)
    if u1 <= u0 or v1 <= v0:
        return np.zeros((3, 0))
    s = max(1, math.ceil(math.sqrt((u1 - u0) * (v1 - v0) / max(max_pixels, 1))))
    z = depth[v0:v1:s, u0:u1:s]
    # most of the rectangle is background or occluder: pixels outside the camera-depth range
    # of [lower, upper] cannot lie in it and are not back-projected (for a rotation ``R`` the
    # range is that of the corners; otherwise every valid pixel is)
    with np.errstate(invalid="ignore"):
        if np.abs(R.T @ R - np.eye(3)).max() < 1e-6:
            ext = np.sort(np.stack([lower, upper]) * R[2], axis=0).sum(1).tolist()
            zlo, zhi = float(c[2]) + ext[0] - _DEPTH_SLACK, float(c[2]) + ext[1] + _DEPTH_SLACK
            valid = (z >= zlo) & (z <= zhi)  # NaN and inf fail too
            if zlo <= 0.0:
                valid &= z > 0
        else:
            valid = np.isfinite(z) & (z > 0)
    rows, cols = np.nonzero(valid)
    # back-projected as :func:`~shape_detector.frustum.pixel_points` does (same arithmetic,
    # so the same floats), minus the box centre, from a strided slice of the depth map
    zz = z[rows, cols].astype(np.float64)
    d = np.empty((rows.size, 3))
    d[:, 0] = ((np.arange(u0, u1, s) - K[0, 2]) / K[0, 0])[cols] * zz - c[0]
    d[:, 1] = ((np.arange(v0, v1, s) - K[1, 2]) / K[1, 1])[rows] * zz - c[1]
    d[:, 2] = zz - c[2]
    q = (d @ R).T
    # axis by axis: np.all(axis=1) on an (n, 3) array is several times slower
    keep = (q[0] >= lower[0]) & (q[0] <= upper[0]) & (q[1] >= lower[1]) & (q[1] <= upper[1])
    keep &= (q[2] >= lower[2]) & (q[2] <= upper[2])
    return np.ascontiguousarray(q[:, keep])  # contiguous rows: each count reads one axis at a time


def _occupied(local: np.ndarray, lo: np.ndarray, hi: np.ndarray, axis: int, sign: float, n: int, p: CarveParams) -> np.ndarray:
    """(n,) counts of the box-frame points ``local`` (3, m), one row per axis, in each of the
    ``n`` layers inside the face on ``axis`` / ``sign`` of the box ``[lo, hi]`` (points
    within ``floor_band`` of the box bottom left out)."""
    o1, o2 = [a for a in range(3) if a != axis]
    q = local
    keep = (q[o1] >= lo[o1]) & (q[o1] <= hi[o1]) & (q[o2] >= lo[o2]) & (q[o2] <= hi[o2])
    keep &= q[2] >= lo[2] + p.floor_band
    d = (hi[axis] - q[axis][keep]) if sign > 0 else (q[axis][keep] - lo[axis])
    k = np.floor(d / p.step).astype(np.int64)
    k = k[(k >= 0) & (k < n)]
    return np.bincount(k, minlength=n)


class _Carving:
    """One box being carved: its pose (``c``, ``R``, camera frame), its original half size,
    its current extent ``[lo, hi]`` and the limits ``stop_lo`` / ``stop_hi`` its faces may
    reach (box frame, metres), and (computed on first use) the measured points near it."""

    def __init__(self, obj: Object3D, local: np.ndarray, depth: np.ndarray, K: np.ndarray, p: CarveParams):
        """``local``: the object's own points in its box frame, sorted per column."""
        self.obj, self.depth, self.K, self.p = obj, depth, K, p
        self.R, self.c = obj.rotation, obj.center
        self.half = half = 0.5 * np.asarray(obj.size, dtype=np.float64)
        self.lo, self.hi = -half.copy(), half.copy()
        # a face moves in by at most max_frac of the size, and never past the object's own points
        self.stop_hi = np.maximum(half - p.max_frac * 2.0 * half, sorted_quantile(local, 1.0 - p.fg_quantile))
        self.stop_lo = np.minimum(-half + p.max_frac * 2.0 * half, sorted_quantile(local, p.fg_quantile))
        flat = obj.class_name in p.top_classes
        if flat:
            self.hi[2] = _capped_top(obj, self.R.T @ (-self.c), local, self.hi[2], self.stop_hi[2], p)
        self.faces = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))[: 5 if flat else 4]
        self._measured: np.ndarray | None = None

    def room(self) -> list[tuple[int, float, int]]:
        """``(axis, sign, n)`` of the faces that can still move, by ``n`` >= 1 layers."""
        p, lo, hi = self.p, self.lo, self.hi
        room = [(a, s, math.floor(((hi[a] - self.stop_hi[a]) if s > 0 else (self.stop_lo[a] - lo[a])) / p.step + 1e-9))
                for a, s in self.faces]
        return [f for f in room if f[2] > 0]

    @property
    def measured(self) -> np.ndarray:
        """Box-frame coordinates (3, n) of the measured points of the box's image rectangle
        (:func:`_box_points`) that a layer :func:`_occupied` is asked about can hold: above
        the floor band, within the box's extent or the faces' stops (a layer of slack covers
        the rounding of the room). The box only shrinks, so the first extent serves all
        later rounds."""
        if self._measured is None:
            p = self.p
            lower = np.minimum(self.lo, self.stop_hi) - p.step
            upper = np.maximum(self.hi, self.stop_lo) + p.step
            lower[2] = max(lower[2], self.lo[2] + p.floor_band)
            self._measured = _box_points(self.c, self.R, self.half, self.depth, self.K, p.max_pixels, lower, upper)
        return self._measured

    def clear(self, face: tuple[int, float, int], ok: list[bool]) -> list[bool]:
        """``ok`` (one per layer of ``face`` = ``(axis, sign, n)``) and-ed with: the layer
        holds at most ``max_occupied`` measured points."""
        if not any(ok):
            return ok
        occ = _occupied(self.measured, self.lo, self.hi, *face, self.p).tolist()
        return [o and m <= self.p.max_occupied for o, m in zip(ok, occ)]

    def pick(self, room: list[tuple[int, float, int]], outer: list[tuple[list[bool], list[int]]]) -> tuple[int, float, int] | None:
        """The face of ``room`` to carve this round, None when none may be: of the faces whose
        outer layer may be carved (``outer``: its :func:`_seen_layers` result per face), the
        one whose outer layer is seen through most, the first on ties. Occupancy is counted
        in that order, only until a face passes."""
        order = sorted((i for i, (seen, _) in enumerate(outer) if seen[0]), key=lambda i: -outer[i][1][0])
        for i in order:
            axis, sign, _ = room[i]
            if self.clear((axis, sign, 1), [True])[0]:
                return room[i]
        return None

    def done(self) -> Object3D:
        """The object, its box set to the carved extent if it changed."""
        if np.all(self.lo == -self.half) and np.all(self.hi == self.half):
            return self.obj
        self.obj.set_extent(self.lo, self.hi)
        return self.obj


def _seen_layers(jobs: list[tuple[_Carving, list[tuple[int, float, int]]]]) -> list[list[tuple[list[bool], list[int]]]]:
    """For each ``(box, faces)`` of ``jobs`` and each ``(axis, sign, n)`` of its faces: (seen,
    seen-through sample counts) of the ``n`` outermost layers inside that face of the box's
    current extent, ``seen`` = the layer passes the seen-through tests (not yet the
    occupancy one, :meth:`_Carving.clear`). The samples of all jobs (all boxes of a frame)
    are projected and looked up in the depth map in one go; each box's samples go to the
    camera frame as one block."""
    if not jobs:
        return []
    first = jobs[0][0]
    depth, K, p = first.depth, first.K, first.p
    # one row per layer: its box, face axis, sign and index inside the face
    box_l, axis_l, sign_l, layer_l = [], [], [], []
    for i, (_, faces) in enumerate(jobs):
        for axis, sign, n in faces:
            box_l += [i] * n
            axis_l += [axis] * n
            sign_l += [sign] * n
            layer_l += range(n)
    box_a = np.array(box_l)
    lo, hi = np.array([b.lo for b, _ in jobs])[box_a], np.array([b.hi for b, _ in jobs])[box_a]
    axis_a, din = np.array(axis_l), (np.array(layer_l) + 0.5) * p.step
    rows = np.arange(len(axis_l))
    # (layers, grid*grid, 3) box-frame samples: each layer a lattice over its face, at its depth
    pts = lo[:, None, :] + _face_lattices(p.grid)[axis_a] * (hi - lo)[:, None, :]
    pts[rows, :, axis_a] = np.where(np.array(sign_l) > 0, hi[rows, axis_a] - din, lo[rows, axis_a] + din)[:, None]
    blocks, start = [], 0
    for box, faces in jobs:
        n = sum(f[2] for f in faces)
        blocks.append(pts[start : start + n].reshape(-1, 3) @ box.R.T + box.c)
        start += n
    free, surface = _seen_through(np.concatenate(blocks), depth, K, p)
    free = free.reshape(len(rows), p.grid, p.grid)
    nf, ns = free.sum((1, 2)), surface.reshape(len(rows), -1).sum(1)
    seen = (nf >= p.min_free) & (ns <= p.max_surface_ratio * nf)
    # side faces: the lattice's second axis is z (up), its last rows on top
    seen &= (axis_a == 2) | (free[:, :, -p.top_rows :].sum((1, 2)) >= p.min_top_free)
    seen_l, nf_l = seen.tolist(), nf.tolist()
    out, start = [], 0
    for _, faces in jobs:
        res = []
        for _, _, n in faces:
            res.append((seen_l[start : start + n], nf_l[start : start + n]))
            start += n
        out.append(res)
    return out


def _capped_top(obj: Object3D, camera: np.ndarray, local: np.ndarray, top: float, stop: float, p: CarveParams) -> float:
    """The box-frame height of ``obj``'s top after the cap for a camera below it (see the
    module docstring): ``camera`` is the camera centre and ``local`` the object's points
    (sorted per column), both in the box frame; the top never goes below ``stop``."""
    if p.top_cap_quantile >= 1.0 or camera[2] >= top or obj.box2d is None:
        return top
    if float(obj.box2d[1]) <= p.top_cap_border:  # the object's top may lie above the image
        return top
    cap = float(sorted_quantile(local, p.top_cap_quantile)[2]) + p.top_cap_margin
    return max(min(top, cap), stop)


def carve_free_space(
    obj: Object3D,
    depth: np.ndarray,
    K: np.ndarray,
    points_cam: PointSource,
    params: CarveParams | None = None,
    min_prob: float | None = None,
) -> Object3D:
    """``obj`` with its side (and, for ``top_classes``, top) faces moved inwards out of
    seen-through space (in place; see the module docstring).

    ``depth``: HxW metres (optical frame z; NaN / 0 invalid), ``K``: 3x3 intrinsics,
    ``points_cam``: flat pixel indices -> camera-frame points (see
    :func:`shape_detector.point_fit.grow_to_points`); ``obj.pixel_index`` and
    ``obj.seg_labels`` select the object's own points (``min_prob``: those with a higher
    foreground probability, :func:`~shape_detector.point_fit.segmented_points`). Objects with
    fewer than ``point_fit.MIN_POINTS`` segmented points are returned unchanged.
    """
    return carve_all([obj], depth, K, points_cam, params, min_prob)[0]


def _start(obj: Object3D, depth: np.ndarray, K: np.ndarray, points_cam: PointSource, p: CarveParams,
           min_prob: float | None) -> _Carving | None:
    """``obj``'s carving state, or None when it is not carved (class, too few points)."""
    if obj.class_name not in p.classes:
        return None
    pts = segmented_points(obj, points_cam, min_prob)
    if pts is None:
        return None
    return _Carving(obj, np.sort((pts - obj.center) @ obj.rotation, axis=0), depth, K, p)


def carve_all(
    objects: list[Object3D],
    depth: np.ndarray,
    K: np.ndarray,
    points_cam: PointSource,
    params: CarveParams | None = None,
    min_prob: float | None = None,
) -> list[Object3D]:
    """:func:`carve_free_space` on each object (in place; same arguments).

    Each box is carved on its own, but the boxes' rounds run side by side, so that a
    round's seen-through tests of all the frame's boxes share one projection and one depth
    lookup: most boxes find no face to carve in their first round and cost little else.
    """
    if len({id(o) for o in objects}) < len(objects):  # the same object twice: carve it twice, in turn
        return [carve_all([o], depth, K, points_cam, params, min_prob)[0] for o in objects]
    p = params or CarveParams()
    boxes = [_start(o, depth, K, points_cam, p, min_prob) for o in objects]
    active = [b for b in boxes if b is not None]
    rnd = 0
    while active:
        rooms = [(b, b.room()) for b in active if rnd < 2 * len(b.faces)]
        rooms = [(b, room) for b, room in rooms if room]
        # the outer layer of each face that can still move: most boxes stop here
        outer = _seen_layers([(b, [(a, s, 1) for a, s, _ in room]) for b, room in rooms])
        moves = [(b, face) for (b, room), res in zip(rooms, outer) if (face := b.pick(room, res)) is not None]
        # how many layers the picked face gives up: those up to the first that may not be carved
        deep = iter(_seen_layers([(b, [face]) for b, face in moves if face[2] > 1]))
        for b, (axis, sign, n) in moves:
            run = 1
            if n > 1:
                ok = b.clear((axis, sign, n), next(deep)[0][0])
                run = ok.index(False) if not all(ok) else n
            if sign > 0:
                b.hi[axis] -= run * p.step
            else:
                b.lo[axis] += run * p.step
        active = [b for b, _ in moves]
        rnd += 1
    return [o if b is None else b.done() for o, b in zip(objects, boxes)]
