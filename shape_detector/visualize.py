"""Drawing detections onto images (cv2): projected 3D boxes, primitives, labels, depth maps."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .classes import class_color
from .geometry import BOX_EDGES, box_corners
from .types import Cuboid, GTObject, Object3D


def _bgr255(rgb01: tuple[float, float, float]) -> tuple[int, int, int]:
    r, g, b = rgb01
    return (int(255 * r), int(255 * g), int(255 * b))


def draw_cuboid(
    image: np.ndarray, cuboid: Cuboid, K: np.ndarray, color: tuple[int, int, int], thickness: int = 2, near: float = 0.05
) -> None:
    """Draw a camera-frame cuboid's 12 edges onto ``image`` (RGB uint8, in place).

    Edges are clipped against the plane z = ``near`` so boxes beside the camera draw sanely.
    """
    corners = box_corners(cuboid.center, cuboid.size, cuboid.rotation)
    for a, b in BOX_EDGES:
        p, q = corners[a].copy(), corners[b].copy()
        if p[2] < near and q[2] < near:
            continue
        if p[2] < near or q[2] < near:
            t = (near - p[2]) / (q[2] - p[2])
            r = p + t * (q - p)
            p, q = (r, q) if p[2] < near else (p, r)
        uv = np.stack([p, q]) @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        if not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e5:
            continue
        pt1 = tuple(int(round(v)) for v in uv[0])
        pt2 = tuple(int(round(v)) for v in uv[1])
        cv2.line(image, pt1, pt2, color, thickness, cv2.LINE_AA)


def draw_objects(
    rgb: np.ndarray,
    K: np.ndarray,
    objects: Sequence[Object3D | GTObject],
    primitives: bool = True,
    labels: bool = True,
    thickness: int = 2,
) -> np.ndarray:
    """A copy of ``rgb`` with each object's 3D box (class colour), primitives and label."""
    out = np.ascontiguousarray(rgb.copy())
    for obj in objects:
        col = _bgr255(class_color(obj.class_name))
        if primitives:
            for prim in getattr(obj, "primitives", None) or getattr(obj, "parts", []):
                draw_cuboid(out, prim, K, tuple(int(0.6 * c + 0.4 * 255) for c in col), 1)
        draw_cuboid(out, obj.cuboid, K, col, thickness)
        if labels and obj.center[2] > 0.05:
            uv = K @ obj.center
            u, v = int(uv[0] / uv[2]), int(uv[1] / uv[2])
            score = getattr(obj, "score", None)
            text = obj.class_name if score is None else f"{obj.class_name} {score:.2f}"
            cv2.putText(out, text, (u - 30, v), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(out, text, (u - 30, v), cv2.FONT_HERSHEY_SIMPLEX, 0.45, col, 1, cv2.LINE_AA)
    return out


def colorize_depth(depth: np.ndarray, max_depth: float = 6.0) -> np.ndarray:
    """HxWx3 uint8 RGB rendering of a metric depth map (invalid = black)."""
    d = np.nan_to_num(depth.astype(np.float32), nan=0.0)
    scaled = np.clip(d / max_depth * 255.0, 0, 255).astype(np.uint8)
    col = cv2.applyColorMap(255 - scaled, cv2.COLORMAP_TURBO)[:, :, ::-1].copy()
    col[d <= 0] = 0
    return col


def draw_boxes2d(image: np.ndarray, boxes: Sequence[Sequence[float]], color=(255, 255, 255), thickness: int = 1) -> np.ndarray:
    """A copy of ``image`` with pixel-edge 2D boxes ``(x1, y1, x2, y2, ...)`` drawn."""
    out = np.ascontiguousarray(image.copy())
    for b in boxes:
        x1, y1, x2, y2 = (int(round(float(v))) for v in list(b)[:4])
        cv2.rectangle(out, (x1, y1), (x2 - 1, y2 - 1), color, thickness)
    return out


def tile(images: Sequence[np.ndarray], cols: int) -> np.ndarray:
    """Images of one size in a grid, ``cols`` wide (missing cells black)."""
    h, w = images[0].shape[:2]
    rows = (len(images) + cols - 1) // cols
    grid = np.zeros((rows * h, cols * w, 3), np.uint8)
    for i, im in enumerate(images):
        r, c = divmod(i, cols)
        grid[r * h : (r + 1) * h, c * w : (c + 1) * w] = im
    return grid


def save_png(path, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image as PNG (creating parent folders)."""
    from pathlib import Path

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), rgb[:, :, ::-1]):
        raise OSError(f"could not write {path}")
