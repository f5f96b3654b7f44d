"""Scene map export for game engines and DCC tools: glTF 2.0 (.glb / .gltf) and Wavefront OBJ.

Built on trimesh; see :func:`export_scene`.
"""

from .scene_export import Z_UP_TO_Y_UP, build_trimesh_scene, export_scene

__all__ = ["Z_UP_TO_Y_UP", "build_trimesh_scene", "export_scene"]
