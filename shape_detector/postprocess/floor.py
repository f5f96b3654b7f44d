"""Floor contact: furniture stands on the floor, so a box whose bottom lands near the
measured floor plane gets its bottom put on it (its top, which the camera sees, is kept).

The network places the top of a box well (it is usually visible) and the bottom less
well (legs and lower parts are the first to be occluded). With the floor measured from
the depth, the bottom is known to within a couple of centimetres.
"""

from __future__ import annotations

import numpy as np

from ..types import Object3D


def snap_to_floor(
    objects: list[Object3D], up: np.ndarray, floor_height: float | None, max_gap: float = 0.25, min_height: float = 0.05
) -> list[Object3D]:
    """Objects with the bottom face moved onto the floor where it is within ``max_gap`` m.

    ``up``: unit gravity-up in the camera optical frame; ``floor_height``: the camera's
    height above the floor (m, the floor plane is ``up . p = -floor_height``), None = no
    floor seen (objects returned unchanged). The box keeps its top face, yaw and footprint;
    its centre moves along ``up`` and its height (``size[2]``, along ``up``) changes;
    primitives stretch with the box (:meth:`Object3D.set_extent`: a part at the box top
    stays at the top). Objects in place, also returned.
    """
    if floor_height is None or max_gap <= 0.0 or not objects:
        return objects
    u = np.asarray(up, dtype=np.float64).reshape(3)
    u = u / np.linalg.norm(u)
    floor = -float(floor_height)
    for obj in objects:
        c_up = float(obj.center @ u)
        top = c_up + 0.5 * float(obj.size[2])
        bottom = c_up - 0.5 * float(obj.size[2])
        if abs(bottom - floor) > max_gap or top - floor < min_height:
            continue
        half = 0.5 * obj.size
        obj.set_extent([-half[0], -half[1], floor - c_up], [half[0], half[1], half[2]])
    return objects
