"""Greedy 3D non-maximum suppression over oriented, yaw-only boxes."""

from __future__ import annotations

import numpy as np

from .types import Object3D


def overlap_ratios(a: Object3D, b: Object3D) -> tuple[float, float]:
    """(IoU, intersection / smaller volume) of two boxes; the second catches nested boxes."""
    from .evaluation.iou import box3d_iou

    iou = box3d_iou(a.center, a.size, a.rotation, b.center, b.size, b.rotation)
    va, vb = float(np.prod(a.size)), float(np.prod(b.size))
    inter = iou * (va + vb) / (1.0 + iou)
    return iou, inter / max(min(va, vb), 1e-12)


def nms_3d(objects: list[Object3D], iou_threshold: float = 0.25, containment_threshold: float = 0.7) -> list[Object3D]:
    """Objects sorted by score, dropping any that overlaps a kept one by more than
    ``iou_threshold`` (3D IoU) or lies mostly inside it / around it (intersection over the
    smaller volume above ``containment_threshold``).

    Class-agnostic: two pieces of furniture do not share space, so overlapping boxes of
    different classes are duplicates of one object from different proposals (a part of
    an object proposed alone, or an object merged with its neighbour).
    """
    ordered = sorted(objects, key=lambda o: -o.score)
    if not ordered:
        return []
    # bounding spheres: boxes whose spheres do not touch cannot overlap (skips the exact IoU)
    centers = np.array([np.asarray(o.center, np.float64).reshape(3) for o in ordered])
    radii = np.array([0.5 * float(np.linalg.norm(o.size)) for o in ordered])
    near = np.linalg.norm(centers[:, None] - centers[None], axis=-1) < radii[:, None] + radii[None]
    kept: list[int] = []
    for i, obj in enumerate(ordered):
        if all(
            iou <= iou_threshold and contained <= containment_threshold
            for iou, contained in (overlap_ratios(obj, ordered[k]) for k in kept if near[i, k])
        ):
            kept.append(i)
    return [ordered[i] for i in kept]
