"""Comparing a predicted cuboid shape abstraction with the GT parts (both list[Cuboid]).

* :func:`shape_iou` -- volumetric IoU of the two *unions* of cuboids, estimated on the
  centres of a ``resolution**3`` voxel grid (``resolution`` cells along each axis, so the
  cells are not cubes in general) spanning the axis-aligned bounding box of all corners
  of both sets (or given ``bounds``). A point counts as inside a cuboid when it is inside
  or on its boundary.
* :func:`surface_distance` -- symmetric chamfer distance between the two union
  *surfaces*: ``n`` points are sampled on the faces of each set (face chosen with
  probability proportional to its area, uniform on the face), samples strictly inside
  another cuboid of the same set are discarded (and replaced by further draws), then
  ``(mean_p min_g |p-g| + mean_g min_p |g-p|) / 2``. Faces shared by two touching
  cuboids are not strictly inside either and so stay in the sample.

  The distance is divided by the **diameter of the GT corner set** (largest distance
  between two corners of the GT parts). That is our stand-in for the diameter ``D`` of
  the smallest sphere around the GT corners: ``diam <= D <= 2/sqrt(3) * diam`` (Jung's
  theorem), it equals ``D`` for a single box (its space diagonal), and unlike the
  axis-aligned bounding-box diagonal it does not change when the frame rotates.
  ``normalise="bbox_diagonal"`` selects the bounding-box diagonal instead, ``"none"``
  returns metres.

  Both sets are sampled with **common random numbers**: the same uniform draws are
  mapped through each set's faces (each set on its own is still an unbiased area-weighted
  sample). This lowers the variance of comparisons and makes the distance of a set to
  itself exactly 0.
* :func:`box_relative_iou` -- the shape IoU with each set expressed relative to its *own*
  box, per axis (``u = R^T (p - c) / size``, the box becomes the unit cube): what the
  shape head controls, since it predicts primitives relative to the box it is given. The
  isotropic object frame of :func:`to_box_frame` still mixes in the box's size error (a
  table top in a box 8 cm too tall sits 4 cm off the GT top there); here the GT parts in
  a wrong box still score 1.
* :func:`to_box_frame` -- cuboids expressed in a box's canonical frame (centre at the
  origin, axes = box axes), optionally scaled isotropically so the box diagonal is 1, so
  shape quality can be measured independently of the box pose error.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import box_corners, points_in_box
from ..types import Cuboid

def _params(c: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        np.asarray(c.center, dtype=np.float64).reshape(3),
        np.asarray(c.size, dtype=np.float64).reshape(3),
        np.asarray(c.rotation, dtype=np.float64).reshape(3, 3),
    )


def all_corners(cuboids: Sequence[Any]) -> np.ndarray:
    """(8M,3) corners of all cuboids."""
    if not cuboids:
        return np.zeros((0, 3))
    return np.concatenate([box_corners(*_params(c)) for c in cuboids], axis=0)


def points_in_union(points: np.ndarray, cuboids: Sequence[Any]) -> np.ndarray:
    """(N,) bool: point inside (or on) at least one of the cuboids."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    inside = np.zeros(len(pts), dtype=bool)
    for c in cuboids:
        inside |= points_in_box(pts, *_params(c))
    return inside


