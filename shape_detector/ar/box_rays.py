"""Ray casts against oriented boxes (world frame, metres): the slab method, one compiled loop.

Each ray keeps its nearest entry into a box: the largest of the three slab entries, where the
box's own axes order them; a box that holds the ray's origin is skipped (a camera inside a
loosely estimated box still sees what is in front of it). Compiled with numba like
:mod:`.surface_rays` (cached on disk after the first call).
"""

from __future__ import annotations

import numba
import numpy as np

from .row_split import run_rows


def first_boxes(o: np.ndarray, d: np.ndarray, centers: np.ndarray, half: np.ndarray, rot: np.ndarray,
                max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first box each ray ``o`` (n,3) + t ``d`` (n,3, unit; NaN rows never hit) enters
    with ``0 < t <= max_distance``, of boxes ``centers`` (P,3), ``half`` (P,3) half extents and
    ``rot`` (P,3,3) (columns = box axes): distance (n,) (inf: none), box index (n,) (-1: none),
    outward unit normal (n,3) of the face entered (zeros: none)."""
    n = len(o)
    dist, best, normal = np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 3))
    if len(centers):
        o, d = np.ascontiguousarray(o, np.float64), np.ascontiguousarray(d, np.float64)
        c, h, r = (np.ascontiguousarray(a, np.float64) for a in (centers, half, rot))
        run_rows(lambda a, b: _first_boxes(o[a:b], d[a:b], c, h, r, float(max_distance), dist[a:b], best[a:b],
                                           normal[a:b]), n)
    return dist, best, normal


@numba.njit(cache=True, nogil=True)
def _first_boxes(o, d, centers, half, rot, max_distance, dist, best, normal):
    """``first_boxes`` for every ray, writing ``dist``, ``best`` and ``normal`` in place."""
    for i in range(o.shape[0]):
        if not (np.isfinite(d[i, 0]) and np.isfinite(d[i, 1]) and np.isfinite(d[i, 2])):
            continue
        t_best, b_best, ax_best, sign_best = np.inf, -1, 0, 0.0
        for b in range(centers.shape[0]):
            t_near, t_far, axis, sign = -np.inf, np.inf, 0, 0.0
            for k in range(3):
                ol = ((o[i, 0] - centers[b, 0]) * rot[b, 0, k] + (o[i, 1] - centers[b, 1]) * rot[b, 1, k]
                      + (o[i, 2] - centers[b, 2]) * rot[b, 2, k])
                dl = d[i, 0] * rot[b, 0, k] + d[i, 1] * rot[b, 1, k] + d[i, 2] * rot[b, 2, k]
                if abs(dl) < 1e-20:  # parallel to this slab: inside it or never
                    if abs(ol) > half[b, k]:
                        t_near = np.inf
                        break
                    continue
                t1, t2 = (-half[b, k] - ol) / dl, (half[b, k] - ol) / dl
                lo, hi = min(t1, t2), max(t1, t2)
                if lo > t_near:
                    t_near, axis, sign = lo, k, -1.0 if dl > 0 else 1.0
                t_far = min(t_far, hi)
            if t_near <= t_far and 0.0 < t_near <= max_distance and t_near < t_best:
                t_best, b_best, ax_best, sign_best = t_near, b, axis, sign
        if b_best >= 0:
            dist[i], best[i] = t_best, b_best
            for a in range(3):
                normal[i, a] = rot[b_best, a, ax_best] * sign_best
