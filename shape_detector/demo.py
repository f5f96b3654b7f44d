"""``shape-detector demo BAG --out DIR``: the main job on a bag, end to end.

Runs the detector (realtime preset, packaged weights) over every synchronised frame of ``BAG``
and builds the scene map (camera poses from the bag's ``/tf``; a static camera without them).
Writes ``DIR/detections.mcap`` (input topics plus ``/shape_detector/markers``, the
Detection3DArray, ``/shape_detector/scene`` and ``/shape_detector/map``; openable in Foxglove /
RViz), ``DIR/scene.json`` (the final map), ``DIR/scene.png`` (the last frame with its boxes
beside the map: top view of the grid with the tracked boxes, their ids and the camera path),
``DIR/overlay.png`` (a few frames: colour with boxes and primitives | depth) and
``DIR/summary.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Flags of ``shape-detector demo``."""
    p.add_argument("bag", type=Path, help="input bag (rosbag2 directory / .mcap / .db3, or ROS 1 .bag)")
    p.add_argument("--out", type=Path, default=Path("out"), help="output directory")
    p.add_argument("--weights", default=None, help="weights file (default: packaged)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--score-threshold", type=float, default=0.3)
    p.add_argument("--overlay-frames", type=int, default=4, help="frames shown in overlay.png")
    p.add_argument("--world-frame", default="odom", help="fixed frame of the scene map (default odom)")
    p.add_argument("--no-scene", action="store_true", help="detections only, no scene map")


def _camera_path(bag: Path, world_frame: str, frames: list[tuple[int, str]]) -> np.ndarray | None:
    """World x, y of the camera at each frame (None without poses)."""
    from .bags.scene_record import SceneOptions, load_poses
    from .poses import TransformLookupError

    poses, _ = load_poses(bag, SceneOptions(world_frame=world_frame))
    if poses is None:
        return None
    xy = []
    for stamp, frame_id in frames:
        try:
            xy.append(poses.T_world_camera(frame_id, stamp)[:2, 3])
        except TransformLookupError:
            continue
    return np.array(xy) if xy else None


def _scene_picture(args: argparse.Namespace, last: np.ndarray, frames: list[tuple[int, str]]) -> Path:
    """``scene.png``: the last frame beside the top view of the final map."""
    from .map_view import draw_map, side_by_side
    from .scene import SceneMap
    from .visualize import save_png

    scene = SceneMap.from_json(args.out / "scene.json")
    top = draw_map(scene.grid(), scene.objects(), height_px=max(480, last.shape[0]),
                   path_xy=_camera_path(args.bag, args.world_frame, frames))
    path = args.out / "scene.png"
    save_png(path, side_by_side(last, top))
    return path


def main(args: argparse.Namespace) -> int:
    """Run the demo; exit status 0 (done), 1 (damaged input), 2 (no bag)."""
    from .bags.detector_factory import make_detector
    from .bags.scene_record import SceneOptions
    from .detector_config import preset
    from .replay import replay_bag
    from .visualize import colorize_depth, draw_objects, save_png, tile

    if not args.bag.exists():
        print(f"demo: no bag at {args.bag}")
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    detector = make_detector(preset("realtime", weights=args.weights or "", device=args.device,
                                    score_threshold=args.score_threshold))
    panels: list[tuple[int, np.ndarray, np.ndarray]] = []
    frames: list[tuple[int, str]] = []

    def keep_overlay(frame: Any, prepared: Any, objects: list) -> None:
        frames.append((int(frame.stamp_ns), str(frame.frame_id)))
        if prepared is None:
            return
        # keep every frame's panel cheaply, thin out at the end
        panels.append((frame.index, draw_objects(prepared.rgb, prepared.K, objects), colorize_depth(prepared.depth)))

    scene = None if args.no_scene else SceneOptions(world_frame=args.world_frame, scene_out=args.out / "scene.json")
    out_bag = args.out / "detections.mcap"
    summary = replay_bag(args.bag, out_bag, detector, progress=True, overwrite=True, on_frame=keep_overlay,
                         scene=scene)
    print(summary.format())
    if panels:
        pick = np.linspace(0, len(panels) - 1, min(args.overlay_frames, len(panels))).round().astype(int)
        cells = []
        for i in sorted(set(pick.tolist())):
            cells += [panels[i][1], panels[i][2]]
        save_png(args.out / "overlay.png", tile(cells, 2))
        print(f"overlay: {args.out / 'overlay.png'}")
        if scene is not None and (args.out / "scene.json").exists():
            print(f"scene: {_scene_picture(args, panels[-1][1], frames)}")
    (args.out / "summary.json").write_text(json.dumps(summary.as_dict(), indent=2, default=str))
    print(f"output bag: {out_bag}")
    return 0 if summary.ok else 1
