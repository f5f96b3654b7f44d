"""Detector objects (camera optical frame) -> world-frame observations ready to fuse.

World frame: z up, metres. A detected box's vertical axis is the rotation column most
parallel to world z; its yaw is that of the box x axis (or, when x is the vertical axis,
the most horizontal other axis) about z. Primitives are stored along the box axes in box
units (see :class:`~shape_detector.scene.tracks.Observation`).
"""

from __future__ import annotations

import numpy as np

from ..geometry import box_corners
from ..types import Object3D
from .tracks import Observation, class_probs_of, rotz
from .visibility import unit_lattice


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
                  height: int, n: int = 5, depth: np.ndarray | None = None, margin: float = 0.1) -> float:
    """Share (0..1) of a camera-frame box the camera sees: of an ``n`` x ``n`` x ``n`` lattice
    of points in the box, those in front of the camera (z > 0.1 m) that project into the
    image (truncation by the border) and, with ``depth`` (metres, NaN invalid), whose pixel
    does not measure something nearer than the whole box by more than ``margin`` (occlusion
    by another object)."""
    g = unit_lattice(n)
    p = (g * np.asarray(size, dtype=np.float64)) @ np.asarray(rotation, dtype=np.float64).T + np.asarray(center)
    z = p[:, 2]
    front = z > 0.1
    if not front.any():
        return 0.0
    Kf = np.asarray(K, dtype=np.float64)
    u = np.floor(Kf[0, 0] * p[front, 0] / z[front] + Kf[0, 2] + 0.5)
    v = np.floor(Kf[1, 1] * p[front, 1] / z[front] + Kf[1, 2] + 0.5)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    seen = int(inside.sum())
    if depth is not None and seen:
        near = float(np.min(box_corners(center, size, rotation)[:, 2]))
        d = depth[v[inside].astype(np.int64), u[inside].astype(np.int64)]
        with np.errstate(invalid="ignore"):
            seen -= int(np.sum(d < near - margin))
    return float(seen) / len(p)


def observation_weight(score: float, share: float) -> float:
    """Fusion weight of a detection (1 for a sure, fully visible one): about the inverse of
    its expected box error, which falls steeply as the detector's score nears 1 and rises
    when the box is cut by the image border."""
    s = float(np.clip(score, 0.0, 1.0))
    return max(share * share * (s / (1.02 - s)) / 50.0, 1e-4)


def to_observation(obj: Object3D, T_world_camera: np.ndarray, stamp_ns: int, K: np.ndarray | None = None,
                   image_size: tuple[int, int] | None = None, depth: np.ndarray | None = None) -> Observation | None:
    """The world-frame :class:`Observation` of one detection, or None when it is malformed
    (non-finite or non-positive size). Weight: :func:`observation_weight` of the score and
    :func:`visible_share` (1 without ``K`` / ``image_size`` = (height, width); occlusion
    counted with ``depth``)."""
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
        share = visible_share(c, s, obj.rotation, K, image_size[1], image_size[0], depth=depth)
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
