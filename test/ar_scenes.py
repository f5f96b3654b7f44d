"""Hand-made scenes with known answers for the AR query tests (world frame, z up, metres)."""

from __future__ import annotations

import base64

import numpy as np

from shape_detector.ar.scene_data import ArScene
from shape_detector.scene.grid import NavGrid
from shape_detector.scene.types import SceneObject, ScenePrimitive


def rotz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def table(oid: int, xy: tuple[float, float], yaw: float = 0.0, size=(1.0, 0.6, 0.75), top: float = 0.05) -> SceneObject:
    """A table: a top slab (primitive 0) and four 5 cm legs (1..4), turned by ``yaw``."""
    R = rotz(yaw)
    c = np.array([xy[0], xy[1], 0.0])
    ln, w, h = size
    prims = [ScenePrimitive(c + R @ np.array([0, 0, h - top / 2]), np.array([ln, w, top]), R)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            off = np.array([sx * (ln / 2 - 0.025), sy * (w / 2 - 0.025), (h - top) / 2])
            prims.append(ScenePrimitive(c + R @ off, np.array([0.05, 0.05, h - top]), R))
    return SceneObject(oid, "table", 1.0, c + np.array([0, 0, h / 2]), np.array(size, float), R, primitives=prims)


def chair(oid: int, xy: tuple[float, float]) -> SceneObject:
    """A chair facing +x: seat (0) 0.5 x 0.5 at 0.45 m, back (1) 5 cm thick up to 0.9 m."""
    c = np.array([xy[0], xy[1], 0.0])
    I3 = np.eye(3)
    prims = [
        ScenePrimitive(c + [0, 0, 0.225], np.array([0.5, 0.5, 0.45]), I3),
        ScenePrimitive(c + [-0.225, 0, 0.675], np.array([0.05, 0.5, 0.45]), I3),
    ]
    return SceneObject(oid, "chair", 1.0, c + [0, 0, 0.45], np.array([0.5, 0.5, 0.9]), I3, primitives=prims)


def bed(oid: int, xy: tuple[float, float]) -> SceneObject:
    """A bed: frame (0) to 0.3 m fully covered by the mattress (1) up to 0.55 m."""
    c = np.array([xy[0], xy[1], 0.0])
    I3 = np.eye(3)
    prims = [
        ScenePrimitive(c + [0, 0, 0.15], np.array([2.0, 1.6, 0.3]), I3),
        ScenePrimitive(c + [0, 0, 0.425], np.array([1.95, 1.55, 0.25]), I3),
    ]
    return SceneObject(oid, "bed", 1.0, c + [0, 0, 0.275], np.array([2.0, 1.6, 0.55]), I3, primitives=prims)


def box_object(oid: int, cls: str, center, size, yaw: float = 0.0) -> SceneObject:
    """An object without primitives (its own box is used)."""
    return SceneObject(oid, cls, 1.0, np.array(center, float), np.array(size, float), rotz(yaw), primitives=[])


def wall_grid(gap: bool = True, res: float = 0.05, width: float = 1.0) -> NavGrid:
    """A 4 m x 4 m free floor at origin (0, 0) with a 10 cm wall along x = 2 m; with ``gap``
    the wall leaves an opening ``width`` m wide from y = 1.5 m (default: y in [1.5, 2.5])."""
    n = int(round(4.0 / res))
    data = np.zeros((n, n), np.int8)
    col = int(round(2.0 / res))
    data[:, col : col + 2] = 100
    if gap:
        data[int(round(1.5 / res)) : int(round((1.5 + width) / res)), col : col + 2] = 0
    return NavGrid(res, np.zeros(2), data)


def scene_json(scene: ArScene) -> dict:
    """The scene in the ``--scene-out`` JSON schema (grid as base64 int8)."""
    objs = [{"id": o.id, "class": o.class_name, "score": o.score, "center": o.center.tolist(),
             "size": o.size.tolist(), "rotation": o.rotation.tolist(), "yaw": 0.0, "observations": 3,
             "first_seen_ns": 0, "last_seen_ns": 0,
             "primitives": [{"center": p.center.tolist(), "size": p.size.tolist(), "rotation": p.rotation.tolist()}
                            for p in o.primitives]} for o in scene.objects]
    out: dict = {"frame_id": "odom", "stamp_ns": 1, "objects": objs}
    g = scene.grid
    if g is not None:
        out["grid"] = {"resolution": g.resolution, "origin": g.origin.tolist(), "width": g.width, "height": g.height,
                       "floor_z": g.floor_z, "encoding": "base64-int8",
                       "data": base64.b64encode(np.ascontiguousarray(g.data, np.int8).tobytes()).decode("ascii")}
    return out
