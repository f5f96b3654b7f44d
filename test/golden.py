"""Golden detections: the accurate preset's output on the sample bag and 50 validation frames.

Recorded before a refactor and after new weights (``python test/golden.py --write``), compared after it by
``test_golden.py`` within tolerance: a move of code must not move a box.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
GOLDEN = Path(__file__).resolve().parent / "data" / "golden_detections.json"
SAMPLE_BAG = ROOT / "bags" / "sample"
VAL_SEED = 2  # the validation split's data seed (Makefile: data/val)
NUM_VAL = 50


def _objects(objs: list[Any]) -> list[dict[str, Any]]:
    return [
        {
            "class": o.class_name,
            "score": round(float(o.score), 6),
            "center": [round(float(v), 6) for v in o.center],
            "size": [round(float(v), 6) for v in o.size],
            "num_primitives": len(o.primitives),
        }
        for o in objs
    ]


def frames() -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, rgb, depth, K) of every golden frame: sample bag first, then validation frames."""
    from shape_detector.bags.reader import iter_frames
    from shape_detector.synth.dataset import frame_seed
    from shape_detector.synth.generate import generate_frame

    out = []
    for sf in iter_frames(SAMPLE_BAG):
        p = sf.prepare()
        out.append((f"bag/{sf.index}", p.rgb, p.depth, p.K))
    for i in range(NUM_VAL):
        f = generate_frame(frame_seed(VAL_SEED, i))
        out.append((f"val/{i}", f.rgb, f.depth, f.K))
    return out


def detect_all(detector: Any = None) -> dict[str, list[dict[str, Any]]]:
    """Detections of ``ShapeDetector(preset="accurate")`` (or ``detector``) on every golden frame."""
    from shape_detector import ShapeDetector

    det = detector or ShapeDetector(preset="accurate")
    return {name: _objects(det.detect(rgb, depth, K)) for name, rgb, depth, K in frames()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--write", action="store_true", help="record the golden file (else print a summary)")
    args = ap.parse_args()
    result = detect_all()
    n = sum(len(v) for v in result.values())
    if args.write:
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        GOLDEN.write_text(json.dumps(result, indent=0, sort_keys=True))
        print(f"wrote {GOLDEN}: {len(result)} frames, {n} objects")
    else:
        print(f"{len(result)} frames, {n} objects")


if __name__ == "__main__":
    main()
