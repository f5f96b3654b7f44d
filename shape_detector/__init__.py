"""shape_detector: RGB-D furniture detection with amodal 3D boxes and cuboid primitives.

``from shape_detector import ShapeDetector`` is the per-frame entry point (torch is imported
only when it is first used); ``SceneMap`` fuses its detections over frames into a world-frame
scene with a navigation grid, and ``SceneQueries`` answers what AR code asks of one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .classes import CLASSES
from .types import Cuboid, Frame, GTObject, Object3D

__all__ = ["CLASSES", "Cuboid", "Frame", "GTObject", "Object3D", "SceneMap", "SceneQueries", "ShapeDetector"]
__version__ = "0.1.0"

if TYPE_CHECKING:
    from .ar import SceneQueries
    from .detector import ShapeDetector
    from .scene import SceneMap


def __getattr__(name: str) -> Any:
    if name == "ShapeDetector":
        from .detector import ShapeDetector

        return ShapeDetector
    if name == "SceneMap":
        from .scene import SceneMap

        return SceneMap
    if name == "SceneQueries":
        from .ar import SceneQueries

        return SceneQueries
    raise AttributeError(name)
