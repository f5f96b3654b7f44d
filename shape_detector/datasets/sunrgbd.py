"""Loader for SUN RGB-D frames in VoteNet's prepared format -> :class:`Frame` with GT.

Layout under ``root``: ``image/NNNNNN.jpg``, ``depth/NNNNNN.mat`` (key ``instance``: (n,6)
float32 x y z r g b, rgb in 0..1, points in the *upright depth* frame: x right, y forward,
z up), ``calib/NNNNNN.txt`` (line 1 Rtilt, line 2 K, both 9 numbers column-major),
``label/NNNNNN.txt`` (``class xmin ymin w h cx cy cz hw hl hh ox oy``: 2D box, 3D centre in
upright coords, HALF sizes (hw along the box's local y, hl along local x, hh along up),
local x axis direction (ox, oy) in the upright x-y plane).

Conversions: upright -> camera-depth (x right, y forward, z up) is ``Rtilt.T @ p``;
camera-depth -> optical is ``(x, -z, y)``; pixels are ``K @ p_optical`` in MATLAB's
1-based convention (we subtract 1). The depth image is rebuilt by projecting the points;
pixels without a point are NaN. Reading ``.mat`` needs scipy (imported lazily).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..classes import CLASS_TO_ID
from ..geometry import rotation_to_heading
from ..types import Frame, GTObject

#: camera-depth (x right, y forward, z up) -> ROS optical (x right, y down, z forward)
DEPTH_TO_OPTICAL = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


def read_calib(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(Rtilt, K)`` 3x3 each from a VoteNet calib file (column-major numbers)."""
    lines = Path(path).read_text().split("\n")
    rtilt = np.array([float(v) for v in lines[0].split()]).reshape(3, 3, order="F")
    K = np.array([float(v) for v in lines[1].split()]).reshape(3, 3, order="F")
    return rtilt, K


def upright_to_optical(rtilt: np.ndarray) -> np.ndarray:
    """Rotation taking upright-depth coordinates to the camera optical frame.

    Rtilt is stored to 5 digits, so it is first projected onto the nearest rotation (SVD).
    """
    u, _, vt = np.linalg.svd(rtilt)
    return DEPTH_TO_OPTICAL @ (u @ vt).T


def read_labels(path: Path, R_ou: np.ndarray, up: np.ndarray) -> list[GTObject]:
    """GT objects of our ten classes (others, e.g. 'lamp', are skipped), optical frame."""
    objects: list[GTObject] = []
    for line in Path(path).read_text().splitlines():
        f = line.split()
        if len(f) < 13 or f[0] not in CLASS_TO_ID:
            continue
        xmin, ymin, w, h, cx, cy, cz, hw, hl, hh, ox, oy = (float(v) for v in f[1:13])
        x_u = np.array([ox, oy, 0.0]) / max(np.hypot(ox, oy), 1e-12)
        z_u = np.array([0.0, 0.0, 1.0])
        R_u = np.stack([x_u, np.cross(z_u, x_u), z_u], axis=1)
        R = R_ou @ R_u
        objects.append(
            GTObject(
                class_name=f[0],
                box2d=(xmin - 1.0, ymin - 1.0, xmin - 1.0 + w, ymin - 1.0 + h),
                center=R_ou @ np.array([cx, cy, cz]),
                size=np.array([2 * hl, 2 * hw, 2 * hh]),
                rotation=R,
                heading=rotation_to_heading(R, up),
                instance_id=len(objects) + 1,
            )
        )
    return objects


def points_to_depth(points_optical: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """HxW float32 depth (metres, NaN where no point) by z-buffered projection, 0-based pixels."""
    p = points_optical[points_optical[:, 2] > 1e-6]
    uv = p @ K.T
    u = np.rint(uv[:, 0] / uv[:, 2]).astype(np.int64)
    v = np.rint(uv[:, 1] / uv[:, 2]).astype(np.int64)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z = u[ok], v[ok], p[ok, 2].astype(np.float32)
    depth = np.full(height * width, np.inf, np.float32)
    np.minimum.at(depth, v * width + u, z)
    depth[~np.isfinite(depth)] = np.nan
    return depth.reshape(height, width)


def load_frame(root: str | Path, index: int | str) -> Frame:
    """One SUN RGB-D frame (VoteNet format) as a :class:`Frame` with GT boxes (no parts)."""
    from scipy.io import loadmat  # optional dependency: only this loader needs it

    root = Path(root)
    name = f"{int(index):06d}" if not isinstance(index, str) else index
    bgr = cv2.imread(str(root / "image" / f"{name}.jpg"), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(root / "image" / f"{name}.jpg")
    rgb = bgr[:, :, ::-1].copy()
    rtilt, K_matlab = read_calib(root / "calib" / f"{name}.txt")
    K = K_matlab.copy()
    K[0, 2] -= 1.0
    K[1, 2] -= 1.0
    R_ou = upright_to_optical(rtilt)
    up = R_ou @ np.array([0.0, 0.0, 1.0])
    pts_u = loadmat(str(root / "depth" / f"{name}.mat"))["instance"][:, :3].astype(np.float64)
    depth = points_to_depth(pts_u @ R_ou.T, K, rgb.shape[1], rgb.shape[0])
    objects = read_labels(root / "label" / f"{name}.txt", R_ou, up)
    return Frame(rgb=rgb, depth=depth, K=K, up=up, objects=objects, frame_id="kinect_optical_frame")
