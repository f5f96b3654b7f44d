"""Greedy 3D non-maximum suppression over oriented, yaw-only boxes."""

from __future__ import annotations

from .types import Object3D


def nms_3d(objects: list[Object3D], iou_threshold: float = 0.25) -> list[Object3D]:
    """Objects sorted by score, dropping any whose 3D IoU with a kept one exceeds the threshold.

    Class-agnostic: two pieces of furniture do not share space, so overlapping boxes of
    different classes are duplicates of one object from different proposals.
    """
    from .evaluation.iou import box3d_iou

    kept: list[Object3D] = []
    for obj in sorted(objects, key=lambda o: -o.score):
        if all(
            box3d_iou(obj.center, obj.size, obj.rotation, k.center, k.size, k.rotation) <= iou_threshold
            for k in kept
        ):
            kept.append(obj)
    return kept
