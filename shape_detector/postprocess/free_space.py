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

Its measured effect is in docs/experiments/code-comment-numbers.md. Pure numpy; boxes
change through :meth:`Object3D.set_extent`, so primitives stretch with them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..classes import CLASSES
from ..frustum import pixel_points
from ..geometry import box_corners, measured_depth, project_points
from .point_fit import PointSource, segmented_points, sorted_quantile
from ..types import Object3D


#: flat-topped furniture: the top surface spans the footprint
FLAT_TOPPED = frozenset({"table", "desk", "dresser", "night_stand", "bookshelf"})
#: classes carved at all: not chairs, whose open backs and thin rails the depth map sees
#: through (carving them made more chairs worse at 3D IoU >= 0.5 than it made better)
CARVED = frozenset(CLASSES) - {"chair"}


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


def _layer_samples(lo: np.ndarray, hi: np.ndarray, axis: int, sign: float, depth_in: np.ndarray, grid: int) -> np.ndarray:
    """Box-frame sample points (L, grid*grid, 3) of the box ``[lo, hi]``'s layers at the
    mid-depths ``depth_in`` (L,) inside its face on ``axis`` / ``sign``, each a ``grid``
    x ``grid`` lattice over the face."""
    o1, o2 = [a for a in range(3) if a != axis]
    t1, t2 = _unit_lattice(grid)
    pts = np.empty((len(depth_in), grid * grid, 3))
    pts[:, :, o1] = lo[o1] + t1 * (hi[o1] - lo[o1])
    pts[:, :, o2] = lo[o2] + t2 * (hi[o2] - lo[o2])
    pts[:, :, axis] = (hi[axis] - depth_in if sign > 0 else lo[axis] + depth_in)[:, None]
    return pts


@lru_cache(maxsize=8)
def _unit_lattice(grid: int) -> tuple[np.ndarray, np.ndarray]:
    """The first and second coordinates (grid*grid,) of a ``grid`` x ``grid`` lattice of cell
    centres in [0, 1]^2, the second varying fastest (read-only)."""
    t = (np.arange(grid) + 0.5) / grid
    a, b = np.repeat(t, grid), np.tile(t, grid)
    a.flags.writeable = b.flags.writeable = False
    return a, b


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


def _box_points(c: np.ndarray, R: np.ndarray, half: np.ndarray, depth: np.ndarray, K: np.ndarray, max_pixels: int) -> np.ndarray:
    """Box-frame points (n, 3) of the valid depth pixels in the image rectangle the box
    projects into (every ``s``-th row and column, ``s`` chosen to keep about
    ``max_pixels``). Empty when the box lies behind the camera."""
    h, w = depth.shape
    corners = box_corners(c, 2.0 * half, R)
    if np.any(corners[:, 2] <= 0.05):
        return np.zeros((0, 3))
    uv = project_points(corners, K)
    u0, u1 = int(np.clip(np.floor(uv[:, 0].min()), 0, w)), int(np.clip(np.ceil(uv[:, 0].max()) + 1, 0, w))
    v0, v1 = int(np.clip(np.floor(uv[:, 1].min()), 0, h)), int(np.clip(np.ceil(uv[:, 1].max()) + 1, 0, h))
    if u1 <= u0 or v1 <= v0:
        return np.zeros((0, 3))
    s = max(1, int(np.ceil(np.sqrt((u1 - u0) * (v1 - v0) / max(max_pixels, 1)))))
    vv, uu = np.mgrid[v0:v1:s, u0:u1:s]
    cam = pixel_points(depth, K, (vv * w + uu).ravel())
    cam = cam[np.isfinite(cam[:, 2]) & (cam[:, 2] > 0)]
    return (cam - c) @ R


def _occupied(local: np.ndarray, lo: np.ndarray, hi: np.ndarray, axis: int, sign: float, n: int, p: CarveParams) -> np.ndarray:
    """(n,) counts of the box-frame points ``local`` in each of the ``n`` layers inside the
    face on ``axis`` / ``sign`` of the box ``[lo, hi]`` (points within ``floor_band`` of
    the box bottom left out)."""
    o1, o2 = [a for a in range(3) if a != axis]
    q = local
    keep = (q[:, o1] >= lo[o1]) & (q[:, o1] <= hi[o1]) & (q[:, o2] >= lo[o2]) & (q[:, o2] <= hi[o2])
    keep &= q[:, 2] >= lo[2] + p.floor_band
    d = (hi[axis] - q[keep, axis]) if sign > 0 else (q[keep, axis] - lo[axis])
    k = np.floor(d / p.step).astype(np.int64)
    k = k[(k >= 0) & (k < n)]
    return np.bincount(k, minlength=n)


