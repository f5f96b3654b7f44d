"""Run the shipped detector on real SUN RGB-D frames (VoteNet's layout) and print what it gets.

The gap between our generated scenes and a real Kinect frame, in the metrics the README uses:
3D IoU / centre error of each labelled object of our ten classes (1) with its GT 2D box and
class given, (2) with its GT 2D box but no class, (3) with the built-in proposals and the
estimated ``up`` (every detection's best 3D IoU with a labelled object); and the ``up`` error
against the frame's Rtilt. Usage::

    python scripts/real_frame.py ../shared/data/sunrgbd_sample [--index 1]
"""

from __future__ import annotations

import argparse

import numpy as np

from shape_detector import ShapeDetector
from shape_detector.datasets.sunrgbd import load_frame
from shape_detector.detector_config import PRESETS
from shape_detector.proposal_source import names as source_names
from shape_detector.box_iou import box3d_iou


def _iou(o, g) -> float:
    return box3d_iou(o.center, o.size, o.rotation, g.center, g.size, g.rotation)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", help="directory with depth/ image/ calib/ label/")
    p.add_argument("--index", type=int, default=1, help="frame index (default 1)")
    p.add_argument("--weights", default=None)
    p.add_argument("--preset", choices=sorted(PRESETS), default="realtime")
    p.add_argument("--proposal-source", choices=[n for n in source_names() if n != "external"], default=None,
                   help="built-in proposals (default: the preset's)")
    a = p.parse_args()
    fr = load_frame(a.root, a.index)
    extra = {"proposal_source": a.proposal_source} if a.proposal_source else {}
    det = ShapeDetector(preset=a.preset, weights=a.weights, score_threshold=0.0, **extra)
    valid = np.isfinite(fr.depth) & (fr.depth > 0)
    print(f"frame {a.index}: {fr.rgb.shape[1]}x{fr.rgb.shape[0]}, valid depth {valid.mean():.0%}, "
          f"median depth {np.median(fr.depth[valid]):.2f} m, {len(fr.objects)} objects of our classes")
    for mode in ("class given", "class-agnostic"):
        print(f"GT 2D boxes, {mode}, GT up:")
        for g in fr.objects:
            box = (*g.box2d, g.class_name if mode == "class given" else None)
            out = det.detect(fr.rgb, fr.depth, fr.K, boxes2d=[box], up=fr.up)
            if not out:
                print(f"  {g.class_name:12s} no valid depth in its box")
                continue
            o = out[0]
            print(f"  {g.class_name:12s} -> {o.class_name:12s} score {o.score:.2f}  3D IoU {_iou(o, g):.3f}  "
                  f"centre error {np.linalg.norm(o.center - g.center):.2f} m  size {np.round(o.size, 2)} "
                  f"(GT {np.round(g.size, 2)})")
    out = det.detect(fr.rgb, fr.depth, fr.K)
    err = np.degrees(np.arccos(np.clip(float(det.last_up @ fr.up), -1.0, 1.0)))
    print(f"built-in proposals, estimated up (error {err:.2f} deg, confidence {det.last_up_confidence:.2f}), "
          f"{len(out)} detections, best first:")
    for o in out[:8]:
        ious = [_iou(o, g) for g in fr.objects]
        k = int(np.argmax(ious)) if ious else -1
        near = f"best 3D IoU {ious[k]:.3f} with the {fr.objects[k].class_name}" if ious else "no labelled object"
        print(f"  {o.class_name:12s} score {o.score:.2f}  {near}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
