"""``shape-detector demo BAG --out DIR``: the main job on a bag, end to end.

Runs the detector (built-in proposals and gravity estimation, packaged weights) over every
synchronised frame of ``BAG`` and writes ``DIR/detections.mcap`` (input topics plus
``/shape_detector/markers`` and the Detection3DArray, openable in Foxglove / RViz),
``DIR/overlay.png`` (a few frames: colour with projected boxes and primitives | depth)
and ``DIR/summary.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", type=Path, help="input bag (rosbag2 directory / .mcap / .db3, or ROS 1 .bag)")
    p.add_argument("--out", type=Path, default=Path("out"), help="output directory")
    p.add_argument("--weights", default=None, help="weights file (default: packaged)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--score-threshold", type=float, default=0.3)
    p.add_argument("--overlay-frames", type=int, default=4, help="frames shown in overlay.png")


def main(args: argparse.Namespace) -> int:
    from .detector import ShapeDetector
    from .replay import replay_bag
    from .visualize import colorize_depth, draw_objects, save_png, tile

    if not args.bag.exists():
        print(f"demo: no bag at {args.bag}")
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    detector = ShapeDetector(weights=args.weights, device=args.device, score_threshold=args.score_threshold)
    panels: list[tuple[int, np.ndarray, np.ndarray]] = []

    def keep_overlay(frame, prepared, objects) -> None:
        if prepared is None:
            return
        # keep every frame's panel cheaply, thin out at the end
        panels.append(
            (frame.index, draw_objects(prepared.rgb, prepared.K, objects), colorize_depth(prepared.depth))
        )

    out_bag = args.out / "detections.mcap"
    summary = replay_bag(args.bag, out_bag, detector, progress=True, overwrite=True, on_frame=keep_overlay)
    print(summary.format())
    if panels:
        pick = np.linspace(0, len(panels) - 1, min(args.overlay_frames, len(panels))).round().astype(int)
        cells = []
        for i in sorted(set(pick.tolist())):
            cells += [panels[i][1], panels[i][2]]
        save_png(args.out / "overlay.png", tile(cells, 2))
        print(f"overlay: {args.out / 'overlay.png'}")
    (args.out / "summary.json").write_text(json.dumps(summary.as_dict(), indent=2, default=str))
    print(f"output bag: {out_bag}")
    return 0 if summary.ok else 1
