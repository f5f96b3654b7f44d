"""Usable surfaces -> ``visualization_msgs/MarkerArray``: outlined polygons labelled by affordance.

Surfaces are duck-typed (``object_id``, ``class_name``, ``height``, ``polygon`` (K,2),
``affordance``), as :func:`shape_detector.ar.surfaces` returns them, in the world frame
``frame_id`` (z up, metres). Works with rclpy and rosbags message classes alike.
"""

from __future__ import annotations

from typing import Any
from collections.abc import Sequence

import numpy as np

from .markers import make_pose
from .msgtypes import MsgTypes
from .stamps import make_header, seconds_to_duration

LINE_STRIP = 4
TEXT_VIEW_FACING = 9
ADD = 0
DELETEALL = 3

NS_OUTLINES = "surfaces"
NS_LABELS = "surface_labels"

#: RGB in [0, 1] per affordance (grey for others).
AFFORDANCE_COLORS: dict[str, tuple[float, float, float]] = {
    "sit": (1.0, 0.6, 0.15),
    "lie": (0.8, 0.25, 0.8),
    "place": (0.25, 0.8, 0.25),
}
LINE_WIDTH = 0.02  # m
TEXT_HEIGHT = 0.1  # m
LIFT = 0.01  # m above the surface, so the outline is not hidden inside the furniture's face
LABEL_LIFT = 0.08  # m


def surfaces_to_markers(surfaces: Sequence[Any], types: MsgTypes, stamp_ns: int, frame_id: str,
                        lifetime_s: float = 0.0) -> Any:
    """A MarkerArray: marker 0 a DELETEALL; per surface ``i`` a closed LINE_STRIP outline at its
    height (ns ``surfaces``, id ``i``) and a TEXT_VIEW_FACING ``"<affordance> (<class> #<id>)"``
    above its centre (ns ``surface_labels``, id ``i``). Surfaces with a non-finite or
    degenerate polygon are skipped."""
    M = types.make
    header = make_header(types, stamp_ns, frame_id)
    lifetime = seconds_to_duration(lifetime_s, types)
    identity = np.eye(3)

    def color(rgb: Sequence[float]) -> Any:
        return M(types.ColorRGBA, r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=1.0)

    def vec(x: float, y: float, z: float) -> Any:
        return M(types.Vector3, x=float(x), y=float(y), z=float(z))

    markers = [M(types.Marker, header=header, ns="", id=0, type=LINE_STRIP, action=DELETEALL,
                 pose=make_pose(types, np.zeros(3), identity), scale=vec(1, 1, 1), color=color((1, 1, 1)))]
    i = 0
    for s in surfaces:
        poly = np.asarray(s.polygon, dtype=np.float64).reshape(-1, 2)
        z = float(s.height)
        if len(poly) < 3 or not (np.all(np.isfinite(poly)) and np.isfinite(z)):
            continue
        rgb = AFFORDANCE_COLORS.get(str(s.affordance), (0.6, 0.6, 0.6))
        ring = np.vstack([poly, poly[:1]])
        pts = [M(types.Point, x=float(x), y=float(y), z=z + LIFT) for x, y in ring]
        markers.append(M(types.Marker, header=header, ns=NS_OUTLINES, id=i, type=LINE_STRIP, action=ADD,
                         pose=make_pose(types, np.zeros(3), identity), scale=vec(LINE_WIDTH, 0, 0), color=color(rgb),
                         points=pts, lifetime=lifetime))
        c = poly.mean(axis=0)
        markers.append(M(types.Marker, header=header, ns=NS_LABELS, id=i, type=TEXT_VIEW_FACING, action=ADD,
                         pose=make_pose(types, (c[0], c[1], z + LABEL_LIFT), identity), scale=vec(0, 0, TEXT_HEIGHT),
                         color=color(rgb), text=f"{s.affordance} ({s.class_name} #{s.object_id})",
                         lifetime=lifetime))
        i += 1
    return M(types.MarkerArray, markers=markers)
