"""Tune the built-in-proposal post-processing on the *validation* shards (never the test set).

Runs the detector once per frame with the proposal cap at its largest, captures the
detections that reach the NMS step (a post-processing hook, in proposal-rank order), then scores every combination of
proposal cap x NMS IoU x containment threshold (with the detector's Soft-NMS decay) with the
AP code. Prints one line per setting, best last. Usage::

    python scripts/tune_builtin.py --data data/val --frames 100 [--weights W]
"""

from __future__ import annotations

import argparse
import itertools
import json

from shape_detector import ShapeDetector
from shape_detector.classes import CLASSES
from shape_detector.evaluation.ap import evaluate_detections
from shape_detector.postprocess.nms import nms_3d
from shape_detector.synth.dataset import iter_frames


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="data/val")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--min-visible", type=float, default=0.1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()

    captured: list = []

    def before_nms(step: str, objects: list) -> None:
        if step == "nms":
            captured.append(objects)

    det = ShapeDetector(preset="accurate", weights=a.weights, score_threshold=0.0, max_objects=30)
    raw, gts, ups = [], [], []
    for i, fr in enumerate(iter_frames(a.data)):
        if i >= a.frames:
            break
        captured.clear()
        det.finish(det.prepare(fr.rgb, fr.depth, fr.K), hook=before_nms)
        raw.append(captured[0] if captured else [])
        gts.append(list(fr.objects))
        ups.append(fr.up)
    rows = []
    for cap, iou, cont in itertools.product((12, 16, 20, 30), (0.1, 0.25, 0.4), (0.5, 0.7, 0.9)):
        dets = [nms_3d(r[:cap], iou, cont, decay=det.nms_decay) for r in raw]  # as the detector (Soft-NMS)
        res = evaluate_detections(dets, gts, (0.25, 0.5), CLASSES, min_visible=a.min_visible, ups_per_frame=ups)
        row = {"cap": cap, "nms_iou": iou, "containment": cont,
               "mAP25": float(res["mAP"]["0.25"]), "mAP50": float(res["mAP"]["0.5"])}
        rows.append(row)
        print(json.dumps(row), flush=True)
    best = max(rows, key=lambda r: r["mAP25"])
    print("best:", json.dumps(best))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
