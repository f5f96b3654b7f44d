"""shape_detector: RGB-D furniture detection with amodal 3D boxes and cuboid primitives.

``from shape_detector import ShapeDetector`` is the public entry point (torch is imported
only when it is first used).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .classes import CLASSES
from .types import Cuboid, Frame, GTObject, Object3D

__all__ = ["CLASSES", "Cuboid", "Frame", "GTObject", "Object3D", "ShapeDetector"]
__version__ = "0.1.0"

if TYPE_CHECKING:
    from .detector import ShapeDetector


def __getattr__(name: str) -> Any:
    if name == "ShapeDetector":
        from .detector import ShapeDetector

        return ShapeDetector
    raise AttributeError(name)
