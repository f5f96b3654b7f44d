"""Greedy 3D non-maximum suppression over oriented, yaw-only boxes."""

from __future__ import annotations

import copy

import numpy as np

from ..types import Object3D


def overlap_ratios(a: Object3D, b: Object3D) -> tuple[float, float]:
    """(IoU, intersection / smaller volume) of two boxes; the second catches nested boxes."""
    from ..box_iou import box3d_iou

    iou = box3d_iou(a.center, a.size, a.rotation, b.center, b.size, b.rotation)
    va, vb = float(np.prod(a.size)), float(np.prod(b.size))
    inter = iou * (va + vb) / (1.0 + iou)
    return iou, inter / max(min(va, vb), 1e-12)


def _prisms(objects: list[Object3D]) -> list[tuple[np.ndarray, float, float, float]] | None:
    """Per box (footprint (4,2) in the upright frame, z min, z max, volume), all boxes
    sharing the first one's vertical; None when some box is not yaw-only about it."""
    from ..box_iou import VERTICAL_TOL, box_prism, vertical_axis
    from ..geometry import normalize, upright_rotation

    up = normalize(np.asarray(objects[0].rotation, np.float64)[:, 2])
    R_cu = upright_rotation(up)
    out = []
    for o in objects:
        k = vertical_axis(o.rotation, up, VERTICAL_TOL)
        if k is None:
            return None
        foot, z0, z1 = box_prism(o.center, o.size, o.rotation, R_cu, k)
        foot = np.ascontiguousarray(foot, dtype=np.float32)
        e1, e2 = foot[1] - foot[0], foot[2] - foot[1]
        if e1[0] * e2[1] - e1[1] * e2[0] < 0:
            foot = foot[::-1].copy()  # counter-clockwise for OpenCV
        out.append((foot, z0, z1, float(np.prod(np.asarray(o.size, np.float64)))))
    return out


def _prism_overlap(a, b) -> tuple[float, float]:
    """(IoU, intersection / smaller volume) of two prisms from :func:`_prisms`; footprints
    intersected by OpenCV's convex clipping (float32: relative error ~1e-6)."""
    import cv2

    (fa, za0, za1, va), (fb, zb0, zb1, vb) = a, b
    dz = min(za1, zb1) - max(za0, zb0)
    if dz <= 0.0 or va <= 0.0 or vb <= 0.0:
        return 0.0, 0.0
    area, _ = cv2.intersectConvexConvex(fa, fb)
    inter = max(float(area), 0.0) * dz
    union = va + vb - inter
    return (inter / union if union > 0 else 0.0), inter / min(va, vb)


def nms_3d(
    objects: list[Object3D],
    iou_threshold: float = 0.25,
    containment_threshold: float = 0.7,
    decay: float = 0.0,
    min_score: float = 0.0,
) -> list[Object3D]:
    """Objects sorted by score, dropping any that overlaps a kept one by more than
    ``iou_threshold`` (3D IoU) or lies mostly inside it / around it (intersection over the
    smaller volume above ``containment_threshold``).

    ``decay`` > 0 keeps the suppressed objects instead, as copies with their ``score`` and
    ``class_scores`` times ``decay``, after the kept ones (a fixed-factor Soft-NMS, Bodla et
    al. 2017): a touching neighbour that lost to a merged box still counts at low
    confidence, while the score threshold of a live node (0.3 against scores <= ``decay``)
    still drops every duplicate. Suppressed objects suppress nothing; those whose decayed
    score falls below ``min_score`` (the caller's score threshold) are not copied at all.

    Class-agnostic: two pieces of furniture do not share space, so overlapping boxes of
    different classes are duplicates of one object from different proposals (a part of
    an object proposed alone, or an object merged with its neighbour). The footprints and
    height intervals are computed once per box (all boxes of a frame share gravity), and
    boxes whose bounding spheres do not touch are never intersected.
    """
    order, kept = nms_keep(objects, iou_threshold, containment_threshold)
    kept_set = set(kept)
    suppressed: list[Object3D] = []
    if decay > 0.0:
        for i in order:
            if i not in kept_set and objects[i].score * decay >= min_score:
                o = copy.copy(objects[i])
                o.score = float(o.score) * decay
                if o.class_scores is not None:
                    o.class_scores = np.asarray(o.class_scores, dtype=np.float64) * decay
                suppressed.append(o)
    return [objects[i] for i in kept] + suppressed


def nms_keep(
    objects: list[Object3D], iou_threshold: float = 0.25, containment_threshold: float = 0.7
) -> tuple[list[int], list[int]]:
    """Greedy NMS as :func:`nms_3d` without rescoring: ``(order, kept)``, the indices of
    ``objects`` by descending score and the kept ones among them (in that order)."""
    order = sorted(range(len(objects)), key=lambda i: -objects[i].score)
    if not order:
        return [], []
    ordered = [objects[i] for i in order]
    centers = np.array([np.asarray(o.center, np.float64).reshape(3) for o in ordered])
    radii = np.array([0.5 * float(np.linalg.norm(o.size)) for o in ordered])
    near = np.linalg.norm(centers[:, None] - centers[None], axis=-1) < radii[:, None] + radii[None]
    prisms = _prisms(ordered)

    def overlap(i: int, k: int) -> tuple[float, float]:
        if prisms is None:
            return overlap_ratios(ordered[i], ordered[k])
        return _prism_overlap(prisms[i], prisms[k])

    kept: list[int] = []
    for i in range(len(ordered)):
        if all(
            iou <= iou_threshold and contained <= containment_threshold
            for iou, contained in (overlap(i, k) for k in kept if near[i, k])
        ):
            kept.append(i)
    return order, [order[i] for i in kept]
