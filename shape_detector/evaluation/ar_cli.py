"""``shape-detector evaluate-ar``: the AR queries scored on generated walk-throughs.

Metrics and acceptance thresholds: :mod:`shape_detector.evaluation.ar_eval`. Walk-through
seeds draw from their own random streams (never training data).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..config_cli import add_detector_flags, config_from_args
from .runner import GT_2D_CHOICES

#: metric -> acceptance threshold (issue #27)
THRESHOLDS = {"ray_within_5cm": 0.90, "collide_precision": 0.90, "collide_recall": 0.90, "plan_found": 0.95,
              "plan_clear": 1.0}


def _nanmean(values: list[float]) -> float:
    """Mean of the finite values (NaN: a metric without samples in every sequence)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``shape-detector evaluate-ar``."""
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(101, 113)),
                   help="walk-through seeds (default 101-112: with 3, one seed moves a share by several points)")
    p.add_argument("--frames", type=int, default=40, help="frames per walk-through")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--gt-map", action="store_true", help="query the true scene instead of the detector's map "
                   "(checks the evaluation, not the map)")
    p.add_argument("--rays", type=int, default=2000, help="ray casts per walk-through")
    p.add_argument("--points", type=int, default=2000, help="collision points per walk-through")
    p.add_argument("--pairs", type=int, default=40, help="start / goal pairs per walk-through")
    p.add_argument("--radius", type=float, default=0.1, help="collision sphere radius (m)")
    p.add_argument("--agent-radius", type=float, default=0.2, help="planning agent radius (m)")
    p.add_argument("--json", default=None, help="also write the per-sequence and mean metrics here")
    p.add_argument("--gt-2d", choices=GT_2D_CHOICES, default=None,
                   help="give the detector the frames' true 2D boxes instead of its proposals, without (boxes) "
                   "or with their classes (classes): the upper bound an ideal 2D stage would give")
    p.add_argument("--processes", type=int, default=1, metavar="N",
                   help="walk-throughs in N worker processes, each with its own detector (default 1: here; "
                   "with more, --workers 1 keeps one core per process)")
    p.add_argument("--save-maps", default=None, help="directory for the detector's maps (map_<seed>.json)")
    p.add_argument("--track-classifier", default=None,
                   help="SceneConfig.track_classifier: default (packaged), a weights file, or '' (off)")
    add_detector_flags(p, "realtime")


def pooled_shares(rows: list[dict[str, float]]) -> dict[str, float]:
    """The shares of :data:`THRESHOLDS` that count rays or paths, pooled over the
    walk-throughs' rays and pairs: a walk-through with 3 testable pairs weighs 3, not as much as
    one with 40 (the printed means weigh each walk-through once)."""
    def share(key: str, weight: Any) -> float:
        v = np.array([r[key] for r in rows], dtype=np.float64)
        w = np.array([weight(r) for r in rows], dtype=np.float64)
        ok = np.isfinite(v) & np.isfinite(w) & (w > 0)
        return float((v[ok] * w[ok]).sum() / w[ok].sum()) if ok.any() else float("nan")

    return {"ray_within_5cm": share("ray_within_5cm", lambda r: r["rays_used"]),
            "plan_found": share("plan_found", lambda r: r["plan_pairs"]),
            "plan_clear": share("plan_clear", lambda r: r["plan_pairs"] * r["plan_found"])}


def evaluate_seed(seed: int, detector: Any = None, save_dir: str | None = None, **kwargs: Any) -> dict[str, float]:
    """:func:`~.ar_eval.evaluate_walkthrough` of ``seed``, its map saved as ``map_<seed>.json``
    in ``save_dir`` when given (module level: worker processes run it)."""
    from .ar_eval import evaluate_walkthrough

    save = str(Path(save_dir) / f"map_{seed}.json") if save_dir else None
    return evaluate_walkthrough(seed, detector=detector, save_map=save, **kwargs)


def main(args: argparse.Namespace) -> int:
    """Evaluate; prints per-sequence lines and the means with pass / FAIL per threshold."""
    from .parallel import map_seeds

    if args.frames < 1 or not args.seeds or args.processes < 1:
        print("evaluate-ar: need at least one seed, one frame and one process", file=sys.stderr)
        return 2
    config = detector = None
    if not args.gt_map:
        from ..detector import ShapeDetector
        from ..scene.track_classifier import load_track_classifier

        try:
            config = config_from_args(args)
            detector = ShapeDetector(config)  # bad settings or weights refused here, before any walk-through
            if args.track_classifier is not None:
                load_track_classifier(args.track_classifier)
        except (FileNotFoundError, ValueError) as e:
            print(f"evaluate-ar: {e}", file=sys.stderr)
            return 2
    rows = []
    if args.save_maps:
        Path(args.save_maps).mkdir(parents=True, exist_ok=True)
    kw = dict(frames=args.frames, width=args.width, height=args.height, use_gt_map=args.gt_map, n_rays=args.rays,
              n_points=args.points, n_pairs=args.pairs, radius=args.radius, agent_radius=args.agent_radius,
              save_dir=args.save_maps if args.save_maps and not args.gt_map else None, gt_2d=args.gt_2d,
              track_classifier=args.track_classifier)
    t0 = time.perf_counter()
    for seed, r in zip(args.seeds, map_seeds(evaluate_seed, args.seeds, config, args.processes, detector, **kw)):
        rows.append(r)
        print(f"seed {seed} ({time.perf_counter() - t0:.0f} s): " + ", ".join(f"{k}={v:.3f}" for k, v in r.items()))
    mean = {k: _nanmean([r[k] for r in rows]) for k in rows[0]}
    given = f", the true 2D boxes{' and classes' if args.gt_2d == 'classes' else ''} given (--gt-2d)" if args.gt_2d else ""
    print(f"map: {'true scene (--gt-map)' if args.gt_map else 'detector + SceneMap' + given}, {len(rows)} walk-throughs")
    for k, thr in THRESHOLDS.items():
        print(f"  {k:>30}: {mean[k]:.3f}  (>= {thr:.2f}: {'pass' if mean[k] >= thr else 'FAIL'})")
    for k in ("ray_floor_within_5cm", "ray_within_5cm_primitives", "ray_median_err_cm", "collide_precision_primitives",
              "collide_recall_primitives", "plan_min_clearance_cm",
              "plan_found_blocked", "plan_clear_blocked", "plan_min_clearance_cm_blocked",
              "surface_height_err_cm", "surface_within_2cm", "surface_matched", "surfaces", "objects_true",
              "objects_map"):
        print(f"  {k:>30}: {mean[k]:.3f}")
    pooled = pooled_shares(rows)
    print("  pooled over all rays / pairs instead of averaged over walk-throughs (comparison only): "
          + ", ".join(f"{k} {v:.3f}" for k, v in pooled.items()))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"seeds": list(args.seeds), "per_sequence": rows, "mean": mean, "pooled": pooled,
                       "gt_map": bool(args.gt_map)}, f, indent=1)
    return 0
