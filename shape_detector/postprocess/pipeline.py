"""Post-processing of the network's objects as an ordered pipeline of small steps.

Each step takes a frame's objects (camera optical frame, metres) and its
:class:`PostContext` and returns the objects it keeps; :func:`build_pipeline` orders
them from a :class:`~shape_detector.detector_config.DetectorConfig`. A ``hook`` passed to
:meth:`Pipeline.run` sees the objects before each step and after the last, which is how
tuning and diagnostics capture intermediate results.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..frustum import pixel_points
from ..types import Object3D
from .floor import snap_to_floor
from .free_space import carve_all
from .nms import nms_3d
from .point_fit import grow_all_to_points
from .primitive_snap import snap_primitives

#: hook(step name or "output", objects) called before each step and once at the end
Hook = Callable[[str, list[Object3D]], None]


@dataclass
class PostContext:
    """What the steps may read about a frame: ``depth`` HxW metres (NaN invalid), ``K``
    (3,3), gravity ``up`` (3,) and the camera's ``floor_height`` above the floor (m, None:
    not measured), all camera frame; ``given_boxes``: the 2D boxes came from the caller."""

    depth: np.ndarray
    K: np.ndarray
    up: np.ndarray
    floor_height: float | None
    given_boxes: bool

    @functools.cached_property
    def points(self) -> Callable[[np.ndarray], np.ndarray]:
        """Flat pixel indices -> (N, 3) camera-frame points of the depth map."""
        return functools.partial(pixel_points, self.depth, self.K)


class Step(Protocol):
    """One post-processing step."""

    @property
    def name(self) -> str:
        """The step's name, as hooks see it."""
        ...

    def __call__(self, objects: list[Object3D], ctx: PostContext) -> list[Object3D]:
        """The objects after this step (new or updated objects; inputs may be reused)."""
        ...


@dataclass(frozen=True)
class PointFit:
    """Grow each box to its surely segmented points (see :mod:`.point_fit`)."""

    quantile: float
    min_prob: float
    name: str = "point_fit"

    def __call__(self, objects: list[Object3D], ctx: PostContext) -> list[Object3D]:
        """Boxes grown to their points (camera frame, metres)."""
        return grow_all_to_points(objects, ctx.points, self.quantile, self.min_prob)


@dataclass(frozen=True)
class FloorSnap:
    """Put boxes whose bottom lies within ``margin`` m of the measured floor on it."""

    margin: float
    name: str = "floor_snap"

    def __call__(self, objects: list[Object3D], ctx: PostContext) -> list[Object3D]:
        """Boxes with their bottom moved onto the floor where it lies within ``margin`` m."""
        return snap_to_floor(objects, ctx.up, ctx.floor_height, self.margin)


@dataclass(frozen=True)
class FreeSpaceCarve:
    """Shrink boxes out of seen-through space (after the floor snap: points near a box's
    bottom are floor by then)."""

    min_prob: float
    name: str = "free_space"

    def __call__(self, objects: list[Object3D], ctx: PostContext) -> list[Object3D]:
        """Boxes shrunk out of the space the depth image sees through."""
        return carve_all(objects, ctx.depth, ctx.K, ctx.points, min_prob=self.min_prob)


@dataclass(frozen=True)
class Nms3D:
    """3D (Soft-)NMS over built-in proposals' objects; given boxes are one per object."""

    iou: float
    decay: float
    min_score: float
    name: str = "nms"

    def __call__(self, objects: list[Object3D], ctx: PostContext) -> list[Object3D]:
        """The NMS survivors (rescored), or ``objects`` unchanged when the boxes were given."""
        if ctx.given_boxes:
            return objects
        return nms_3d(objects, self.iou, decay=self.decay, min_score=self.min_score)


@dataclass(frozen=True)
class PrimitiveSnap:
    """Turn nearly box-aligned primitives to the box axes and clip them to the box."""

    name: str = "primitive_snap"

    def __call__(self, objects: list[Object3D], ctx: PostContext) -> list[Object3D]:
        """Objects with their nearly aligned primitives snapped to the box."""
        return snap_primitives(objects)


@dataclass(frozen=True)
class Pipeline:
    """Steps run in order; the result is sorted by score, best first."""

    steps: tuple[Step, ...]

    @property
    def names(self) -> list[str]:
        """The steps' names in order."""
        return [s.name for s in self.steps]

    def run(self, objects: list[Object3D], ctx: PostContext, hook: Hook | None = None) -> list[Object3D]:
        """Apply every step; ``hook`` sees the objects before each step and the output."""
        for step in self.steps:
            if hook is not None:
                hook(step.name, list(objects))
            objects = step(objects, ctx)
        objects = sorted(objects, key=lambda o: -o.score)
        if hook is not None:
            hook("output", list(objects))
        return objects


def build_pipeline(config: Any) -> Pipeline:
    """The steps a :class:`~shape_detector.detector_config.DetectorConfig` asks for, in
    their one valid order: point fit, floor snap, free-space carving, NMS, primitive snap."""
    steps: list[Step] = []
    if config.point_fit > 0.0:
        steps.append(PointFit(config.point_fit, config.fit_confidence))
    if config.floor_snap > 0.0:
        steps.append(FloorSnap(config.floor_snap))
    if config.free_space:
        steps.append(FreeSpaceCarve(config.fit_confidence))
    steps.append(Nms3D(config.nms_iou, config.nms_decay, config.score_threshold))
    if config.snap_primitives:
        steps.append(PrimitiveSnap())
    return Pipeline(tuple(steps))