class _View:
    """One box's view of the frame: pose, depth, intrinsics, and (computed on first use)
    the box-frame measured points of its image rectangle."""

    def __init__(self, c: np.ndarray, R: np.ndarray, half: np.ndarray, depth: np.ndarray, K: np.ndarray, p: CarveParams):
        self.c, self.R, self.half, self.depth, self.K, self.p = c, R, half, depth, K, p
        self._measured: np.ndarray | None = None

    @property
    def measured(self) -> np.ndarray:
        if self._measured is None:
            self._measured = _box_points(self.c, self.R, self.half, self.depth, self.K, self.p.max_pixels)
        return self._measured


def _layers_ok(
    lo: np.ndarray, hi: np.ndarray, faces: list[tuple[int, float, int]], view: _View
) -> list[tuple[np.ndarray, np.ndarray]]:
    """For each ``(axis, sign, n)`` of ``faces``: (ok (n,) bool, seen-through counts (n,)) of
    the ``n`` outermost layers inside that face of the box ``[lo, hi]`` (box frame of
    ``view``). All samples are projected in one go."""
    c, R, depth, K, p = view.c, view.R, view.depth, view.K, view.p
    samples = [_layer_samples(lo, hi, axis, sign, (np.arange(n) + 0.5) * p.step, p.grid) for axis, sign, n in faces]
    free_all, surface_all = _seen_through(np.concatenate(samples) @ R.T + c, depth, K, p)
    out, start = [], 0
    for axis, sign, n in faces:
        free, surface = free_all[start : start + n], surface_all[start : start + n]
        start += n
        nf, ns = free.sum(1), surface.sum(1)
        ok = (nf >= p.min_free) & (ns <= p.max_surface_ratio * nf)
        if axis != 2:  # side face: the lattice's second axis is z (up), its last rows on top
            ok &= free.reshape(n, p.grid, p.grid)[:, :, -p.top_rows :].sum((1, 2)) >= p.min_top_free
        if ok.any():
            ok &= _occupied(view.measured, lo, hi, axis, sign, n, p) <= p.max_occupied
        out.append((ok, nf))
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
    p = params or CarveParams()
    if obj.class_name not in p.classes:
        return obj
    pts = segmented_points(obj, points_cam, min_prob)
    if pts is None:
        return obj
    R, c = obj.rotation, obj.center
    half = 0.5 * np.asarray(obj.size, dtype=np.float64)
    local = np.sort((pts - c) @ R, axis=0)
    lo, hi = -half.copy(), half.copy()
    # a face moves in by at most max_frac of the size, and never past the object's own points
    stop_hi = np.maximum(half - p.max_frac * 2.0 * half, sorted_quantile(local, 1.0 - p.fg_quantile))
    stop_lo = np.minimum(-half + p.max_frac * 2.0 * half, sorted_quantile(local, p.fg_quantile))
    if obj.class_name in p.top_classes:
        hi[2] = _capped_top(obj, R.T @ (-c), local, hi[2], stop_hi[2], p)
    view = _View(c, R, half, depth, K, p)
    faces = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))[: 5 if obj.class_name in p.top_classes else 4]
    for _ in range(2 * len(faces)):  # rounds: the face whose outer layer is seen through most first
        room = [(a, s, int(np.floor(((hi[a] - stop_hi[a]) if s > 0 else (stop_lo[a] - lo[a])) / p.step + 1e-9)))
                for a, s in faces]
        room = [f for f in room if f[2] > 0]
        if not room:
            break
        outer = _layers_ok(lo, hi, [(a, s, 1) for a, s, _ in room], view)  # most faces stop here
        score = [int(nf[0]) if ok[0] else -1 for ok, nf in outer]
        k = int(np.argmax(score))
        if score[k] < 0:
            break
        axis, sign, n = room[k]
        run = 1
        if n > 1:
            ok, _ = _layers_ok(lo, hi, [room[k]], view)[0]
            run = int(np.argmin(ok)) if not ok.all() else n
        if sign > 0:
            hi[axis] -= run * p.step
        else:
            lo[axis] += run * p.step
    if np.all(lo == -half) and np.all(hi == half):
        return obj
    obj.set_extent(lo, hi)
    return obj


def carve_all(
    objects: list[Object3D],
    depth: np.ndarray,
    K: np.ndarray,
    points_cam: PointSource,
    params: CarveParams | None = None,
    min_prob: float | None = None,
) -> list[Object3D]:
    """:func:`carve_free_space` on each object."""
    return [carve_free_space(o, depth, K, points_cam, params, min_prob) for o in objects]
