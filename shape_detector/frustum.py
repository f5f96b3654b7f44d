"""Back-projection and frustum extraction (thesis section 3.3.1), pure numpy.

Pixel convention: column ``u`` / row ``v`` index pixel centres, so ``K @ p`` of a camera
point gives its (u, v) directly (0-based). A 2D box ``(x1, y1, x2, y2)`` selects the
pixels ``x1 <= u < x2``, ``y1 <= v < y2`` (edges; boxes are clipped to the image).

A frustum's points are returned in its **frustum frame** ``F``: the upright frame
``U`` (z = gravity-up, see :mod:`shape_detector.geometry`) rotated about z by the
frustum angle ``phi`` so that the box's centre ray points along +y. Only the yaw is
normalised (boxes are yaw-only, so tilting the vertical would break the heading
parametrisation). ``p_F = rot_z(phi) @ R_cu.T @ p_cam``; a heading ``theta`` in ``U``
becomes ``theta + phi`` in ``F``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import rot_z, upright_rotation


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (H,W,3) from a depth map in metres (NaN/0 stay NaN/0 in z)."""
    h, w = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = (np.arange(w, dtype=np.float32) - cx) / fx
    v = (np.arange(h, dtype=np.float32) - cy) / fy
    z = depth.astype(np.float32, copy=False)
    return np.stack([u[None, :] * z, v[:, None] * z, z], axis=-1)


def pixel_points(depth: np.ndarray, K: np.ndarray, flat_index: np.ndarray) -> np.ndarray:
    """Camera-frame points (n,3) float64, metres, of the pixels ``flat_index`` (``v * W + u``)
    of ``depth`` (HxW metres; invalid pixels keep their NaN/0 in z). Back-projects only the
    pixels asked for: a detector needs a few thousand of a VGA frame's 307,200."""
    flat_index = np.asarray(flat_index, dtype=np.int64)
    v, u = np.divmod(flat_index, depth.shape[1])
    z = depth[v, u].astype(np.float64)
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)


def valid_depth(depth: np.ndarray, max_depth: float = 10.0) -> np.ndarray:
    """Boolean mask of usable depth pixels: finite, > 0 and < ``max_depth`` metres."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0) & (depth < max_depth)


def clip_box(box2d, width: int, height: int) -> tuple[int, int, int, int]:
    """Integer pixel-edge box clipped to the image; may be empty (x2 <= x1)."""
    x1, y1, x2, y2 = (float(b) for b in box2d[:4])
    xi1 = int(np.clip(np.floor(x1), 0, width))
    yi1 = int(np.clip(np.floor(y1), 0, height))
    xi2 = int(np.clip(np.ceil(x2), 0, width))
    yi2 = int(np.clip(np.ceil(y2), 0, height))
    return xi1, yi1, xi2, yi2


def frustum_angle(box2d, K: np.ndarray, R_cu: np.ndarray) -> float:
    """Yaw ``phi`` (rad) that turns the box's centre ray onto +y of the upright frame."""
    uc = 0.5 * (float(box2d[0]) + float(box2d[2])) - 0.5
    vc = 0.5 * (float(box2d[1]) + float(box2d[3])) - 0.5
    ray = np.linalg.solve(np.asarray(K, dtype=np.float64), np.array([uc, vc, 1.0]))
    d = R_cu.T @ ray
    return float(np.arctan2(d[0], d[1]))


@dataclass
class Frustum:
    """Points of one 2D box in its frustum frame.

    ``points``: (N,6) float32, x y z in metres (frame ``F``) then r g b in [0,1];
    ``pixel_index``: (N,) int64 flat indices ``v * W + u`` of the sampled pixels (for
    looking up instance labels); ``valid``: number of distinct valid pixels before
    sampling (0 -> ``points`` is all zeros); ``phi``: frustum angle; ``R_cu``: the
    upright rotation used. ``to_camera`` maps frame-``F`` points back.
    """

    points: np.ndarray
    pixel_index: np.ndarray
    valid: int
    phi: float
    R_cu: np.ndarray

    @property
    def R_cf(self) -> np.ndarray:
        """Rotation taking frustum-frame vectors to the camera frame."""
        return self.R_cu @ rot_z(-self.phi)

    def to_camera(self, p_f: np.ndarray) -> np.ndarray:
        """Frustum-frame points (...,3) to camera-frame points."""
        return np.asarray(p_f) @ self.R_cf.T


