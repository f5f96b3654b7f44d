"""Detections -> ``visualization_msgs/MarkerArray`` for RViz / Foxglove, plus quaternions."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from shape_detector.classes import class_color
from shape_detector.geometry import BOX_EDGES, box_corners
from shape_detector.types import Object3D

from .msgtypes import MsgTypes
from .stamps import make_header, seconds_to_duration

# visualization_msgs/Marker constants (same values in every ROS 2 distro).
CUBE = 1
LINE_LIST = 5
TEXT_VIEW_FACING = 9
ADD = 0
DELETEALL = 3

NS_BOXES = "boxes"
NS_WIREFRAMES = "wireframes"
NS_LABELS = "labels"
NS_PRIMITIVES = "primitives"

LINE_WIDTH = 0.015  # m
TEXT_HEIGHT = 0.12  # m
LABEL_GAP = 0.08  # m between the box top and the label
PRIMITIVE_ALPHA = 0.8
MIN_SCALE = 1e-3  # RViz rejects zero-size cubes


def _nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The proper rotation closest (Frobenius) to ``R``."""
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        U = U.copy()
        U[:, -1] *= -1
        Rn = U @ Vt
    return Rn


def rotation_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)``, ``w >= 0``, of a 3x3 rotation matrix.

    ``R`` is first projected onto the nearest proper rotation (so slightly non-orthogonal
    matrices, and reflections, give the closest valid quaternion); Shepperd's method picks
    the numerically stable branch. Raises ``ValueError`` for non-finite or wrongly shaped
    input.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"rotation must be 3x3, got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("rotation contains NaN or Inf")
    R = _nearest_rotation(R)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def quaternion_to_rotation(q: Sequence[float] | Any) -> np.ndarray:
    """3x3 rotation of a quaternion ``(x, y, z, w)`` or a message with ``x, y, z, w``."""
    if hasattr(q, "w"):
        q = (q.x, q.y, q.z, q.w)
    x, y, z, w = (float(v) for v in q)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"quaternion {q!r} has zero or non-finite norm")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def make_pose(types: MsgTypes, center: Any, rotation: Any) -> Any:
    """A ``geometry_msgs/Pose`` at ``center`` with the orientation of ``rotation`` (3x3)."""
    c = np.asarray(center, dtype=np.float64).reshape(3)
    qx, qy, qz, qw = rotation_to_quaternion(rotation)
    return types.make(
        types.Pose,
        position=types.make(types.Point, x=float(c[0]), y=float(c[1]), z=float(c[2])),
        orientation=types.make(types.Quaternion, x=qx, y=qy, z=qz, w=qw),
    )


def _color(types: MsgTypes, rgb: Sequence[float], alpha: float) -> Any:
    return types.make(types.ColorRGBA, r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(alpha))


def _vec3(types: MsgTypes, v: Any) -> Any:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return types.make(types.Vector3, x=float(v[0]), y=float(v[1]), z=float(v[2]))


def delete_all_marker(types: MsgTypes, header: Any) -> Any:
    """A DELETEALL marker (ns ``''``, id 0): clears what earlier arrays on the topic drew."""
    return types.make(
        types.Marker, header=header, ns="", id=0, type=CUBE, action=DELETEALL,
        pose=make_pose(types, np.zeros(3), np.eye(3)), scale=_vec3(types, (1.0, 1.0, 1.0)),
        color=_color(types, (1.0, 1.0, 1.0), 1.0),
    )


def _box_markers(marker: Callable[..., Any], types: MsgTypes, i: int, obj: Object3D, rgb: Sequence[float],
                 box_alpha: float) -> list[Any]:
    """The translucent CUBE, the LINE_LIST of the 12 edges and the label of object ``i``."""
    M = types.make
    center = np.asarray(obj.center, dtype=np.float64).reshape(3)
    size = np.asarray(obj.size, dtype=np.float64).reshape(3)
    R = np.asarray(obj.rotation, dtype=np.float64).reshape(3, 3)
    corners = box_corners(center, size, R)
    pts = [M(types.Point, x=float(p[0]), y=float(p[1]), z=float(p[2])) for e in BOX_EDGES for p in corners[list(e)]]
    up = R[:, 2] / max(np.linalg.norm(R[:, 2]), 1e-12)
    label_pos = center + up * (0.5 * size[2] + LABEL_GAP)
    return [
        marker(NS_BOXES, i, CUBE, pose=make_pose(types, center, R),
               scale=_vec3(types, np.maximum(size, MIN_SCALE)), color=_color(types, rgb, box_alpha)),
        marker(NS_WIREFRAMES, i, LINE_LIST, pose=make_pose(types, np.zeros(3), np.eye(3)),
               scale=_vec3(types, (LINE_WIDTH, 0.0, 0.0)), color=_color(types, rgb, 1.0), points=pts),
        marker(NS_LABELS, i, TEXT_VIEW_FACING, pose=make_pose(types, label_pos, np.eye(3)),
               scale=_vec3(types, (0.0, 0.0, TEXT_HEIGHT)), color=_color(types, rgb, 1.0),
               text=f"{obj.class_name} {float(obj.score):.2f}"),
    ]


def objects_to_markers(
    objects: Sequence[Object3D],
    types: MsgTypes,
    stamp_ns: int,
    frame_id: str,
    lifetime_s: float = 0.0,
    show_primitives: bool = True,
    box_alpha: float = 0.35,
) -> Any:
    """A MarkerArray drawing ``objects`` (camera frame ``frame_id``).

    Marker 0 is a DELETEALL (ns ``''``, id 0) clearing the previous frame's markers. Per
    object ``i``: a translucent CUBE (ns ``boxes``, id ``i``), a LINE_LIST of the 12 box
    edges (ns ``wireframes``, id ``i``, 24 points in the header frame), a TEXT_VIEW_FACING
    ``"<class> <score>"`` above the box along its up (z) axis (ns ``labels``, id ``i``) and,
    with ``show_primitives``, one CUBE per shape primitive (ns ``primitives``, ids counted
    over all objects). Colours are fixed per class; all markers share stamp and frame.
    """
    if not 0.0 < box_alpha <= 1.0:
        raise ValueError(f"box_alpha={box_alpha} must be in (0, 1]")
    header = make_header(types, stamp_ns, frame_id)
    lifetime = seconds_to_duration(lifetime_s, types)

    def marker(ns: str, mid: int, mtype: int, **kw: Any) -> Any:
        kw.setdefault("lifetime", lifetime)
        return types.make(types.Marker, header=header, ns=ns, id=int(mid), type=mtype, action=ADD, **kw)

    markers = [delete_all_marker(types, header)]
    prim_id = 0
    for i, obj in enumerate(objects):
        rgb = class_color(obj.class_name)
        markers += _box_markers(marker, types, i, obj, rgb, box_alpha)
        if show_primitives:
            for prim in obj.primitives:
                markers.append(marker(
                    NS_PRIMITIVES, prim_id, CUBE, pose=make_pose(types, prim.center, prim.rotation),
                    scale=_vec3(types, np.maximum(np.asarray(prim.size, dtype=np.float64), MIN_SCALE)),
                    color=_color(types, rgb, PRIMITIVE_ALPHA),
                ))
                prim_id += 1
    return types.make(types.MarkerArray, markers=markers)
