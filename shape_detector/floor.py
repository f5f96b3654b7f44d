"""Floor contact: furniture stands on the floor, so a box whose bottom lands near the
measured floor plane gets its bottom put on it (its top, which the camera sees, is kept).

The network places the top of a box well (it is usually visible) and the bottom less
well (legs and lower parts are the first to be occluded). With the floor measured from
the depth, the bottom is known to within a couple of centimetres.
"""

from __future__ import annotations

import numpy as np

from .geometry import stretch_cuboids
from .types import Cuboid, Object3D


def snap_to_floor(
    objects: list[Object3D], up: np.ndarray, floor_height: float | None, max_gap: float = 0.25, min_height: float = 0.05
) -> list[Object3D]:
    """Objects with the bottom face moved onto the floor where it is within ``max_gap`` m.

    ``up``: unit gravity-up in the camera optical frame; ``floor_height``: the camera's
    height above the floor (m, the floor plane is ``up . p = -floor_height``), None = no
    floor seen (objects returned unchanged). The box keeps its top face, yaw and footprint;
    its centre moves along ``up`` and its height (``size[2]``, along ``up``) changes;
    primitives stretch with the box (they are predicted in units of its size, so a part
    at the box top stays at the top). Objects in place, also returned.
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
        shift = 0.5 * (top + floor) - c_up
        ratio = np.array([1.0, 1.0, (top - floor) / max(float(obj.size[2]), 1e-9)])
        if obj.primitives:
            R, c0 = obj.rotation, obj.center
            local_c, sizes = stretch_cuboids(
                (np.stack([p.center for p in obj.primitives]) - c0) @ R,
                np.stack([p.size for p in obj.primitives]),
                R.T @ np.stack([p.rotation for p in obj.primitives]),
                ratio,
            )
            new_c = c0 + shift * u + local_c @ R.T
            obj.primitives = [Cuboid(c, s, p.rotation) for c, s, p in zip(new_c, sizes, obj.primitives)]
        obj.center = obj.center + shift * u
        obj.size = np.array([obj.size[0], obj.size[1], top - floor])
    return objects
