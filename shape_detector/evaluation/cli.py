"""``shape-detector evaluate``: weights -> AP / box errors / shape metrics report.

Frames come from a synthetic shard directory (``--data``, read with
``shape_detector.synth.dataset.iter_frames``) or, without ``--data``, are generated on the
fly with ``shape_detector.synth.generate.generate_frame(seed + i)``. By default the
detector gets the GT 2D boxes (the thesis' evaluation of the 3D stage alone);
``--no-gt-boxes`` lets it find its own. Writes report.md / report.json / PNGs to ``--out``.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..model.config import PRECISIONS


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--weights", default=None, help="network weights (.pt); default: the packaged ones")
    p.add_argument("--data", default=None, help="synthetic shard directory; omitted -> generate frames on the fly")
    p.add_argument("--frames", type=int, default=100, help="number of frames to evaluate (default 100)")
    p.add_argument("--out", default="eval_out", help="output directory for the report (default eval_out)")
    p.add_argument("--no-gt-boxes", action="store_true", help="use the detector's own 2D proposals")
    p.add_argument("--seed", type=int, default=0, help="first generator seed (on-the-fly frames) and sampling seed")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--min-visible", type=float, default=0.0,
                   help="GT with a smaller visible fraction is ignored (default 0)")
    p.add_argument("--surface-samples", type=int, default=5000,
                   help="surface samples per shape set (default 5000, as issue #4 specifies)")
    p.add_argument("--score-threshold", type=float, default=0.0,
                   help="detector score threshold (default 0: keep everything, AP needs the full ranking)")
    p.add_argument("--floor-snap", type=float, default=0.25,
                   help="put box bottoms within this many metres of the measured floor on it (0 = off; default 0.25)")
    p.add_argument("--point-fit", type=float, default=0.15,
                   help="grow boxes to cover their segmented points between this quantile and its complement "
                   "(0 = off; default 0.15)")
    p.add_argument("--fit-confidence", type=float, default=0.8,
                   help="point fit and free-space carving use the points segmented with a foreground "
                   "probability above this (default 0.8)")
    p.add_argument("--no-free-space", action="store_true",
                   help="leave boxes where the camera sees through them (no free-space carving)")
    p.add_argument("--mirror-tta", default="given", choices=("given", "always", "never"),
                   help="mirrored second pass, averaged: for given boxes (default), always, or never")
    p.add_argument("--no-snap-primitives", action="store_true",
                   help="leave primitives as predicted instead of box-aligned and clipped to their box")
    p.add_argument("--nms-decay", type=float, default=0.1,
                   help="built-in proposals: keep boxes 3D NMS suppresses at this fraction of their score "
                   "(Soft-NMS; 0 = drop them; default 0.1)")
    p.add_argument("--max-objects", type=int, default=25,
                   help="built-in proposals per frame, best first (default 25, as ShapeDetector)")
    p.add_argument("--classifier", default=None, metavar="PATH|none",
                   help="proposal classifier for built-in proposals (default: the packaged one; none = off)")
    p.add_argument("--no-refine", action="store_true",
                   help="built-in proposals: no class-given second pass")
    p.add_argument("--refine-min-score", type=float, default=0.3,
                   help="score (after the proposal classifier) a built-in proposal needs for the second pass "
                        "(default 0.3, as ShapeDetector)")
    p.add_argument("--class-hypotheses", type=int, default=1,
                   help="also report AP with each detection counted for its top-K classes (VoteNet's "
                   "per-class proposals; detected boxes only; default 1 = off)")
    p.add_argument("--estimate-up", action="store_true",
                   help="let the detector estimate gravity instead of passing the frame's GT up vector")
    p.add_argument("--precision", default="fp32", choices=PRECISIONS,
                   help="network arithmetic (bf16: bfloat16 autocast, faster on CPUs with AMX / AVX512-BF16; auto: bf16 "
                        "for 4 or more frustums where the CPU has AMX)")
    p.add_argument("--title", default=None, help="report title")
    p.add_argument("--quiet", action="store_true", help="no per-frame progress")


def _classifier(text: str | None) -> str | bool:
    """``--classifier`` as ``ShapeDetector(classifier=...)`` (not given: the packaged one)."""
    from ..detector import classifier_option

    spec = classifier_option(text)
    return True if spec is None else spec


def _frames(args: argparse.Namespace) -> Iterator[Any]:
    if args.data:
        from ..synth.dataset import iter_frames

        return itertools.islice(iter_frames(args.data), max(args.frames, 0))
    from ..synth.generate import generate_frame

    return (generate_frame(args.seed + i) for i in range(max(args.frames, 0)))


def main(args: argparse.Namespace) -> int:
    if args.data and not Path(args.data).exists():
        print(f"shape-detector evaluate: no data directory {args.data!r}", file=sys.stderr)
        return 2
    from .. import ShapeDetector
    from .report import write_report
    from .runner import evaluate

    try:
        detector = ShapeDetector(weights=args.weights, device=args.device, score_threshold=args.score_threshold,
                                 floor_snap=args.floor_snap, point_fit=args.point_fit,
                                 fit_confidence=args.fit_confidence,
                                 free_space=not args.no_free_space,
                                 mirror_tta=args.mirror_tta, snap_primitives=not args.no_snap_primitives,
                                 nms_decay=args.nms_decay, precision=args.precision,
                                 classifier=_classifier(args.classifier),
                                 refine=not args.no_refine, refine_min_score=args.refine_min_score,
                                 max_objects=args.max_objects)
    except FileNotFoundError as e:
        print(f"shape-detector evaluate: {e}", file=sys.stderr)
        return 2

    def detect_fn(frame, boxes2d):
        up = None if args.estimate_up else frame.up
        return detector.detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes2d, up=up)

    def progress(i: int, dt: float) -> None:
        if not args.quiet and (i + 1) % 10 == 0:
            print(f"  frame {i + 1}: {dt * 1000:.0f} ms", file=sys.stderr)

    use_gt = not args.no_gt_boxes
    if use_gt and args.class_hypotheses > 1:
        print("shape-detector evaluate: --class-hypotheses applies to detected boxes (--no-gt-boxes) only; "
              "with GT boxes the class is given", file=sys.stderr)
    results = evaluate(
        detect_fn,
        _frames(args),
        use_gt_boxes=use_gt,
        min_visible=args.min_visible,
        surface_samples=args.surface_samples,
        seed=args.seed,
        progress=progress,
        class_hypotheses=args.class_hypotheses,
    )
    results["settings"].update(
        {
            "weights": str(getattr(detector, "weights", args.weights)),
            "data": str(args.data or f"generated on the fly, seeds {args.seed}..{args.seed + args.frames - 1}"),
            "score_threshold": args.score_threshold,
            "floor_snap_m": args.floor_snap,
            "point_fit_quantile": args.point_fit,
            "fit_confidence": args.fit_confidence,
            "free_space": not args.no_free_space,
            "snap_primitives": not args.no_snap_primitives,
            "mirror_tta": args.mirror_tta,
            "nms_decay": args.nms_decay,
            "max_objects": args.max_objects,
            "classifier": (args.classifier or "packaged") if getattr(detector, "classifier", None) is not None else "off",
            "refine": "off" if args.no_refine else f"score >= {args.refine_min_score:g}",
            "precision": args.precision,
            "up": "estimated" if args.estimate_up else "ground truth",
        }
    )
    title = args.title or f"shape_detector evaluation ({'GT 2D boxes' if use_gt else 'detected 2D boxes'})"
    paths = write_report(results, args.out, title)
    det = results["detection"]
    maps = ", ".join(f"mAP@{k} {v:.3f}" if v is not None else f"mAP@{k} -" for k, v in det["mAP"].items())
    print(f"{results['num_frames']} frames: {maps}")
    if "detection_class_hypotheses" in results:
        hyp = results["detection_class_hypotheses"]
        maps = ", ".join(f"mAP@{k} {v:.3f}" if v is not None else f"mAP@{k} -" for k, v in hyp["mAP"].items())
        print(f"  counting each box for its top {hyp['k']} classes: {maps}")
    print(f"report: {paths['markdown']}")
    return 0