def extract_frustum(
    rgb: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    box2d,
    num_points: int,
    up: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
    max_depth: float = 10.0,
    points_cam: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    R_cu: np.ndarray | None = None,
) -> Frustum:
    """Sample ``num_points`` points of the pixels inside ``box2d`` into the frustum frame.

    ``rgb`` HxWx3 uint8, ``depth`` HxW float32 metres (NaN/0/beyond ``max_depth`` invalid),
    ``K`` 3x3. Fewer valid pixels than ``num_points`` are resampled with replacement;
    none gives a zero frustum with ``valid == 0``. Only the sampled pixels are
    back-projected (:func:`pixel_points`); ``points_cam`` may instead pass a
    :func:`backproject` of the whole frame to read them from. ``valid`` may pass a cached
    :func:`valid_depth` mask and ``R_cu`` a cached ``upright_rotation(up)`` (per-frame work
    a detector does once for all boxes).
    ``rng`` None samples deterministically (evenly spaced).
    """
    h, w = depth.shape
    if R_cu is None:
        R_cu = upright_rotation(up)
    phi = frustum_angle(box2d, K, R_cu)
    x1, y1, x2, y2 = clip_box(box2d, w, h)
    empty = Frustum(
        np.zeros((num_points, 6), np.float32), np.zeros(num_points, np.int64), 0, phi, R_cu
    )
    if x2 <= x1 or y2 <= y1:
        return empty
    ok = valid_depth(depth[y1:y2, x1:x2], max_depth) if valid is None else valid[y1:y2, x1:x2]
    flat = np.flatnonzero(ok)  # raster order inside the box; 3x faster than 2D nonzero
    n = flat.size
    if n == 0:
        return empty
    if rng is None:  # evenly spaced: distinct pixels when n >= num_points, repeats otherwise
        sel = np.linspace(0, n - 1, num_points).round().astype(np.int64)
    else:
        sel = rng.choice(n, num_points, replace=n < num_points)
    vv, uu = np.divmod(flat[sel], x2 - x1)
    vv += y1
    uu += x1
    index = vv * w + uu  # flat pixel index in the image
    if points_cam is not None:
        p_cam = points_cam[vv, uu].astype(np.float64)
    else:
        p_cam = pixel_points(depth, K, index)
    R_fc = (R_cu @ rot_z(-phi)).T
    p_f = p_cam @ R_fc.T
    col = rgb[vv, uu].astype(np.float32) / 255.0
    pts = np.concatenate([p_f.astype(np.float32), col], axis=1)
    return Frustum(pts, index, int(n), phi, R_cu)


def extract_frustums(
    rgb: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    boxes2d: list,
    num_points: int,
    up: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    R_cu: np.ndarray | None = None,
    max_depth: float = 10.0,
) -> list[Frustum]:
    """:func:`extract_frustum` (deterministic sampling) of every box in ``boxes2d``, the
    per-box pixel selection in a loop and the back-projection, rotation into each frame
    ``F`` and colour lookup of all sampled pixels at once; same frustums."""
    h, w = depth.shape
    if R_cu is None:
        R_cu = upright_rotation(up)
    if valid is None:
        valid = valid_depth(depth, max_depth)
    K = np.asarray(K, dtype=np.float64)
    phis = [frustum_angle(b, K, R_cu) for b in boxes2d]
    out: list[Frustum | None] = [None] * len(boxes2d)
    picked, index = [], []
    for i, box in enumerate(boxes2d):
        x1, y1, x2, y2 = clip_box(box, w, h)
        flat = np.flatnonzero(valid[y1:y2, x1:x2]) if x2 > x1 and y2 > y1 else np.zeros(0, np.int64)
        if flat.size == 0:
            out[i] = Frustum(np.zeros((num_points, 6), np.float32), np.zeros(num_points, np.int64), 0,
                             float(phis[i]), R_cu)
            continue
        sel = np.linspace(0, flat.size - 1, num_points).round().astype(np.int64)
        vv, uu = np.divmod(flat[sel], x2 - x1)
        index.append((vv + y1) * w + (uu + x1))
        picked.append((i, int(flat.size)))
    if not picked:
        return out  # type: ignore[return-value]
    flat_all = np.concatenate(index)
    p_cam = pixel_points(depth, K, flat_all).reshape(len(picked), num_points, 3)
    col = (rgb.reshape(-1, 3)[flat_all].astype(np.float32) / 255.0).reshape(len(picked), num_points, 3)
    for k, (i, n) in enumerate(picked):
        R_fc = (R_cu @ rot_z(-float(phis[i]))).T
        pts = np.concatenate([(p_cam[k] @ R_fc.T).astype(np.float32), col[k]], axis=1)
        out[i] = Frustum(pts, index[k], n, float(phis[i]), R_cu)
    return out  # type: ignore[return-value]
