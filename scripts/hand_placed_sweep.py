"""How far off is a hand-placed box, over many poses? (issue #4's 5 cm check, measured widely)

The unit test places one 0.53 x 1.00 x 1.17 m dresser by hand; this script places the same box
at 9 yaws x 2 lateral offsets x 3 distances (54 poses) in toy ray-cast frames (camera 1.3 m
high, pitched 12 degrees down), with and without a back wall, gives the detector the visible 2D
box with its class and the true `up`, and prints the centre error statistics (metres).

    python scripts/hand_placed_sweep.py [--weights PATH]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

from shape_detector import ShapeDetector

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))  # the ray-cast toy scenes live with the tests
from toy_scenes import placed_box_scene  # noqa: E402

SIZE = (0.53, 1.00, 1.17)  # l, w, h (m)


def centre_error(det: ShapeDetector, yaw: float, x: float, y: float, walls: tuple) -> float:
    """Centre error (m) of the dresser placed at world (x, y) on the floor with ``yaw`` (rad)."""
    frame, c_cam, _ = placed_box_scene("dresser", SIZE, x, y, yaw, walls=walls)
    objs = det.detect(frame.rgb, frame.depth, frame.K, boxes2d=[(*frame.objects[0].box2d, "dresser")], up=frame.up)
    return float(np.linalg.norm(objs[0].center - c_cam)) if objs else float("inf")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None, help="network weights (default: the packaged ones)")
    args = ap.parse_args()
    det = ShapeDetector(weights=args.weights, score_threshold=0.0)
    poses = list(itertools.product(np.arange(-1.4, 1.45, 0.35), [-0.5, 0.25], [2.2, 2.6, 3.2]))
    for name, walls in (("no walls", ()), ("back wall 3.5 m", ((np.pi / 2, 3.5),)),
                        ("back wall 4.0 m", ((np.pi / 2, 4.0),)), ("back wall 5.0 m", ((np.pi / 2, 5.0),))):
        e = np.array([centre_error(det, yaw, x, y, walls) for yaw, x, y in poses])
        print(f"{name:16s} poses {len(e)}  centre error median {np.median(e):.3f} m  p75 {np.quantile(e, 0.75):.3f}"
              f"  max {e.max():.3f}  within 5 cm {np.mean(e < 0.05):.0%}", flush=True)


if __name__ == "__main__":
    main()
