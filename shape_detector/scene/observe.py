"""Detector objects (camera optical frame) -> world-frame observations ready to fuse.

World frame: z up, metres. A detected box's vertical axis is the rotation column most
parallel to world z; its yaw is that of the box x axis (or, when x is the vertical axis,
the most horizontal other axis) about z. Primitives are stored along the box axes in box
units (see :class:`~shape_detector.scene.tracks.Observation`).
"""

from __future__ import annotations

import numpy as np

from ..types import Object3D
from .tracks import Observation, class_probs_of, rotz


def upright_box(center: np.ndarray, size: np.ndarray, R_world: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(size (l, w, h) with h along world up, yaw of the l axis about z, (3,3) the box axes
    matrix whose columns are the l, w, h axes in the world)."""
    R = np.asarray(R_world, dtype=np.float64)
    s = np.asarray(size, dtype=np.float64)
    v = int(np.argmax(np.abs(R[2])))
    hor = [i for i in range(3) if i != v]
    i0, i1 = hor
    x = R[:, i0].copy()
    x[2] = 0.0
    yaw = float(np.arctan2(x[1], x[0]))
    out = np.array([s[i0], s[i1], s[v]])
    return out, yaw, np.stack([R[:, i0], R[:, i1], R[:, v]], axis=1)


def visible_share(center: np.ndarray, size: np.ndarray, rotation: np.ndarray, K: np.ndarray, width: int,
                  height: int) -> float:
    """Share (0..1) of a camera-frame box's projected 2D bounding rectangle that lies inside
    the image (truncation by the border; 0.5 when part of the box is behind the camera)."""
    from ..geometry import box_corners

    c = box_corners(center, size, rotation)
    if np.any(c[:, 2] <= 0.05):
        return 0.5
    uv = (c @ np.asarray(K, dtype=np.float64).T)
    uv = uv[:, :2] / uv[:, 2:3]
    x0, y0 = uv.min(0)
    x1, y1 = uv.max(0)
    area = max(x1 - x0, 1e-6) * max(y1 - y0, 1e-6)
    ix = max(0.0, min(x1, width) - max(x0, 0.0))
    iy = max(0.0, min(y1, height) - max(y0, 0.0))
    return float(np.clip(ix * iy / area, 0.0, 1.0))


def observation_weight(score: float, share: float) -> float:
    """Fusion weight of a detection (1 for a sure, fully visible one): about the inverse of
    its expected box error, which falls steeply as the detector's score nears 1 and rises
    when the box is cut by the image border."""
    s = float(np.clip(score, 0.0, 1.0))
    return max(share * share * (s / (1.02 - s)) / 50.0, 1e-4)


def to_observation(obj: Object3D, T_world_camera: np.ndarray, stamp_ns: int, K: np.ndarray | None = None,
                   image_size: tuple[int, int] | None = None) -> Observation | None:
    """The world-frame :class:`Observation` of one detection, or None when it is malformed
    (non-finite or non-positive size). Weight: :func:`observation_weight` (share 1 without
    ``K`` / ``image_size`` = (height, width))."""
    c = np.asarray(obj.center, dtype=np.float64)
    s = np.asarray(obj.size, dtype=np.float64)
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(s)) and np.all(s > 0) and np.isfinite(obj.score)):
        return None
    T = np.asarray(T_world_camera, dtype=np.float64)
    Rw = T[:3, :3] @ np.asarray(obj.rotation, dtype=np.float64)
    cw = T[:3, :3] @ c + T[:3, 3]
    size, yaw, _ = upright_box(cw, s, Rw)
    axes = rotz(yaw)  # the track's box frame (third column +z)
    share = 1.0
    if K is not None and image_size is not None:
        share = visible_share(c, s, obj.rotation, K, image_size[1], image_size[0])
    score = float(np.clip(obj.score, 0.0, 1.0))
    prims = []
    for p in obj.primitives:
        pc = T[:3, :3] @ np.asarray(p.center, dtype=np.float64) + T[:3, 3]
        pr = T[:3, :3] @ np.asarray(p.rotation, dtype=np.float64)
        # the part's extent along the box axes (exact for box-aligned parts)
        ext = np.abs(axes.T @ pr) @ np.asarray(p.size, dtype=np.float64)
        local = axes.T @ (pc - cw)
        prims.append((local / np.maximum(size, 1e-6), ext / np.maximum(size, 1e-6)))
    return Observation(class_name=obj.class_name, score=score, center=cw, size=size, yaw=yaw,
                       weight=observation_weight(score, share),
                       class_probs=class_probs_of(obj.class_name, score, obj.class_scores),
                       prims_local=prims, stamp_ns=int(stamp_ns))
