"""``shape-detector export SCENE.json -o scene.glb``: the scene map for game engines.

Formats by suffix: ``.glb`` (binary glTF), ``.gltf`` (one JSON file, buffers embedded),
``.obj`` (plus ``.mtl``). Node layout and frames: :mod:`shape_detector.export.scene_export`.
"""

from __future__ import annotations

import argparse
import sys


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``shape-detector export``."""
    p.add_argument("scene", help="scene JSON written by --scene-out (SceneMap.save_json)")
    p.add_argument("-o", "--out", required=True, help="output file: .glb, .gltf or .obj")
    p.add_argument("--no-colliders", action="store_true", help="leave out the collider nodes")
    p.add_argument("--picture", default=None, help="also write a PNG here: a 3D view of the exported file "
                   "(.glb / .gltf) over a top + side view of the scene")


def main(args: argparse.Namespace) -> int:
    """Export; 0 on success, 2 on bad input (message on stderr)."""
    from ..ar.scene_data import load_scene
    from .scene_export import export_scene, scene_summary

    try:
        scene = load_scene(args.scene)
        files = export_scene(scene, args.out, colliders=not args.no_colliders)
    except ValueError as e:
        print(f"shape-detector export: {e}", file=sys.stderr)
        return 2
    print(f"wrote {', '.join(str(f) for f in files)} ({scene_summary(scene)})")
    if args.picture:
        import trimesh

        from .picture import write_picture

        exported = trimesh.load(files[0]) if files[0].suffix.lower() in (".glb", ".gltf") else None
        print(f"wrote {write_picture(scene, args.picture, exported=exported)}")
    return 0
