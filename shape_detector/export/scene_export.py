"""The scene map as a glTF / OBJ scene: one node per object, one box mesh per primitive.

Node layout (glTF): under the scene root, per object a node ``"<class> #<id>"`` placed at
the object's box pose, with one child ``"<class> #<id> part <k>"`` per primitive (a box mesh
of the primitive's size at its pose relative to the object), and a sibling node
``"<class> #<id> collider"`` with children ``"... collider <k>"``: the same boxes again, with
glTF ``extras`` ``{"collider": "box", "size": [x, y, z]}`` so an importer script (Unity,
Unreal, Godot, Blender) can turn them into box colliders and hide them; object nodes carry
``{"class", "id", "score"}``. One PBR material per
class (the class colour). The map's world frame (z up, metres) becomes glTF's y-up frame
(x stays, y = world z, z = -world y). OBJ has no hierarchy or '#' in names: it gets one
group per box named ``<class>_<id>_part_<k>`` / ``<class>_<id>_collider_<k>`` (y-up too)
and a material library next to it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from trimesh.visual.material import PBRMaterial

from ..ar.scene_data import ArScene, load_scene
from ..scene.types import SceneObject, object_parts
from ..classes import class_color

#: world (z up) -> glTF (y up): x -> x, y -> -z, z -> y.
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])

FORMATS = (".glb", ".gltf", ".obj")
_MIN_SIZE = 1e-3  # m; engines reject zero-thickness colliders


def _rotation(R: np.ndarray) -> np.ndarray:
    """The proper rotation nearest to ``R`` (boxes from a tracker may drift off orthonormal)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        U[:, -1] *= -1
        Rn = U @ Vt
    return Rn


def _pose(center: np.ndarray, R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rotation(R)
    T[:3, 3] = center
    return T


def _material(class_name: str) -> PBRMaterial:
    r, g, b = class_color(class_name)
    return PBRMaterial(name=class_name, baseColorFactor=[int(255 * r), int(255 * g), int(255 * b), 255],
                       metallicFactor=0.0, roughnessFactor=0.8)


def object_name(o: SceneObject) -> str:
    """The node name of an object: ``"<class> #<id>"``."""
    return f"{o.class_name} #{o.id}"


def build_trimesh_scene(source: Any, colliders: bool = True, y_up: bool = True) -> trimesh.Scene:
    """A trimesh scene of the map (node layout in the module doc); ``y_up``: convert the
    world's z up to glTF's y up (else keep world coordinates)."""
    scene = load_scene(source)
    out = trimesh.Scene()
    base = out.graph.base_frame
    C = Z_UP_TO_Y_UP if y_up else np.eye(4)
    materials: dict[str, PBRMaterial] = {}
    for o in scene.objects:
        mat = materials.setdefault(o.class_name, _material(o.class_name))
        name = object_name(o)
        T_obj = C @ _pose(o.center, o.rotation)
        inv = np.linalg.inv(T_obj)
        groups = [(name, "part", mat)] + ([(f"{name} collider", "collider", None)] if colliders else [])
        for node, kind, m in groups:
            out.graph.update(frame_to=node, frame_from=base, matrix=T_obj)
            for k, p in enumerate(object_parts(o)):
                box = trimesh.creation.box(extents=np.maximum(np.abs(p.size), _MIN_SIZE))
                if m is not None:
                    box.visual = trimesh.visual.TextureVisuals(material=m)
                child = f"{name} {kind} {k}" if kind == "part" else f"{node} {k}"
                out.add_geometry(box, node_name=child, geom_name=child, parent_node_name=node,
                                 transform=inv @ C @ _pose(p.center, p.rotation))
    return out


def _extras(objects: dict[str, SceneObject]) -> Any:
    """A glTF tree post-processor adding ``extras``: ``{"class", "id", "score"}`` (and
    ``"class_probs"`` where known) on object nodes and ``{"collider": "box", "size": [x, y, z]}``
    (full size, metres) on collider boxes."""

    def post(tree: dict) -> None:
        meshes = tree.get("meshes", [])
        accessors = tree.get("accessors", [])
        for node in tree.get("nodes", []):
            name = node.get("name", "")
            if name in objects:
                o = objects[name]
                node["extras"] = {"class": o.class_name, "id": int(o.id), "score": round(float(o.score), 4)}
                if o.class_probs:
                    node["extras"]["class_probs"] = {k: round(float(v), 3) for k, v in o.class_probs.items()}
            if " collider " not in name or "mesh" not in node:
                continue
            extras: dict[str, Any] = {"collider": "box"}
            acc = accessors[meshes[node["mesh"]]["primitives"][0]["attributes"]["POSITION"]]
            if "min" in acc and "max" in acc:
                extras["size"] = [float(b - a) for a, b in zip(acc["min"], acc["max"])]
            node["extras"] = extras

    return post


def _obj_text(ts: trimesh.Scene, mtl_name: str) -> tuple[str, dict[str, bytes]]:
    flat = trimesh.Scene()
    for node in ts.graph.nodes_geometry:
        T, geom = ts.graph[node]
        mesh = ts.geometry[geom].copy()
        mesh.apply_transform(T)
        flat.add_geometry(mesh, geom_name=node.replace(" #", "_").replace(" ", "_"))
    text, files = trimesh.exchange.obj.export_obj(flat, include_normals=False, return_texture=True,
                                                  mtl_name=mtl_name)
    return text, files


def export_scene(source: Any, path: str | Path, colliders: bool = True) -> list[Path]:
    """Write the map to ``path`` (.glb, .gltf with embedded buffers, or .obj plus its .mtl);
    returns the files written. Raises ``ValueError`` for other suffixes or bad scenes."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"unsupported export format {suffix!r}; use one of {FORMATS}")
    scene = load_scene(source)
    ts = build_trimesh_scene(scene, colliders=colliders)
    post = _extras({object_name(o): o for o in scene.objects})
    path.parent.mkdir(parents=True, exist_ok=True)
    if not ts.geometry:
        raise ValueError("the scene has no objects to export")
    if suffix == ".glb":
        path.write_bytes(trimesh.exchange.gltf.export_glb(ts, tree_postprocessor=post))
        return [path]
    if suffix == ".gltf":
        files = trimesh.exchange.gltf.export_gltf(ts, tree_postprocessor=post, embed_buffers=True)
        tree = json.loads(files["model.gltf"])
        path.write_text(json.dumps(tree))
        return [path]
    mtl = path.with_suffix(".mtl")
    text, files = _obj_text(ts, mtl.name)
    path.write_text(text)
    written = [path]
    for name, data in files.items():
        target = path.parent / name
        target.write_bytes(data if isinstance(data, bytes) else str(data).encode())
        written.append(target)
    return written


def scene_summary(scene: ArScene) -> str:
    """One line: objects, boxes, classes."""
    classes = sorted({o.class_name for o in scene.objects})
    return f"{len(scene.objects)} objects, {len(scene.boxes)} boxes, classes: {', '.join(classes) or '-'}"
