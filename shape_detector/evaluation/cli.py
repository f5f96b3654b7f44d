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

from ..config_cli import add_detector_flags, config_from_args


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``shape-detector evaluate``: frame source, report directory and detector flags."""
    p.add_argument("--data", default=None, help="synthetic shard directory; omitted -> generate frames on the fly")
    p.add_argument("--frames", type=int, default=100, help="number of frames to evaluate (default 100)")
    p.add_argument("--out", default="eval_out", help="output directory for the report (default eval_out)")
    p.add_argument("--no-gt-boxes", action="store_true", help="use the detector's own 2D proposals")
    p.add_argument("--no-gt-class", action="store_true",
                   help="give the GT 2D boxes without their class: the detector classifies them (as boxes from "
                        "a class-agnostic 2D detector)")
    p.add_argument("--seed", type=int, default=0, help="first generator seed (on-the-fly frames) and sampling seed")
    p.add_argument("--min-visible", type=float, default=0.0,
                   help="GT with a smaller visible fraction is ignored (default 0)")
    p.add_argument("--surface-samples", type=int, default=5000,
                   help="surface samples per shape set (default 5000, as issue #4 specifies)")
    p.add_argument("--class-hypotheses", type=int, default=1,
                   help="also report AP with each detection counted for its top-K classes (VoteNet's "
                   "per-class proposals; detected boxes only; default 1 = off)")
    p.add_argument("--estimate-up", action="store_true",
                   help="let the detector estimate gravity instead of passing the frame's GT up vector")
    p.add_argument("--title", default=None, help="report title")
    p.add_argument("--quiet", action="store_true", help="no per-frame progress")
    add_detector_flags(p, "accurate")


def _frames(args: argparse.Namespace) -> Iterator[Any]:
    if args.data:
        from ..synth.dataset import iter_frames

        return itertools.islice(iter_frames(args.data), max(args.frames, 0))
    from ..synth.generate import generate_frame

    return (generate_frame(args.seed + i) for i in range(max(args.frames, 0)))


def main(args: argparse.Namespace) -> int:
    """Run the detector over the frames and write the evaluation report to ``args.out`` (exit code 2: no data)."""
    if args.data and not Path(args.data).exists():
        print(f"shape-detector evaluate: no data directory {args.data!r}", file=sys.stderr)
        return 2
    from .. import ShapeDetector
    from .report import write_report
    from .runner import evaluate

    # AP needs the full ranking: keep every detection unless a threshold is asked for
    config = config_from_args(args, **({} if args.score_threshold is not None else {"score_threshold": 0.0}))
    try:
        detector = ShapeDetector(config)
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
    if args.no_gt_class and not use_gt:
        print("shape-detector evaluate: --no-gt-class applies to GT boxes only (not with --no-gt-boxes)", file=sys.stderr)
        return 2
    if use_gt and args.class_hypotheses > 1 and not args.no_gt_class:
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
        gt_class=not args.no_gt_class,
    )
    results["settings"].update(
        {
            "weights": str(getattr(detector, "weights", args.weights)),
            "data": str(args.data or f"generated on the fly, seeds {args.seed}..{args.seed + args.frames - 1}"),
            **{k: v for k, v in config.to_dict().items() if k != "weights"},
            "preset": args.preset,
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