def voxel_centers(bounds: np.ndarray, resolution: int) -> np.ndarray:
    """(r^3, 3) centres of a ``resolution``-per-axis grid over ``bounds = [[lo],[hi]]``."""
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    r = int(resolution)
    axes = [b[0, d] + (np.arange(r) + 0.5) * (b[1, d] - b[0, d]) / r for d in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def shape_iou(pred: Sequence[Any], gt: Sequence[Any], resolution: int = 32, bounds: np.ndarray | None = None) -> float:
    """Voxelised IoU of the union of ``pred`` cuboids and the union of ``gt`` cuboids.

    ``bounds``: (2,3) ``[min, max]`` corners of the grid; default the bounding box of all
    corners of both sets. Returns NaN when both sets are empty (or the grid has zero
    volume and nothing is inside), 0 when exactly one set is empty.
    """
    if not pred and not gt:
        return float("nan")
    if not pred or not gt:
        return 0.0
    if bounds is None:
        corners = np.concatenate([all_corners(pred), all_corners(gt)])
        bounds = np.stack([corners.min(0), corners.max(0)])
    g = voxel_centers(bounds, resolution)
    a = points_in_union(g, pred)
    b = points_in_union(g, gt)
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return float("nan")
    return float(np.count_nonzero(a & b) / union)


def _unit_box_map(box: Sequence[Any]) -> tuple[np.ndarray, np.ndarray]:
    """``(centre (3,), A (3,3))`` of a box ``(centre, rotation, size)``: ``p = centre + A u``
    maps its unit-cube coordinates ``u`` to the cuboids' frame."""
    c, R, s = (np.asarray(v, dtype=np.float64) for v in box)
    s = s.reshape(3)
    if not np.all(s > 0.0):
        raise ValueError(f"box size must be positive, got {s}")
    return c.reshape(3), R.reshape(3, 3) * s


def box_relative_iou(
    pred: Sequence[Any],
    pred_box: Sequence[Any],
    gt: Sequence[Any],
    gt_box: Sequence[Any],
    resolution: int = 32,
) -> float:
    """Voxelised IoU of ``pred`` and ``gt`` cuboid unions, each relative to its own box.

    ``pred_box`` / ``gt_box``: ``(centre (3,), rotation (3,3) columns = box axes, full size
    (3,))`` in the frame of the cuboids. Each set is mapped to its box's unit cube per axis
    (``u = R^T (p - c) / size``); the grid is ``resolution ** 3`` voxel centres over the
    bounding box of both sets' corners in those coordinates. The point test maps each voxel
    centre back into the set's own frame, so primitives that are not box-aligned need no
    special case. Same NaN / 0 conventions as :func:`shape_iou`.
    """
    if not pred and not gt:
        return float("nan")
    if not pred or not gt:
        return 0.0
    (cp, Ap), (cg, Ag) = _unit_box_map(pred_box), _unit_box_map(gt_box)
    corners = np.concatenate(
        [np.linalg.solve(Ap, (all_corners(pred) - cp).T).T, np.linalg.solve(Ag, (all_corners(gt) - cg).T).T]
    )
    u = voxel_centers(np.stack([corners.min(0), corners.max(0)]), resolution)
    a = points_in_union(cp + u @ Ap.T, pred)
    b = points_in_union(cg + u @ Ag.T, gt)
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return float("nan")
    return float(np.count_nonzero(a & b) / union)


# --------------------------------------------------------------------- surface samples
def _faces(cuboids: Sequence[Any]) -> tuple[np.ndarray, np.ndarray]:
    """Face table: (6M,) areas and (6M,3) int rows (cuboid index, normal axis, sign)."""
    areas, rows = [], []
    for k, c in enumerate(cuboids):
        s = np.abs(np.asarray(c.size, dtype=np.float64).reshape(3))
        for a in range(3):
            b, d = [x for x in range(3) if x != a]
            for sign in (1, -1):
                areas.append(s[b] * s[d])
                rows.append((k, a, sign))
    return np.asarray(areas, dtype=np.float64), np.asarray(rows, dtype=np.int64).reshape(-1, 3)


def _strictly_inside_other(points: np.ndarray, owner: np.ndarray, cuboids: Sequence[Any], eps: float) -> np.ndarray:
    bad = np.zeros(len(points), dtype=bool)
    for k, c in enumerate(cuboids):
        center, size, rot = _params(c)
        local = (points - center) @ rot
        half = 0.5 * np.abs(size) - eps
        if np.any(half <= 0):
            continue  # a flat cuboid has no interior
        bad |= np.all(np.abs(local) < half, axis=1) & (owner != k)
    return bad


def sample_union_surface(
    cuboids: Sequence[Any],
    n: int,
    rng: np.random.Generator | int | None = None,
    *,
    max_rounds: int = 20,
    eps: float = 1e-9,
) -> np.ndarray:
    """(<=n, 3) points on the surface of the union of ``cuboids`` (see module docstring).

    Draws batches of area-weighted face samples, drops those strictly inside another
    cuboid of the set, and stops once ``n`` are kept (or after ``max_rounds`` batches,
    returning fewer). Two calls with equally seeded generators consume identical uniform
    streams (common random numbers).
    """
    rng = np.random.default_rng(rng)
    if not cuboids or n <= 0:
        return np.zeros((0, 3))
    areas, rows = _faces(cuboids)
    total = float(areas.sum())
    if total <= 0.0:
        return np.zeros((0, 3))
    cdf = np.cumsum(areas) / total
    params = [_params(c) for c in cuboids]
    centers = np.stack([p[0] for p in params])
    sizes = np.stack([p[1] for p in params])
    rots = np.stack([p[2] for p in params])
    kept: list[np.ndarray] = []
    have = 0
    batch = max(int(n), 16)
    for _ in range(max_rounds):
        u = rng.random((batch, 3))
        f = np.minimum(np.searchsorted(cdf, u[:, 0], side="right"), len(areas) - 1)
        k, a, sign = rows[f, 0], rows[f, 1], rows[f, 2].astype(np.float64)
        # local coordinates: the normal axis at +-half, the other two uniform on the face
        local = np.zeros((batch, 3))
        b = np.where(a == 0, 1, 0)
        d = np.where(a == 2, 1, 2)
        idx = np.arange(batch)
        s = sizes[k]
        local[idx, a] = sign * 0.5 * s[idx, a]
        local[idx, b] = (u[:, 1] - 0.5) * s[idx, b]
        local[idx, d] = (u[:, 2] - 0.5) * s[idx, d]
        pts = np.einsum("nij,nj->ni", rots[k], local) + centers[k]
        if len(cuboids) > 1:
            pts = pts[~_strictly_inside_other(pts, k, cuboids, eps)]
        kept.append(pts)
        have += len(pts)
        if have >= n:
            break
    return np.concatenate(kept)[: int(n)]


def nearest_distances(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(N,) distance from each ``src`` point to its nearest ``dst`` point (exact: a k-d tree
    of ``dst``, SciPy's ``cKDTree``; coincident points give exactly 0)."""
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if len(dst) == 0:
        return np.full(len(src), np.inf)
    if len(src) == 0:
        return np.zeros(0)
    return cKDTree(dst).query(src, k=1)[0]


def set_diameter(points: np.ndarray) -> float:
    """Largest distance between two of the points (0 for fewer than two)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return 0.0
    return float(np.sqrt(np.max(np.sum((p[:, None] - p[None]) ** 2, axis=-1))))


def gt_scale(gt: Sequence[Any], normalise: str = "diameter") -> float:
    """The normaliser of :func:`surface_distance` for a GT set (1.0 for ``"none"``)."""
    if normalise == "none":
        return 1.0
    corners = all_corners(gt)
    if normalise == "diameter":
        return set_diameter(corners)
    if normalise == "bbox_diagonal":
        return float(np.linalg.norm(corners.max(0) - corners.min(0))) if len(corners) else 0.0
    raise ValueError(f"normalise must be 'diameter', 'bbox_diagonal' or 'none', not {normalise!r}")


def surface_distance(
    pred: Sequence[Any],
    gt: Sequence[Any],
    n: int = 5000,
    rng: np.random.Generator | int | None = None,
    normalise: str = "diameter",
) -> float:
    """Symmetric chamfer distance between the union surfaces, over the GT scale.

    ``(mean over pred samples of the distance to the nearest GT sample + the same from GT
    to pred) / 2``, divided by :func:`gt_scale` (see module docstring). NaN when either
    set is empty / has no surface, or the GT scale is 0.
    """
    rng = np.random.default_rng(rng)
    seed = int(rng.integers(0, 2**63 - 1))
    p = sample_union_surface(pred, n, np.random.default_rng(seed))
    g = sample_union_surface(gt, n, np.random.default_rng(seed))
    if len(p) == 0 or len(g) == 0:
        return float("nan")
    scale = gt_scale(gt, normalise)
    if not scale > 0.0:
        return float("nan")
    d = 0.5 * (nearest_distances(p, g).mean() + nearest_distances(g, p).mean())
    return float(d / scale)


# --------------------------------------------------------------------- frames
def to_box_frame(
    cuboids: Sequence[Any],
    center: np.ndarray,
    rotation: np.ndarray,
    size: np.ndarray | None = None,
    normalise: bool = False,
) -> list[Cuboid]:
    """``cuboids`` in the canonical frame of a box: ``p_box = R^T (p - center)``.

    The box's axes become x, y, z (so for furniture x = facing direction, z = up).
    ``normalise=True`` also scales isotropically by ``1 / |size|`` so the box's space
    diagonal is 1 (isotropic, so cuboids stay cuboids whatever their orientation);
    ``size`` is then required.
    """
    c = np.asarray(center, dtype=np.float64).reshape(3)
    R = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    scale = 1.0
    if normalise:
        if size is None:
            raise ValueError("to_box_frame(normalise=True) needs the box size")
        diag = float(np.linalg.norm(np.asarray(size, dtype=np.float64)))
        if not diag > 0.0:
            raise ValueError("cannot normalise by a box of zero size")
        scale = 1.0 / diag
    out = []
    for q in cuboids:
        qc, qs, qr = _params(q)
        out.append(Cuboid(scale * (R.T @ (qc - c)), scale * qs, R.T @ qr))
    return out


def shape_metrics(
    pred: Sequence[Any],
    gt: Sequence[Any],
    resolution: int = 32,
    n: int = 5000,
    rng: np.random.Generator | int | None = None,
    normalise: str = "diameter",
) -> dict[str, float]:
    """``{"iou": shape_iou(...), "surface_distance": surface_distance(...)}`` for one pair."""
    return {
        "iou": shape_iou(pred, gt, resolution=resolution),
        "surface_distance": surface_distance(pred, gt, n=n, rng=rng, normalise=normalise),
    }
