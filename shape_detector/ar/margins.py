"""Safety margins for planning where the map is unsure of a box (world frame, z up, metres).

A track's box is the weighted mean of many detections. Where those detections disagree on
a face (:attr:`SceneObject.face_sd`, their spread), the fused face is often off by about as
much (docs/experiments/open-targets.md). Before planning, :func:`padded_grid` therefore grows
the occupied footprint of each object that blocks the agent by ``uncertainty`` standard
deviations per face, at most :data:`MAX_MARGIN`. Well-seen faces keep their place, so free
passages beside them stay open.

It applies only to an object whose whole box footprint is occupied in the grid
(:data:`BLOCKING_SHARE` of its cells), i.e. one that blocks the agent over its whole extent.
A table above a small robot, whose grid cells are only its legs, keeps the space under it.

A track the map doubts (its own score, :attr:`SceneObject.track_score`, below
:data:`DOUBT_SCORE`: mostly clutter and second tracks of one object) still blocks plans, but
:func:`without_doubtful` gives the grid in which a plan may cross it where nothing else gets
through (the planner's squeeze, :mod:`.planning`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..scene.grid import OCCUPIED, UNKNOWN, NavGrid, footprint_mask
from ..scene.types import SceneObject, object_parts

#: standard deviations of a face's spread added to it by default (0 = no margins)
UNCERTAINTY = 0.5
#: largest margin added to one face, metres
MAX_MARGIN = 0.10
#: share of an object's box footprint cells that must be occupied for its margins to apply
BLOCKING_SHARE = 0.8
#: objects scored below this are doubtful (see the module doc)
DOUBT_SCORE = 0.6


def padded_grid(grid: NavGrid, objects: Sequence[SceneObject], uncertainty: float = UNCERTAINTY,
                max_margin: float = MAX_MARGIN) -> NavGrid:
    """A copy of ``grid`` with the cells around each blocking object's box marked occupied out
    to ``min(uncertainty * face_sd, max_margin)`` beyond each of its four side faces (see
    the module doc); ``grid`` itself when nothing is added."""
    if not (np.isfinite(uncertainty) and uncertainty >= 0.0):
        raise ValueError(f"uncertainty={uncertainty} must be finite and >= 0 (standard deviations)")
    if uncertainty == 0.0 or grid.data.size == 0:
        return grid
    out: np.ndarray | None = None
    for o in objects:
        margin = np.minimum(uncertainty * np.abs(np.asarray(o.face_sd, dtype=np.float64).reshape(4)), max_margin)
        if not np.any(margin > 0.5 * grid.resolution):
            continue
        box = footprint_mask(grid, o.center, o.size, o.rotation)
        if box is None or np.mean(grid.data[box[0], box[1]][box[2]] == OCCUPIED) < BLOCKING_SHARE:
            continue
        R = np.asarray(o.rotation, dtype=np.float64)
        lo = -0.5 * np.asarray(o.size[:2], dtype=np.float64) - margin[[0, 2]]
        hi = 0.5 * np.asarray(o.size[:2], dtype=np.float64) + margin[[1, 3]]
        center = np.asarray(o.center, dtype=np.float64) + R[:, :2] @ (0.5 * (lo + hi))
        grown = footprint_mask(grid, center, np.r_[hi - lo, float(o.size[2])], R)
        if grown is None:
            continue
        if out is None:
            out = grid.data.copy()
        rs, cs, m = grown
        out[rs, cs][m] = OCCUPIED
    if out is None:
        return grid
    return NavGrid(grid.resolution, grid.origin.copy(), out, grid.floor_z)


def _footprints(grid: NavGrid, o: SceneObject) -> list[tuple[slice, slice, np.ndarray]]:
    """The grid windows under an object's parts (its box when it has none)."""
    return [w for p in object_parts(o) if (w := footprint_mask(grid, p.center, p.size, p.rotation)) is not None]


def without_doubtful(grid: NavGrid, objects: Sequence[SceneObject], min_score: float = DOUBT_SCORE) -> NavGrid:
    """A copy of ``grid`` whose occupied cells under the parts of objects whose own score
    (:attr:`SceneObject.own_score`) is below ``min_score``, and under no other object's, are unknown;
    ``grid`` itself when there are none."""
    doubtful = [o for o in objects if o.own_score < min_score]
    if not doubtful or grid.data.size == 0:
        return grid
    sure = np.zeros(grid.data.shape, bool)
    for o in objects:
        if o.own_score >= min_score:
            for rs, cs, m in _footprints(grid, o):
                sure[rs, cs] |= m
    out = grid.data.copy()
    for o in doubtful:
        for rs, cs, m in _footprints(grid, o):
            window = out[rs, cs]
            window[m & (window == OCCUPIED) & ~sure[rs, cs]] = UNKNOWN
    return NavGrid(grid.resolution, grid.origin.copy(), out, grid.floor_z)
