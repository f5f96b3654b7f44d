"""The scene map -> ``visualization_msgs/MarkerArray`` and ``nav_msgs/OccupancyGrid`` (world frame).

Scene objects and grids are read by duck typing (``shape_detector.scene`` types or anything with
the same attributes), so this module imports nothing from the scene package.
"""

from __future__ import annotations

import array
from typing import Any
from collections.abc import Sequence

import numpy as np

from shape_detector.classes import class_color

from .markers import ADD, CUBE, DELETEALL, MIN_SCALE, TEXT_VIEW_FACING, make_pose
from .msgtypes import MsgTypes
from .stamps import make_header, ns_to_stamp

NS_OBJECTS = "objects"
NS_SCENE_PRIMITIVES = "primitives"
NS_SCENE_LABELS = "labels"
OBJECT_ALPHA = 0.4
PRIMITIVE_ALPHA = 0.8
TEXT_HEIGHT = 0.15  # m
LABEL_GAP = 0.1  # m between the box top and its label


def _vec3(types: MsgTypes, v: Any) -> Any:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return types.make(types.Vector3, x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _color(types: MsgTypes, rgb: Sequence[float], alpha: float) -> Any:
    return types.make(types.ColorRGBA, r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(alpha))


def scene_to_markers(objects: Sequence[Any], types: MsgTypes, stamp_ns: int, frame_id: str) -> Any:
    """A MarkerArray of the scene's confirmed objects (world frame ``frame_id``).

    Marker 0 is a DELETEALL so each message replaces the previous one. Per object: a CUBE in ns
    ``objects`` whose ``id`` is the track id, a TEXT_VIEW_FACING ``"<class> #<id>"`` above the box
    (ns ``labels``, same id) and one CUBE per primitive (ns ``primitives``, ids counted over all
    objects). Colours are fixed per class; lifetime 0 (kept until replaced).
    """
    M = types.make
    header = make_header(types, stamp_ns, frame_id)
    identity = np.eye(3)

    def marker(ns: str, mid: int, mtype: int, action: int = ADD, **kw: Any) -> Any:
        return M(types.Marker, header=header, ns=ns, id=int(mid), type=mtype, action=action, **kw)

    markers = [
        marker("", 0, CUBE, DELETEALL, pose=make_pose(types, np.zeros(3), identity),
               scale=_vec3(types, (1.0, 1.0, 1.0)), color=_color(types, (1.0, 1.0, 1.0), 1.0))
    ]
    prim_id = 0
    for obj in objects:
        rgb = class_color(obj.class_name)
        center = np.asarray(obj.center, dtype=np.float64).reshape(3)
        size = np.asarray(obj.size, dtype=np.float64).reshape(3)
        R = np.asarray(obj.rotation, dtype=np.float64).reshape(3, 3)
        markers.append(marker(NS_OBJECTS, obj.id, CUBE, pose=make_pose(types, center, R),
                              scale=_vec3(types, np.maximum(size, MIN_SCALE)), color=_color(types, rgb, OBJECT_ALPHA)))
        label_pos = center + np.array([0.0, 0.0, 0.5 * size[2] + LABEL_GAP])  # world z is up
        markers.append(marker(NS_SCENE_LABELS, obj.id, TEXT_VIEW_FACING, pose=make_pose(types, label_pos, identity),
                              scale=_vec3(types, (0.0, 0.0, TEXT_HEIGHT)), color=_color(types, rgb, 1.0),
                              text=f"{obj.class_name} #{int(obj.id)}"))
        for prim in getattr(obj, "primitives", ()) or ():
            markers.append(marker(NS_SCENE_PRIMITIVES, prim_id, CUBE, pose=make_pose(types, prim.center, prim.rotation),
                                  scale=_vec3(types, np.maximum(np.asarray(prim.size, dtype=np.float64), MIN_SCALE)),
                                  color=_color(types, rgb, PRIMITIVE_ALPHA)))
            prim_id += 1
    return M(types.MarkerArray, markers=markers)


def _grid_data(cells: np.ndarray, types: MsgTypes) -> Any:
    flat = np.ascontiguousarray(cells, dtype=np.int8).reshape(-1)
    if types.flavour == "rclpy":
        out = array.array("b")
        out.frombytes(flat.tobytes())
        return out
    return flat.copy()


def grid_to_occupancy(grid: Any, types: MsgTypes, stamp_ns: int, frame_id: str) -> Any:
    """A ``nav_msgs/OccupancyGrid`` of a NavGrid (``resolution`` m/cell, ``origin`` (2,) world x, y of
    cell (0, 0)'s corner, ``data`` (height, width) int8 with row = y, col = x, ``floor_z``).

    The map origin is at the floor height with identity orientation; cells are row-major (ROS's
    convention), -1 unknown, 0 free, 100 occupied. ``ValueError`` for a grid that is not 2-D.
    """
    cells = np.asarray(grid.data)
    if cells.ndim != 2:
        raise ValueError(f"grid data must be 2-D (height, width), got shape {cells.shape}")
    height, width = cells.shape
    origin = np.asarray(grid.origin, dtype=np.float64).reshape(2)
    floor_z = float(getattr(grid, "floor_z", 0.0))
    M = types.make_by_name
    info = M(
        "nav_msgs/msg/MapMetaData",
        map_load_time=ns_to_stamp(stamp_ns, types),
        resolution=float(grid.resolution),
        width=int(width),
        height=int(height),
        origin=make_pose(types, (origin[0], origin[1], floor_z), np.eye(3)),
    )
    return M("nav_msgs/msg/OccupancyGrid", header=make_header(types, stamp_ns, frame_id), info=info,
             data=_grid_data(cells, types))


def occupancy_to_cells(msg: Any) -> np.ndarray:
    """(height, width) int8 cells of an OccupancyGrid of either flavour (row = y, col = x)."""
    data = msg.data
    if isinstance(data, array.array):
        flat = np.frombuffer(data, dtype=np.int8)
    else:
        flat = np.asarray(data).astype(np.int8, copy=False).reshape(-1)
    h, w = int(msg.info.height), int(msg.info.width)
    if flat.size != h * w:
        raise ValueError(f"OccupancyGrid has {flat.size} cells, expected {h}x{w}")
    return flat.reshape(h, w)
