"""Snap predicted cuboid primitives to their amodal box: axis-aligned and inside it.

Furniture parts are axis-aligned in the object's frame and bounded by its amodal box (the
box is by definition the bounding box of the parts). The shape head regresses free 3D
rotations and translations relative to the box, so its primitives come out slightly
tilted or sticking out of the box (a table top predicted 2 cm above the box top). In the
box's frame (metres, centre at the origin, axes = box axes) each primitive is

1. turned to the box axes when every one of its axes is within ``max_angle_deg`` of a box
   axis (its sizes permuted accordingly), and then
2. clipped to the box (dropped when nothing of it is left inside).

Primitives tilted more than ``max_angle_deg`` are left as predicted.

Measured on 100 validation frames with GT boxes (after floor contact stretches the
primitives with the box): object-frame shape IoU averaged over classes 0.427 -> 0.430,
surface distance 0.0413 -> 0.0398. Also extending primitives to a box face when within
5-20% of the box size of it gave no further gain (0.425-0.426), so it is not done.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..types import Cuboid, Object3D

_PERMS = np.array(list(itertools.permutations(range(3))))  # (6, 3)


def snap_in_box(
    center: np.ndarray,
    size: np.ndarray,
    rotation: np.ndarray,
    box_size: np.ndarray,
    max_angle_deg: float = 30.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Snap cuboids given in a box's frame (``center`` (M,3) m, full ``size`` (M,3) m,
    ``rotation`` (M,3,3) columns = cuboid axes) to the box of full size ``box_size`` (3,)
    centred at the origin, or to one box each ((M,3)).

    Returns ``(center, size, rotation, keep)``: the snapped cuboids (all M, rows of dropped
    ones unchanged) and a bool (M,) mask of those that still have volume inside the box.
    """
    c = np.array(center, dtype=np.float64).reshape(-1, 3)
    s = np.array(size, dtype=np.float64).reshape(-1, 3)
    r = np.array(rotation, dtype=np.float64).reshape(-1, 3, 3)
    half = np.broadcast_to(0.5 * np.asarray(box_size, dtype=np.float64), c.shape)
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    absr = np.abs(r)  # [m, box axis, cuboid axis]
    # best assignment cuboid axis j -> box axis perm[j]: maximise the summed |cosines|
    best = _PERMS[np.argmax(absr[:, _PERMS, np.arange(3)].sum(-1), axis=1)]  # (M, 3)
    cosines = np.take_along_axis(absr, best[:, None, :], axis=1)[:, 0, :]  # |cos| per cuboid axis
    aligned = np.all(cosines >= cos_max, axis=1)
    along_box = np.empty_like(s)
    np.put_along_axis(along_box, best, s, axis=1)  # sizes along the box axes
    lo = np.maximum(c - 0.5 * along_box, -half)
    hi = np.minimum(c + 0.5 * along_box, half)
    keep = ~aligned | np.all(hi - lo > 1e-6, axis=1)
    a = aligned & keep
    c[a], s[a], r[a] = 0.5 * (lo[a] + hi[a]), (hi - lo)[a], np.eye(3)
    return c, s, r, keep


def snap_primitives(objects: list[Object3D], max_angle_deg: float = 30.0) -> list[Object3D]:
    """``objects`` with their camera-frame primitives snapped to their boxes (in place, also
    returned), see :func:`snap_in_box`; one vectorised pass over all of a frame's primitives.
    An object none of whose primitives is left inside its box keeps them as predicted."""
    counts = [len(o.primitives) for o in objects]
    if not any(counts):
        return objects
    prims = [p for o in objects for p in o.primitives]

    def per_primitive(key: str) -> np.ndarray:  # each primitive's row of its object's box
        return np.repeat(np.stack([getattr(o, key) for o in objects]), counts, axis=0)

    R, c0, box = per_primitive("rotation"), per_primitive("center"), per_primitive("size")  # box axes (N,3,3)
    local_c = np.einsum("ni,nij->nj", np.stack([p.center for p in prims]) - c0, R)
    local_r = np.einsum("nji,njk->nik", R, np.stack([p.rotation for p in prims]))
    c, s, r, keep = snap_in_box(local_c, np.stack([p.size for p in prims]), local_r, box, max_angle_deg)
    cam_c = c0 + np.einsum("nij,nj->ni", R, c)
    cam_r = R @ r
    start = 0
    for obj, n in zip(objects, counts):
        rows = np.arange(start, start + n)
        start += n
        if n and keep[rows].any():
            obj.primitives = [Cuboid(cam_c[m], s[m], cam_r[m]) for m in rows[keep[rows]]]
    return objects
