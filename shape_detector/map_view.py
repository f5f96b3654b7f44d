"""Top view of a scene map: the navigation grid with the tracked boxes and their ids (for ``demo``).

World frame z up, metres; the picture has world +x to the right and +y up. Pure numpy + OpenCV.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from .classes import class_color
from .geometry import box_corners

UNKNOWN_RGB = (150, 150, 150)
FREE_RGB = (240, 240, 240)
OCCUPIED_RGB = (60, 60, 60)
PATH_RGB = (30, 120, 230)


def _world_to_px(xy: np.ndarray, origin: np.ndarray, res_m: float, scale: float, height_px: int) -> np.ndarray:
    """Pixel (u, v) of world points (N,2): column from x, row from -y (so +y is up)."""
    cells = (np.asarray(xy, dtype=np.float64).reshape(-1, 2) - origin) / res_m * scale
    return np.stack([cells[:, 0], height_px - cells[:, 1]], axis=1)


def draw_map(grid: Any, objects: Sequence[Any], height_px: int = 480,
             path_xy: np.ndarray | None = None) -> np.ndarray:
    """(height_px, W, 3) uint8 RGB top view of ``grid`` (a NavGrid: -1 unknown, 0 free, 100 occupied,
    row = y, col = x) with each object's footprint outlined in its class colour and labelled
    ``"<class> #<id>"``; ``path_xy`` (N,2) world x, y of the camera drawn as a line."""
    cells = np.asarray(grid.data)
    h, w = cells.shape if cells.ndim == 2 and cells.size else (1, 1)
    scale = height_px / h
    img = np.empty((h, w, 3), np.uint8)
    img[:] = UNKNOWN_RGB
    if cells.ndim == 2 and cells.size:
        img[cells == 0] = FREE_RGB
        img[cells >= 50] = OCCUPIED_RGB
    img = np.ascontiguousarray(cv2.resize(img[::-1], (max(1, int(round(w * scale))), height_px),
                                          interpolation=cv2.INTER_NEAREST))
    origin = np.asarray(grid.origin, dtype=np.float64).reshape(2)
    res = float(grid.resolution)
    if path_xy is not None and len(path_xy) > 1:
        pts = _world_to_px(path_xy, origin, res, scale, height_px).round().astype(np.int32)
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, PATH_RGB, 2, cv2.LINE_AA)
        cv2.circle(img, tuple(int(v) for v in pts[-1]), 5, PATH_RGB, -1, cv2.LINE_AA)
    for obj in objects:
        rgb = tuple(int(255 * c) for c in class_color(obj.class_name))
        corners = box_corners(np.asarray(obj.center), np.asarray(obj.size), np.asarray(obj.rotation))
        foot = corners[np.argsort(corners[:, 2])[:4], :2]  # the four lowest corners
        centre = foot.mean(axis=0)
        order = np.argsort(np.arctan2(foot[:, 1] - centre[1], foot[:, 0] - centre[0]))
        pts = _world_to_px(foot[order], origin, res, scale, height_px).round().astype(np.int32)
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], True, rgb, 2, cv2.LINE_AA)
        u, v = _world_to_px(centre, origin, res, scale, height_px)[0]
        text = f"{obj.class_name} #{int(obj.id)}"
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        org = (int(np.clip(u - tw / 2, 0, max(0, img.shape[1] - tw))), int(np.clip(v + th / 2, th, img.shape[0] - 2)))
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Two RGB images next to each other, both scaled to the taller one's height."""
    h = max(left.shape[0], right.shape[0])

    def fit(im: np.ndarray) -> np.ndarray:
        if im.shape[0] == h:
            return im
        return cv2.resize(im, (max(1, int(round(im.shape[1] * h / im.shape[0]))), h), interpolation=cv2.INTER_LINEAR)

    return np.concatenate([fit(left), fit(right)], axis=1)
