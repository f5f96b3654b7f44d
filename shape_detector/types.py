"""Plain data types shared by every stage of the pipeline.

Frames and units: everything 3D is in the **camera optical frame** (x right, y down,
z forward) in metres unless a docstring says otherwise; stamps are integer
nanoseconds; 2D boxes are ``(x1, y1, x2, y2)`` pixel *edges* (``x2 = last column + 1``,
so a box's width is ``x2 - x1``).

A box's ``rotation`` is a 3x3 matrix whose columns are the box's x, y, z axes in the
camera frame; ``size = (l, w, h)`` are the full extents along those columns. For
furniture the z column is gravity-up (yaw about gravity only) and x is the object's
facing (heading) direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

Box2D = tuple[float, float, float, float]


def _vec(a: Any, n: int = 3) -> np.ndarray:
    out = np.asarray(a, dtype=np.float64).reshape(n)
    return out


@dataclass
class Cuboid:
    """An oriented cuboid: centre (3,) m, full size (3,) m, rotation (3,3) columns = axes."""

    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        self.center = _vec(self.center)
        self.size = _vec(self.size)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)

    def to_dict(self) -> dict[str, list]:
        """JSON-ready dict: ``center``, ``size``, ``rotation`` as lists."""
        return {
            "center": self.center.tolist(),
            "size": self.size.tolist(),
            "rotation": self.rotation.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Cuboid:
        """The cuboid stored by :meth:`to_dict`."""
        return cls(np.array(d["center"]), np.array(d["size"]), np.array(d["rotation"]))

    def transformed(self, R: np.ndarray, t: np.ndarray) -> Cuboid:
        """This cuboid under ``p' = R p + t``."""
        return Cuboid(R @ self.center + t, self.size.copy(), R @ self.rotation)


@dataclass
class Object3D:
    """One detected object, camera optical frame, metres.

    ``score`` is the detector's confidence in [0, 1]; ``box2d`` the 2D proposal it came
    from; ``primitives`` the predicted cuboid shape abstraction (camera frame).
    """

    class_name: str
    score: float
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    box2d: Box2D = (0.0, 0.0, 0.0, 0.0)
    primitives: list[Cuboid] = field(default_factory=list)
    #: diagnostics: flat pixel indices (v * W + u) of the frustum's sampled points and the
    #: network's foreground decision for each (None when not computed).
    pixel_index: np.ndarray | None = field(default=None, repr=False)
    seg_labels: np.ndarray | None = field(default=None, repr=False)
    #: the network's foreground probability of each of those points (``seg_labels`` is
    #: ``seg_prob > 0.5``); the geometric post-processing can ask for surer points
    seg_prob: np.ndarray | None = field(default=None, repr=False)
    #: the network's calibrated probability of each class of ``CLASSES`` (background
    #: excluded, so it sums to 1 - P(background)); None when not computed.
    class_scores: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.center = _vec(self.center)
        self.size = _vec(self.size)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)

    @property
    def cuboid(self) -> Cuboid:
        """The box as a :class:`Cuboid` (camera optical frame, metres)."""
        return Cuboid(self.center, self.size, self.rotation)

    def set_extent(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Make the box span ``[lo, hi]`` (3,) along its own axes (metres, in its current
        frame: centre at the origin, axes = ``rotation``'s columns), rotation kept. The
        primitives, which the network predicts in units of the box, stretch with it: a part
        flush with a box face stays flush with it."""
        from .geometry import stretch_cuboids

        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        R, c0 = self.rotation, self.center
        mid = 0.5 * (lo + hi)
        if self.primitives:
            local_c, sizes = stretch_cuboids(
                (np.stack([p.center for p in self.primitives]) - c0) @ R,
                np.stack([p.size for p in self.primitives]),
                R.T @ np.stack([p.rotation for p in self.primitives]),
                (hi - lo) / np.maximum(self.size, 1e-9),
            )
            new_c = c0 + (mid + local_c) @ R.T
            self.primitives = [Cuboid(c, s, p.rotation) for c, s, p in zip(new_c, sizes, self.primitives)]
        self.center = c0 + R @ mid
        self.size = hi - lo


@dataclass
class GTObject:
    """Ground truth for one object of a generated (or loaded) frame. Camera frame, metres.

    ``heading`` is the yaw of the box x axis in the upright frame (see
    :func:`shape_detector.geometry.upright_rotation`), radians; ``parts`` the exact cuboid
    parts the object is built from (shape ground truth; empty when unknown);
    ``visible_fraction`` the share of the object's projected pixels that are not occluded
    (truncation by the image border counts as not visible); ``instance_id`` its value in
    the frame's instance mask.
    """

    class_name: str
    box2d: Box2D
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    heading: float = 0.0
    parts: list[Cuboid] = field(default_factory=list)
    visible_fraction: float = 1.0
    instance_id: int = 0

    def __post_init__(self) -> None:
        self.center = _vec(self.center)
        self.size = _vec(self.size)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        self.box2d = tuple(float(v) for v in self.box2d)  # type: ignore[assignment]

    @property
    def cuboid(self) -> Cuboid:
        """The amodal box as a :class:`Cuboid` (camera optical frame, metres)."""
        return Cuboid(self.center, self.size, self.rotation)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field (arrays as lists, parts as cuboid dicts)."""
        return {
            "class_name": self.class_name,
            "box2d": list(self.box2d),
            "center": self.center.tolist(),
            "size": self.size.tolist(),
            "rotation": self.rotation.tolist(),
            "heading": float(self.heading),
            "parts": [p.to_dict() for p in self.parts],
            "visible_fraction": float(self.visible_fraction),
            "instance_id": int(self.instance_id),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GTObject:
        """The object stored by :meth:`to_dict` (missing optional fields take their defaults)."""
        return cls(
            class_name=d["class_name"],
            box2d=tuple(d["box2d"]),
            center=np.array(d["center"]),
            size=np.array(d["size"]),
            rotation=np.array(d["rotation"]),
            heading=float(d.get("heading", 0.0)),
            parts=[Cuboid.from_dict(p) for p in d.get("parts", [])],
            visible_fraction=float(d.get("visible_fraction", 1.0)),
            instance_id=int(d.get("instance_id", 0)),
        )


@dataclass
class Frame:
    """One RGB-D frame with its calibration.

    ``rgb``: HxWx3 uint8 RGB. ``depth``: HxW float32 metres, registered to ``rgb``,
    NaN where invalid. ``K``: 3x3 intrinsics of ``rgb``. ``up``: gravity-up unit vector
    in the camera optical frame, or None when unknown. ``objects``: ground truth when the
    frame comes from the generator or a labelled dataset; ``instance_mask``: HxW int32,
    0 = no labelled object, ``objects[i].instance_id`` otherwise. ``clutter_boxes``: visible
    2D boxes of unlabelled clutter (negatives for training the classification head).
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    up: np.ndarray | None = None
    stamp_ns: int = 0
    frame_id: str = "camera_color_optical_frame"
    objects: list[GTObject] = field(default_factory=list)
    instance_mask: np.ndarray | None = None
    clutter_boxes: list[Box2D] = field(default_factory=list)

    @property
    def height(self) -> int:
        """Image height (px)."""
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        """Image width (px)."""
        return int(self.depth.shape[1])
