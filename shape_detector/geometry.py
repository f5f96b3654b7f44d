"""Pure-numpy geometry: gravity-aligned frames, yaw-only boxes, corners.

Frames
------
* **camera** (ROS optical): x right, y down, z forward, metres.
* **upright** ``U`` (built from the gravity-up vector ``up`` given in the camera frame):
  z = up, y = the camera's forward axis projected onto the horizontal plane, x = y x z
  (to the right). Origin at the camera centre. For a level camera ``up = (0, -1, 0)``
  and ``U`` is SUN RGB-D's upright depth frame (x right, y forward, z up).
  ``p_cam = R_cu @ p_U`` with ``R_cu = upright_rotation(up)``.
* **frustum** ``F``: ``U`` rotated about z by the frustum angle ``phi`` so that the 2D
  box's centre ray points along +y (see :mod:`shape_detector.frustum`).

A yaw-only box has heading ``theta``: its x axis in ``U`` is ``(cos theta, sin theta, 0)``,
its z axis is up; its rotation in the camera frame is ``R_cu @ rot_z(theta)``.
"""

from __future__ import annotations

import math

import numpy as np

DEFAULT_UP = np.array([0.0, -1.0, 0.0])


def normalize(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """``v`` scaled to unit length along its last axis."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, eps)


def rot_z(theta: float | np.ndarray) -> np.ndarray:
    """Rotation by ``theta`` radians about +z; shape (3,3) or (...,3,3) for arrays."""
    if np.ndim(theta) == 0:  # the common scalar case, ~10x faster than the stacking below
        c, s = math.cos(float(theta)), math.sin(float(theta))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(t), np.sin(t)
    z, o = np.zeros_like(t), np.ones_like(t)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def stretch_cuboids(
    center: np.ndarray, size: np.ndarray, rotation: np.ndarray, ratio: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cuboids in a box's frame (``center`` (..., 3), ``size`` (..., 3), ``rotation``
    (..., 3, 3), columns = cuboid axes) under the box's per-axis stretch ``p' = ratio * p``
    (``ratio`` broadcastable to ``center``): new centres and sizes, rotations unchanged.
    Exact for cuboids aligned with the box axes; otherwise each cuboid axis is scaled by the
    length it gets under the stretch."""
    ratio = np.asarray(ratio, dtype=np.float64)
    scale = np.linalg.norm(ratio[..., :, None] * rotation, axis=-2)
    return center * ratio, size * scale


def upright_rotation(up: np.ndarray | None) -> np.ndarray:
    """``R_cu`` (3,3): columns are the upright frame's x, y, z axes in camera coordinates.

    ``up`` is the gravity-up vector in the camera optical frame (any length; None means
    level camera, ``(0, -1, 0)``). Degenerate when the camera looks straight up or down;
    then the camera's -y axis replaces its forward axis as the reference.
    """
    # scalar arithmetic: numpy's per-call overhead made this 3x3 cost ~80 us, and it runs
    # several times a frame
    ux, uy, uz = (float(c) for c in np.asarray(DEFAULT_UP if up is None else up, dtype=np.float64).reshape(3))
    n = max(math.sqrt(ux * ux + uy * uy + uz * uz), 1e-12)
    ux, uy, uz = ux / n, uy / n, uz / n
    # y: the camera's forward axis (else its -y axis) made orthogonal to up
    yx, yy, yz = -ux * uz, -uy * uz, 1.0 - uz * uz
    if math.sqrt(yx * yx + yy * yy + yz * yz) < 1e-6:
        yx, yy, yz = uy * ux, -1.0 + uy * uy, uy * uz
    n = max(math.sqrt(yx * yx + yy * yy + yz * yz), 1e-12)
    yx, yy, yz = yx / n, yy / n, yz / n
    x = (yy * uz - yz * uy, yz * ux - yx * uz, yx * uy - yy * ux)  # y cross up
    return np.array([[x[0], yx, ux], [x[1], yy, uy], [x[2], yz, uz]])


def heading_to_rotation(theta: float, up: np.ndarray | None) -> np.ndarray:
    """Camera-frame rotation (3,3) of a yaw-only box with heading ``theta`` (rad) in ``U``."""
    return upright_rotation(up) @ rot_z(theta)


def rotation_to_heading(rotation: np.ndarray, up: np.ndarray | None) -> float:
    """Heading (rad, in (-pi, pi]) of a box's x axis in the upright frame built from ``up``."""
    x_u = upright_rotation(up).T @ np.asarray(rotation, dtype=np.float64)[:, 0]
    return float(np.arctan2(x_u[1], x_u[0]))


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


#: unit-cube corner signs, ordered: bottom face (z=-) counter-clockwise, then top face.
CORNER_SIGNS = np.array(
    [
        [1, 1, -1],
        [-1, 1, -1],
        [-1, -1, -1],
        [1, -1, -1],
        [1, 1, 1],
        [-1, 1, 1],
        [-1, -1, 1],
        [1, -1, 1],
    ],
    dtype=np.float64,
)

#: the 12 edges of a box as pairs of indices into :func:`box_corners`' output.
BOX_EDGES: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 2), (2, 3), (3, 0),
    (4, 5), (5, 6), (6, 7), (7, 4),
    (0, 4), (1, 5), (2, 6), (3, 7),
)


def box_corners(center: np.ndarray, size: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """The 8 corners (8,3) of an oriented box (same frame as ``center``), see ``CORNER_SIGNS``."""
    half = 0.5 * np.asarray(size, dtype=np.float64).reshape(1, 3)
    local = CORNER_SIGNS * half
    return local @ np.asarray(rotation, dtype=np.float64).T + np.asarray(center).reshape(1, 3)


def points_in_box(
    points: np.ndarray, center: np.ndarray, size: np.ndarray, rotation: np.ndarray, margin: float = 0.0
) -> np.ndarray:
    """Boolean mask (N,) of ``points`` (N,3) inside the oriented box grown by ``margin`` m."""
    local = (np.asarray(points, dtype=np.float64) - np.asarray(center).reshape(1, 3)) @ np.asarray(
        rotation, dtype=np.float64
    )
    half = 0.5 * np.asarray(size, dtype=np.float64).reshape(1, 3) + margin
    return np.all(np.abs(local) <= half, axis=1)


def project_points(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N,2) of camera-frame points (N,3) with z > 0 (pixel-centre convention)."""
    p = np.asarray(points, dtype=np.float64)
    uvw = p @ np.asarray(K, dtype=np.float64).T
    return uvw[:, :2] / uvw[:, 2:3]


def measured_depth(cam: np.ndarray, depth: np.ndarray, K: np.ndarray, min_z: float = 0.05) -> np.ndarray:
    """The depth map's value (metres) at the pixel each camera-frame point (..., 3) projects to;
    NaN for points nearer than ``min_z``, outside the image or on an invalid (0 / NaN) pixel.
    Comparing it with the point's own z tells seen through (larger), surface or hidden."""
    cam = np.asarray(cam, dtype=np.float64)
    z = cam[..., 2]
    h, w = depth.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.floor(project_points(cam.reshape(-1, 3), K) + 0.5).reshape(*z.shape, 2)
    u, v = uv[..., 0], uv[..., 1]
    inside = (z > min_z) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.full(z.shape, np.nan)
    d[inside] = depth[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    d[~(d > 0)] = np.nan
    return d
