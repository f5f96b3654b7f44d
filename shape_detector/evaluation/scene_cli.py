"""``shape-detector evaluate-scene``: the scene map on generated walk-through sequences.

Renders ``--sequences`` walk-throughs (seeds ``--seed``.., never used in training), runs the
detector on every frame, feeds a SceneMap with the true poses and prints the metrics of
:mod:`shape_detector.evaluation.scene_eval` against the targets of issue #26 (``--json``:
the numbers as JSON instead).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from ..config_cli import add_detector_flags, config_from_args
from .runner import GT_2D_CHOICES

#: metric key, label, target text, format
ROWS = (
    ("mAP@0.25", "map mAP@0.25", ">= 90", "{:.1f}"),
    ("mAP@0.5", "map mAP@0.5", ">= 75", "{:.1f}"),
    ("duplicates_per_object", "duplicate tracks / object", "<= 0.05", "{:.3f}"),
    ("id_switches_per_object", "identity switches / object", "<= 0.1", "{:.3f}"),
    ("jitter_cm", "centre jitter (cm)", "<= 2", "{:.2f}"),
    ("grid_iou", "grid IoU (occupied cells)", ">= 0.7", "{:.3f}"),
    ("map_update_ms", "ms per map update", "<= 5", "{:.2f}"),
    ("detector_ms", "ms per detector frame", "", "{:.0f}"),
)


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Add the options of ``evaluate-scene`` to ``p``."""
    p.add_argument("--sequences", type=int, default=12,
                   help="walk-through sequences (default 12: with fewer, one missed object of a rare class "
                   "moves the mAP by 10 points)")
    p.add_argument("--frames", type=int, default=40, help="frames per sequence (default 40, 5 Hz)")
    p.add_argument("--seed", type=int, default=1000, help="first sequence seed (default 1000; training used 1-6)")
    p.add_argument("--width", type=int, default=640, help="image width (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height (default 480)")
    p.add_argument("--min-frames", type=int, default=3,
                   help="ground truth: objects seen in at least this many frames (default 3)")
    p.add_argument("--confirm-observations", type=int, default=None, help="SceneConfig.confirm_observations")
    p.add_argument("--delete-misses", type=int, default=None, help="SceneConfig.delete_misses")
    p.add_argument("--publish-score", type=float, default=None, help="SceneConfig.publish_score (0: every "
                   "confirmed track)")
    p.add_argument("--track-classifier", default=None,
                   help="SceneConfig.track_classifier: default (packaged), a weights file, or '' (off: the class "
                   "evidence decides)")
    p.add_argument("--up", choices=("pose", "estimate"), default="pose",
                   help="gravity for the detector: pose (the camera pose's z axis, default; the node's "
                   "up_source auto with a pose) or estimate (from each frame)")
    p.add_argument("--pose-noise", default=None, metavar="D,Y,J,JD",
                   help="poses as odometry reports them: drift D m per m travelled, heading drift Y deg per m, "
                   "per-frame jitter J m and JD deg (e.g. 0.01,0.5,0.005,0.2); default: the true poses")
    p.add_argument("--gt-2d", choices=GT_2D_CHOICES, default=None,
                   help="give the detector the frames' true 2D boxes instead of its proposals, without (boxes) "
                   "or with their classes (classes): the upper bound an ideal 2D stage would give")
    p.add_argument("--processes", type=int, default=1, metavar="N",
                   help="walk-throughs in N worker processes, each with its own detector (default 1: here; "
                   "with more, --workers 1 keeps one core per process)")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    p.add_argument("--quiet", action="store_true", help="no per-sequence progress")
    add_detector_flags(p, "realtime")


def _config(args: argparse.Namespace) -> Any:
    from dataclasses import replace

    from ..scene import SceneConfig

    changes = {k: v for k, v in (("confirm_observations", args.confirm_observations),
                                 ("delete_misses", args.delete_misses),
                                 ("publish_score", args.publish_score),
                                 ("track_classifier", args.track_classifier)) if v is not None}
    return replace(SceneConfig(), **changes)


def format_table(res: dict[str, Any], args: argparse.Namespace) -> str:
    """The results as a text table (map, target, stacked-detections baseline)."""
    seeds = f"{args.seed}..{args.seed + args.sequences - 1}"
    lines = [f"scene map: {res['sequences']} walk-throughs x {args.frames} frames at {args.width}x{args.height} "
             f"(seeds {seeds}), {res['objects']} objects seen in >= {args.min_frames} frames, "
             f"{res['tracks']} published tracks; gravity {args.up}, "
             + (f"poses with noise {args.pose_noise} (drift m/m, deg/m, jitter m, deg)" if args.pose_noise
                else "true poses")
             + (f"; the true 2D boxes{' and classes' if args.gt_2d == 'classes' else ''} given (--gt-2d)"
                if args.gt_2d else ""),
             f"{'metric':30s} {'map':>9s} {'target':>9s} {'stacked':>9s}"]
    flat = {**{f"mAP@{k}": v for k, v in res["map_mAP"].items()}, **res}
    stacked = {f"mAP@{k}": v for k, v in res["stack_mAP"].items()}
    for key, label, target, fmt in ROWS:
        base = fmt.format(stacked[key]) if key in stacked else ""
        lines.append(f"{label:30s} {fmt.format(flat[key]):>9s} {target:>9s} {base:>9s}")
    oi = res.get("object_iou")
    if oi:
        lines.append(f"per object, best same-class track: median 3D IoU {oi['median']:.3f}, "
                     f"share >= 0.25 / 0.5: {oi['0.25']:.3f} / {oi['0.5']:.3f} (of {res['objects']})")
    hyp = res.get("map_mAP_runner_up")
    if hyp:
        lines.append("comparison only, each object also scored for its runner-up class: map mAP@0.25 / @0.5 "
                     + " / ".join(f"{hyp[k]:.1f}" for k in sorted(hyp)))
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Run the evaluation; 0 on success, 2 on bad options or a missing detector."""
    if args.sequences < 1 or args.frames < 1 or args.processes < 1:
        print("shape-detector evaluate-scene: --sequences, --frames and --processes must be >= 1", file=sys.stderr)
        return 2
    from ..detector import ShapeDetector
    from ..scene.track_classifier import load_track_classifier
    from .pose_noise import parse_pose_noise
    from .scene_eval import collect, score_sequences

    try:
        det_config = config_from_args(args)
        detector = ShapeDetector(det_config)  # also with workers: bad settings or weights refused here, clearly
        config = _config(args)
        load_track_classifier(config.track_classifier)  # a bad file is refused before the walk-throughs run
        noise = parse_pose_noise(args.pose_noise) if args.pose_noise else None
    except (FileNotFoundError, ValueError) as e:
        print(f"shape-detector evaluate-scene: {e}", file=sys.stderr)
        return 2
    progress = None if args.quiet else (lambda s: print(s, file=sys.stderr))
    seeds = list(range(args.seed, args.seed + args.sequences))
    data = collect(seeds, args.frames, args.width, args.height, progress=progress, up=args.up,
                   detector=detector if args.processes == 1 else None,
                   pose_noise=noise, config=det_config, processes=args.processes, gt_2d=args.gt_2d)
    res = score_sequences(data, config, min_frames=args.min_frames)
    if args.json:
        print(json.dumps(res, indent=2, sort_keys=True))
    else:
        print(format_table(res, args))
    return 0


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="shape-detector evaluate-scene", description=__doc__)
    configure_parser(parser)
    sys.exit(main(parser.parse_args()))
