"""Hand-made scenes for the scene-map tests: world boxes rendered to depth from a pose.

World: z up, floor at z = 0. The camera stands at ``(x, y, h)`` looking along a heading
(level); depth comes from the synthetic renderer's z-buffer (no noise).
"""

from __future__ import annotations

import numpy as np

from shape_detector.synth.render import rasterize
from shape_detector.types import Cuboid, Object3D

W, H = 160, 120
K = np.array([[120.0, 0.0, 79.5], [0.0, 120.0, 59.5], [0.0, 0.0, 1.0]])


def rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose(x: float, y: float, h: float, heading: float) -> np.ndarray:
    """T_world_camera of a level camera at (x, y, h) looking along ``heading`` (radians)."""
    f = np.array([np.cos(heading), np.sin(heading), 0.0])
    right = np.array([np.sin(heading), -np.cos(heading), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, f], axis=1)
    T[:3, 3] = [x, y, h]
    return T


def room(extra: list[tuple] = ()) -> list[tuple]:
    """World boxes (center, size, yaw): a 10 x 10 m floor slab and walls at x = 8 and x = -8, plus ``extra``."""
    return [((0.0, 0.0, -0.05), (20.0, 20.0, 0.1), 0.0), ((8.1, 0.0, 1.5), (0.2, 20.0, 3.0), 0.0),
            ((-8.1, 0.0, 1.5), (0.2, 20.0, 3.0), 0.0), *extra]


def render(boxes: list[tuple], T: np.ndarray) -> np.ndarray:
    """(H, W) float32 depth (metres, NaN where nothing) of world ``boxes`` seen from ``T``."""
    R, t = T[:3, :3], T[:3, 3]
    c = np.array([(np.asarray(b[0]) - t) @ R for b in boxes])
    s = np.array([b[1] for b in boxes], dtype=np.float64)
    r = np.array([R.T @ rotz(b[2]) for b in boxes])
    d, _, _ = rasterize(c, s, r, K, W, H)
    d = d.astype(np.float32)
    d[~np.isfinite(d)] = np.nan
    return d


def detection(center, size, yaw: float, T: np.ndarray, cls: str = "chair", score: float = 0.95,
              parts: list[tuple] = ()) -> Object3D:
    """A detector object (camera frame) for the world box (center, size, yaw) seen from ``T``."""
    R, t = T[:3, :3], T[:3, 3]
    Rc = R.T @ rotz(yaw)
    prims = [Cuboid(R.T @ (np.asarray(pc) - t), ps, Rc) for pc, ps in parts]
    return Object3D(cls, score, R.T @ (np.asarray(center, float) - t), np.asarray(size, float), Rc, primitives=prims)


def test_render_sees_the_floor_and_a_box():
    T = pose(0.0, 0.0, 1.2, 0.0)
    d = render(room([((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)]), T)
    assert abs(float(d[H // 2 + 30, W // 2]) - 2.75) < 0.02  # the box's front face
    assert np.isfinite(d[-1]).all()  # the floor at the bottom row
