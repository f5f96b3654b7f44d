"""The ten SUN RGB-D furniture classes, their mean sizes and display colours.

Sizes are full extents in metres, ``(l, w, h)``: ``l`` along the box's x axis (the
object's facing / heading direction), ``w`` along its y axis, ``h`` along gravity-up.
The means are SUN RGB-D's (as used by VoteNet / Frustum PointNets); the network's
size head regresses residuals to these clusters.
"""

from __future__ import annotations

import numpy as np

CLASSES: tuple[str, ...] = (
    "bed",
    "table",
    "sofa",
    "chair",
    "toilet",
    "desk",
    "dresser",
    "night_stand",
    "bookshelf",
    "bathtub",
)
NUM_CLASSES = len(CLASSES)
CLASS_TO_ID: dict[str, int] = {name: i for i, name in enumerate(CLASSES)}

#: mean (l, w, h) per class in metres, SUN RGB-D statistics.
MEAN_SIZES: np.ndarray = np.array(
    [
        [2.114, 1.620, 0.927],  # bed
        [0.791, 1.280, 0.718],  # table
        [0.924, 1.867, 0.845],  # sofa
        [0.592, 0.553, 0.827],  # chair
        [0.700, 0.455, 0.756],  # toilet
        [0.699, 1.358, 0.736],  # desk
        [0.529, 1.003, 1.173],  # dresser
        [0.501, 0.632, 0.683],  # night_stand
        [0.405, 1.071, 1.689],  # bookshelf
        [0.766, 1.398, 0.473],  # bathtub
    ],
    dtype=np.float32,
)

#: fixed RGB colour per class, floats in [0, 1] (used for markers and figures).
CLASS_COLORS: np.ndarray = np.array(
    [
        [0.90, 0.10, 0.29],  # bed
        [0.24, 0.71, 0.29],  # table
        [1.00, 0.88, 0.10],  # sofa
        [0.26, 0.39, 0.85],  # chair
        [0.96, 0.51, 0.19],  # toilet
        [0.57, 0.12, 0.71],  # desk
        [0.27, 0.94, 0.94],  # dresser
        [0.94, 0.20, 0.90],  # night_stand
        [0.60, 0.39, 0.16],  # bookshelf
        [0.50, 0.50, 0.50],  # bathtub
    ],
    dtype=np.float32,
)


def class_id(name: str) -> int:
    """Index of ``name`` in :data:`CLASSES`; raises ``ValueError`` for unknown names."""
    try:
        return CLASS_TO_ID[name]
    except KeyError:
        raise ValueError(f"unknown class {name!r}; expected one of {CLASSES}") from None


def class_color(name: str) -> tuple[float, float, float]:
    """RGB colour in [0, 1] for a class name; grey for names outside :data:`CLASSES`."""
    idx = CLASS_TO_ID.get(name)
    if idx is None:
        return (0.7, 0.7, 0.7)
    r, g, b = CLASS_COLORS[idx]
    return (float(r), float(g), float(b))
