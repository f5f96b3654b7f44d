"""Per-class primitive anchors for the shape head: class templates learnt from the GT parts.

The box head regresses sizes as residuals from per-class size clusters; the shape head does
the same for its ``M`` cuboids when ``ModelConfig.shape_anchors`` is on. Each class has an
anchor row (``M * 10`` raw values, see :mod:`.primitives`) added to the head's output, so the
head only predicts each object's deviation from its class template.

Templates are computed from the training frustums' GT parts, **box-relative** (each object's
parts in its GT box's canonical frame divided by the box size per axis, so the box is the
unit cube ``[-0.5, 0.5]^3``):

1. occupancy of each sampled object's parts on a ``resolution^3`` grid over the unit cube;
2. the class **medoid**: the object with the highest mean voxel IoU to the others;
3. its ``M`` largest parts (by box-relative volume) become the template, as axis-aligned
   cuboids. An object with fewer parts has its largest part split in two along its longest
   side until there are ``M`` (same union; repeated parts would shadow each other in the
   losses and never separate).

Why: without anchors, 4 of the 6 primitives of the earlier head collapsed to slivers during
training (nothing pulled them back), so a chair was its seat and back and a table its top.
A class template starts every slot on a real part (a leg, a shelf, a side panel).
"""

from __future__ import annotations

import numpy as np

from ..evaluation.shape_metrics import points_in_union, voxel_centers
from ..types import Cuboid
from .primitives import primitive_raw


def relative_parts(
    centers: np.ndarray, sizes: np.ndarray, rotations: np.ndarray, box_size: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds ``(lo, hi)`` (P, 3) of parts in box-relative coordinates.

    ``centers`` (P,3), ``sizes`` (P,3), ``rotations`` (P,3,3) in the box's canonical frame
    (metres, origin at the box centre); ``box_size`` (3,) full size. A rotated part is
    replaced by its axis-aligned bounds."""
    s = np.asarray(box_size, np.float64).reshape(1, 3)
    half = 0.5 * np.einsum("pij,pj->pi", np.abs(np.asarray(rotations, np.float64)), np.asarray(sizes, np.float64))
    c = np.asarray(centers, np.float64)
    return (c - half) / s, (c + half) / s


#: the box-relative unit cube
_UNIT_CUBE = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])


def _occupancy(lo: np.ndarray, hi: np.ndarray, grid: np.ndarray) -> np.ndarray:
    return points_in_union(grid, [Cuboid(0.5 * (a + b), b - a, np.eye(3)) for a, b in zip(lo, hi)])


def medoid_template(
    objects: list[tuple[np.ndarray, np.ndarray]], num_primitives: int, resolution: int = 24
) -> tuple[np.ndarray, np.ndarray, float]:
    """The medoid object's ``num_primitives`` largest parts ``(lo, hi)`` (M,3) each, and its
    mean voxel IoU to the objects. ``objects``: box-relative part bounds per object."""
    if not objects:
        raise ValueError("medoid_template needs at least one object")
    grid = voxel_centers(_UNIT_CUBE, resolution)
    occ = np.stack([_occupancy(lo, hi, grid) for lo, hi in objects]).astype(np.float32)
    inter = occ @ occ.T
    vol = occ.sum(1)
    iou = inter / np.maximum(vol[:, None] + vol[None, :] - inter, 1.0)
    mean_iou = iou.mean(1)
    m = int(mean_iou.argmax())
    lo, hi = (np.array(a, np.float64) for a in objects[m])
    while len(lo) < num_primitives:  # split the largest part in two along its longest side
        k = int(np.argmax(np.prod(hi - lo, axis=1)))
        ax = int(np.argmax(hi[k] - lo[k]))
        mid = 0.5 * (lo[k, ax] + hi[k, ax])
        lo2, hi2 = lo[k].copy(), hi[k].copy()
        hi[k, ax], lo2[ax] = mid, mid
        lo, hi = np.vstack([lo, lo2]), np.vstack([hi, hi2])
    order = np.argsort(-np.prod(hi - lo, axis=1))[:num_primitives]
    return lo[order], hi[order], float(mean_iou[m])


def class_templates(
    parts_center: np.ndarray,
    parts_size: np.ndarray,
    parts_rotation: np.ndarray,
    parts_count: np.ndarray,
    box_size: np.ndarray,
    class_id: np.ndarray,
    num_classes: int,
    num_primitives: int,
    per_class: int = 300,
    resolution: int = 24,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-class templates from a frustum dataset's GT parts (see the module docstring).

    Arrays as in :mod:`shape_detector.training.frustum_dataset` (rows with ``parts_count``
    > 0 and ``class_id`` in ``[0, num_classes)`` are used; at most ``per_class`` random
    objects per class). Returns ``lo``, ``hi`` (num_classes, M, 3) box-relative bounds and
    ``found`` (num_classes,) bool (False: no object of that class; its rows are zeros)."""
    rng = np.random.default_rng(seed)
    M = int(num_primitives)
    lo = np.zeros((num_classes, M, 3))
    hi = np.zeros((num_classes, M, 3))
    found = np.zeros(num_classes, bool)
    cid = np.asarray(class_id).astype(np.int64)
    count = np.asarray(parts_count).astype(np.int64)
    for c in range(num_classes):
        rows = np.flatnonzero((cid == c) & (count > 0))
        if rows.size == 0:
            continue
        if rows.size > per_class:
            rows = rng.choice(rows, per_class, replace=False)
        objs = []
        for r in rows:
            k = int(count[r])
            objs.append(relative_parts(parts_center[r, :k], parts_size[r, :k], parts_rotation[r, :k], box_size[r]))
        lo[c], hi[c], _ = medoid_template(objs, M, resolution)
        found[c] = True
    return lo, hi, found


def templates_to_raw(lo: np.ndarray, hi: np.ndarray, min_frac: float = 0.01) -> np.ndarray:
    """Raw shape-head values (..., M, 10) whose cuboids (:func:`.primitives.primitive_params`
    with a box of any size) are the box-relative bounds ``lo``, ``hi`` (..., M, 3):
    identity rotation, centre ``(lo + hi) / 2``, size ``hi - lo`` (times the box size)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return primitive_raw(0.5 * (lo + hi), hi - lo, min_frac)
