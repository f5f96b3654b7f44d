"""Intersection over union of 2D boxes and of oriented 3D boxes: the one implementation the
post-processing (NMS), training and evaluation share.

3D boxes are given as ``center`` (3,), full ``size`` (3,) and ``rotation`` (3,3) whose
columns are the box axes (see :mod:`shape_detector.types`), all in one frame (usually
the camera optical frame).

Exact path (yaw-only boxes)
---------------------------
Furniture boxes rotate about gravity only, so two boxes that share a vertical axis
intersect in a prism: (footprint polygon intersection) x (vertical interval overlap).
:func:`box3d_iou` expresses both boxes in the upright frame ``U`` built from ``up``
(:func:`shape_detector.geometry.upright_rotation`), or -- when ``up`` is not given --
from the z column of the first box's rotation, which is the gravity-up axis by the
package convention. Any box axis that is parallel to that vertical (not only the z
column) is accepted as the box's vertical axis. The two footprint rectangles are
intersected with Sutherland--Hodgman convex polygon clipping (:func:`clip_convex`) and
the area comes from the shoelace formula, so the result is exact up to floating point.

Fallback (boxes with different vertical axes)
---------------------------------------------
When some box has no axis parallel to the vertical (within ``vertical_tol``), the
intersection is no longer a prism. :func:`box3d_iou_grid` then *approximates* the
intersection volume by counting the centres of a regular ``resolution**3`` grid laid over
the intersection of the two boxes' axis-aligned bounding boxes that fall inside both
boxes (deterministic; the volumes of the two boxes themselves are exact). The error is
``O(1 / resolution)`` relative to that bounding-box overlap; the default 64 gives about
1e-2 absolute IoU error in the worst case. :func:`box3d_iou` uses it automatically
unless ``fallback=False``, in which case it raises ``ValueError``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .geometry import box_corners, normalize, points_in_box, upright_rotation

#: ``1 - |cos(angle)|`` below which a box axis counts as parallel to the vertical
#: (1e-5 is about 0.26 degrees).
VERTICAL_TOL = 1e-5


# --------------------------------------------------------------------------- 2D boxes
def box2d_iou(a: Sequence[float], b: Sequence[float]) -> float:
    """IoU of two axis-aligned 2D boxes ``(x1, y1, x2, y2, ...)`` (pixel edges, extra items ignored).

    Areas are ``(x2 - x1) * (y2 - y1)`` (the package's edge convention, no ``+1``).
    Returns 0 for empty or degenerate boxes.
    """
    ax1, ay1, ax2, ay2 = (float(v) for v in a[:4])
    bx1, by1, bx2, by2 = (float(v) for v in b[:4])
    iw = min(ax2, bx2) - max(ax1, bx1)
    ih = min(ay2, by2) - max(ay1, by1)
    if iw <= 0.0 or ih <= 0.0:
        return 0.0
    inter = iw * ih
    area_a = max(ax2 - ax1, 0.0) * max(ay2 - ay1, 0.0)
    area_b = max(bx2 - bx1, 0.0) * max(by2 - by1, 0.0)
    union = area_a + area_b - inter
    return float(inter / union) if union > 0.0 else 0.0


# ------------------------------------------------------------------ polygon clipping
def polygon_area(poly: np.ndarray) -> float:
    """Signed area of a simple polygon (K,2) (shoelace); positive when counter-clockwise."""
    p = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
    if len(p) < 3:
        return 0.0
    x, y = p[:, 0], p[:, 1]
    return float(0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))


def _ccw(poly: np.ndarray) -> np.ndarray:
    return poly[::-1].copy() if polygon_area(poly) < 0.0 else poly


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland--Hodgman: the part (K,2) of polygon ``subject`` inside convex polygon ``clip``.

    Both are (N,2) vertex lists in either winding (they are made counter-clockwise
    first); ``subject`` must be convex for the result to be a single polygon (true for
    rectangles). Returns an empty (0,2) array when they do not overlap.
    """
    out = [tuple(p) for p in _ccw(np.asarray(subject, dtype=np.float64).reshape(-1, 2))]
    clip = _ccw(np.asarray(clip, dtype=np.float64).reshape(-1, 2))
    n = len(clip)
    for i in range(n):
        if not out:
            break
        e0, e1 = clip[i], clip[(i + 1) % n]
        ex, ey = e1[0] - e0[0], e1[1] - e0[1]

        def side(p: tuple[float, float], e0: np.ndarray = e0, ex: float = ex, ey: float = ey) -> float:
            # > 0: left of the edge, i.e. inside a counter-clockwise polygon (edge bound per iteration)
            return ex * (p[1] - e0[1]) - ey * (p[0] - e0[0])

        inp, out = out, []
        prev = inp[-1]
        s_prev = side(prev)
        for cur in inp:
            s_cur = side(cur)
            if s_cur >= 0.0:
                if s_prev < 0.0:
                    t = s_prev / (s_prev - s_cur)
                    out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
                out.append(cur)
            elif s_prev >= 0.0:
                t = s_prev / (s_prev - s_cur)
                out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
            prev, s_prev = cur, s_cur
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


# ------------------------------------------------------------------------- 3D boxes
def vertical_axis(rotation: np.ndarray, up: np.ndarray, tol: float) -> int | None:
    """Index of the box axis parallel to ``up``, or None when none is (within ``tol``)."""
    dots = np.abs(np.asarray(rotation, dtype=np.float64).T @ up)
    k = int(np.argmax(dots))
    return k if dots[k] >= 1.0 - tol else None


def box_prism(center, size, rotation, R_cu: np.ndarray, k: int) -> tuple[np.ndarray, float, float]:
    """Footprint (4,2) in the upright frame U's xy plane (``R_cu``: U's axes in the camera frame)
    and the vertical interval [zmin, zmax] of a box whose axis ``k`` is vertical."""
    c = R_cu.T @ np.asarray(center, dtype=np.float64).reshape(3)
    rot_u = R_cu.T @ np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    s = np.asarray(size, dtype=np.float64).reshape(3)
    i, j = [a for a in range(3) if a != k]
    hi = 0.5 * s[i] * rot_u[:2, i]
    hj = 0.5 * s[j] * rot_u[:2, j]
    cxy = c[:2]
    foot = np.stack([cxy + hi + hj, cxy - hi + hj, cxy - hi - hj, cxy + hi - hj])
    return foot, c[2] - 0.5 * s[k], c[2] + 0.5 * s[k]


def box3d_iou_grid(center_a, size_a, rot_a, center_b, size_b, rot_b, resolution: int = 64) -> float:
    """Approximate 3D IoU of two arbitrarily oriented boxes (see the module docstring).

    Intersection volume = (share of grid-cell centres inside both boxes) x (volume of the
    overlap of the two axis-aligned bounding boxes); the grid has ``resolution`` cells per
    axis. Box volumes are exact.
    """
    ca, cb = box_corners(center_a, size_a, rot_a), box_corners(center_b, size_b, rot_b)
    lo = np.maximum(ca.min(0), cb.min(0))
    hi = np.minimum(ca.max(0), cb.max(0))
    vol_a = float(np.prod(np.asarray(size_a, dtype=np.float64)))
    vol_b = float(np.prod(np.asarray(size_b, dtype=np.float64)))
    if np.any(hi <= lo) or vol_a <= 0.0 or vol_b <= 0.0:
        return 0.0
    r = int(resolution)
    axes = [lo[d] + (np.arange(r) + 0.5) * (hi[d] - lo[d]) / r for d in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = points_in_box(g, center_a, size_a, rot_a) & points_in_box(g, center_b, size_b, rot_b)
    inter = float(inside.mean()) * float(np.prod(hi - lo))
    union = vol_a + vol_b - inter
    return float(inter / union) if union > 0.0 else 0.0


def box3d_iou(
    center_a,
    size_a,
    rot_a,
    center_b,
    size_b,
    rot_b,
    up: np.ndarray | None = None,
    *,
    fallback: bool = True,
    vertical_tol: float = VERTICAL_TOL,
    grid_resolution: int = 64,
) -> float:
    """3D IoU of two oriented boxes; exact when both are yaw-only about a common vertical.

    ``up``: the vertical (gravity-up) direction in the boxes' frame; None -> the z column
    of ``rot_a``. If a box has no axis parallel to it, the grid approximation
    :func:`box3d_iou_grid` is used (or ``ValueError`` raised when ``fallback`` is False).
    Degenerate boxes (zero volume) give 0.
    """
    rot_a = np.asarray(rot_a, dtype=np.float64).reshape(3, 3)
    rot_b = np.asarray(rot_b, dtype=np.float64).reshape(3, 3)
    u = normalize(rot_a[:, 2] if up is None else np.asarray(up, dtype=np.float64).reshape(3))
    ka = vertical_axis(rot_a, u, vertical_tol)
    kb = vertical_axis(rot_b, u, vertical_tol)
    if ka is None or kb is None:
        if not fallback:
            raise ValueError("boxes do not share a vertical axis; exact prism IoU not applicable")
        return box3d_iou_grid(center_a, size_a, rot_a, center_b, size_b, rot_b, grid_resolution)
    vol_a = float(np.prod(np.asarray(size_a, dtype=np.float64)))
    vol_b = float(np.prod(np.asarray(size_b, dtype=np.float64)))
    if vol_a <= 0.0 or vol_b <= 0.0:
        return 0.0
    R_cu = upright_rotation(u)
    fa, za0, za1 = box_prism(center_a, size_a, rot_a, R_cu, ka)
    fb, zb0, zb1 = box_prism(center_b, size_b, rot_b, R_cu, kb)
    dz = min(za1, zb1) - max(za0, zb0)
    if dz <= 0.0:
        return 0.0
    # quick reject on the footprints' bounding circles
    ra = 0.5 * np.hypot(*np.delete(np.asarray(size_a, float), ka))
    rb = 0.5 * np.hypot(*np.delete(np.asarray(size_b, float), kb))
    if np.linalg.norm(fa.mean(0) - fb.mean(0)) >= ra + rb:
        return 0.0
    area = abs(polygon_area(clip_convex(fa, fb)))
    inter = area * dz
    union = vol_a + vol_b - inter
    return float(min(max(inter / union, 0.0), 1.0)) if union > 0.0 else 0.0


def _box_params(box: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(box, dict):
        return np.asarray(box["center"]), np.asarray(box["size"]), np.asarray(box["rotation"])
    return box.center, box.size, box.rotation


def iou_matrix(boxes_a: Sequence[Any], boxes_b: Sequence[Any], up: np.ndarray | None = None, **kw: Any) -> np.ndarray:
    """(A,B) 3D IoUs between two lists of Cuboid-like objects (``.center/.size/.rotation``
    attributes, or dicts with those keys). ``up`` and ``kw`` go to :func:`box3d_iou`."""
    out = np.zeros((len(boxes_a), len(boxes_b)), dtype=np.float64)
    pb = [_box_params(b) for b in boxes_b]
    for i, a in enumerate(boxes_a):
        ca, sa, ra = _box_params(a)
        for j, (cb, sb, rb) in enumerate(pb):
            out[i, j] = box3d_iou(ca, sa, ra, cb, sb, rb, up, **kw)
    return out


def _edges(boxes: Sequence[Sequence[float]]) -> np.ndarray:
    """(N, 4) float ``x1, y1, x2, y2`` of ``(x1, y1, x2, y2, ...)`` boxes."""
    if len(boxes) == 0:
        return np.zeros((0, 4))
    return np.array([[float(v) for v in box[:4]] for box in boxes])


def box2d_iou_matrix(boxes_a: Sequence[Sequence[float]], boxes_b: Sequence[Sequence[float]]) -> np.ndarray:
    """(A,B) 2D IoUs between two lists of ``(x1, y1, x2, y2, ...)`` boxes, as :func:`box2d_iou`
    gives them one pair at a time (degenerate boxes: 0)."""
    a, b = _edges(boxes_a), _edges(boxes_b)
    iw = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0.0, None)
    ih = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0.0, None)
    inter = iw * ih
    area_a = np.clip(a[:, 2] - a[:, 0], 0.0, None) * np.clip(a[:, 3] - a[:, 1], 0.0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0.0, None) * np.clip(b[:, 3] - b[:, 1], 0.0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0.0)
