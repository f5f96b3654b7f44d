"""Scene memory: tracked furniture in a fixed world frame (z up) and a 2D navigation grid.

Pure numpy (no rclpy). :class:`SceneMap` is fed the detector's per-frame objects (camera
optical frame), the camera pose in the world frame, and the frame's depth and intrinsics.
"""

from .grid import NavGrid
from .map import SceneConfig, SceneMap
from .types import SceneObject, ScenePrimitive

__all__ = ["NavGrid", "SceneConfig", "SceneMap", "SceneObject", "ScenePrimitive"]
