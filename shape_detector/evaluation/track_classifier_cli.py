"""``shape-detector train-track-classifier``: fit the scene map's track classifier.

Renders ``--sequences`` walk-throughs (seeds ``--seed``.., default 2000..: no evaluation uses
them; ``evaluate-scene`` uses 1000.., ``evaluate-ar`` 101..), runs the detector (the
``realtime`` defaults; ``--weights`` for another network than the packaged one) on every
frame, builds each map without a track classifier, and takes every track the final map
publishes as one example: features
(:func:`~shape_detector.scene.track_classifier.tracks_features`) and the class of the labelled
object it overlaps (3D IoU >= 0.25, any class) or background. Objects glimpsed in fewer than 3
frames give no example (``evaluate-scene`` ignores them). The L2 weight is chosen by
``--folds``-fold cross-validation over sequences (log loss), then the classifier is fitted on
all examples and written with its provenance (``meta``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..classes import CLASSES
from ..config_cli import add_detector_flags, config_from_args
from ..scene.track_classifier import OUTPUTS, default_path, fit, tracks_features

#: L2 weights tried by the cross-validation
L2_GRID = (1e-3, 3e-3, 1e-2, 3e-2)


def sequence_examples(data: Any, scene_config: Any = None, min_frames: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Features (N, F) and labels (N,) (indices into ``OUTPUTS``) of the tracks that the final
    map of one walk-through (``SequenceData``) publishes, built without a track classifier."""
    from ..scene import SceneConfig
    from .scene_eval import best_gt, labelled_objects, run_map

    config = replace(scene_config or SceneConfig(), track_classifier="")
    m, _ = run_map(data, config)
    tracks = [t for t in sorted(m.tracks, key=lambda t: t.id) if m.shown(t)]
    gts, ignored = labelled_objects(data, min_frames)
    objects = gts + ignored
    labels, keep = [], []
    for j in best_gt(tracks, objects):  # a track on an ignored object teaches nothing, as it counts nothing
        labels.append(OUTPUTS.index("background") if j < 0 else CLASSES.index(objects[j].class_name))
        keep.append(j < len(gts))
    k = np.array(keep, bool)
    return tracks_features(tracks, m.floor_z)[k], np.array(labels, int)[k]


def seed_examples(seed: int, detector: Any = None, frames: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sequence_examples` of walk-through ``seed`` (rendered and detected here: a worker
    of :func:`~.parallel.map_seeds` returns only the examples, not the frames)."""
    from .scene_eval import collect_one

    return sequence_examples(collect_one(seed, frames, detector=detector))


def cross_validate(xs: Sequence[np.ndarray], ys: Sequence[np.ndarray], folds: int, l2: float) -> dict[str, float]:
    """Mean held-out log loss and accuracy of :func:`fit` at ``l2``, sequences split into ``folds``."""
    idx = np.arange(len(xs))
    loss, acc, n = 0.0, 0.0, 0
    for f in range(folds):
        test = idx % folds == f
        xtr = np.concatenate([x for x, t in zip(xs, test) if not t])
        ytr = np.concatenate([y for y, t in zip(ys, test) if not t])
        xte = np.concatenate([x for x, t in zip(xs, test) if t])
        yte = np.concatenate([y for y, t in zip(ys, test) if t])
        if len(yte) == 0 or len(ytr) == 0:
            continue
        p = fit(xtr, ytr, l2).probabilities(xte)
        loss += float(-np.log(p[np.arange(len(yte)), yte] + 1e-12).sum())
        acc += float((p.argmax(1) == yte).sum())
        n += len(yte)
    return {"l2": l2, "log_loss": loss / max(n, 1), "accuracy": acc / max(n, 1)}


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Add the options of ``train-track-classifier`` to ``p``."""
    p.add_argument("--sequences", type=int, default=192, help="walk-throughs to learn from (default 192)")
    p.add_argument("--frames", type=int, default=40, help="frames per walk-through (default 40, 5 Hz)")
    p.add_argument("--seed", type=int, default=2000, help="first walk-through seed (default 2000)")
    p.add_argument("--folds", type=int, default=4, help="cross-validation folds for the L2 weight (default 4)")
    p.add_argument("--processes", type=int, default=2, metavar="N", help="walk-throughs in N worker processes")
    p.add_argument("-o", "--out", default=str(default_path()),
                   help="weights file to write (default: the packaged one)")
    add_detector_flags(p, "realtime", only=("weights",))


def main(args: argparse.Namespace) -> int:
    """Collect, cross-validate, fit and save; 0 on success, 2 on bad options."""
    if args.sequences < args.folds or args.folds < 2 or args.frames < 1 or args.processes < 1:
        print("shape-detector train-track-classifier: need --sequences >= --folds >= 2, --frames and "
              "--processes >= 1", file=sys.stderr)
        return 2
    from ..detector import ShapeDetector
    from ..digests import sha256_file
    from .parallel import map_seeds

    t0 = time.time()
    seeds = list(range(args.seed, args.seed + args.sequences))
    xs, ys = [], []
    det_config = config_from_args(args)
    try:  # bad weights refused here, before any walk-through; the detector resolves the file
        detector = ShapeDetector(det_config)
    except (FileNotFoundError, ValueError) as e:
        print(f"shape-detector train-track-classifier: {e}", file=sys.stderr)
        return 2
    weights = detector.predictor.weights_path
    if weights is None:
        print("shape-detector train-track-classifier: no network weights (none packaged, no --weights)",
              file=sys.stderr)
        return 2
    for seed, (x, y) in zip(seeds, map_seeds(seed_examples, seeds, det_config, args.processes, detector,
                                             frames=args.frames)):
        xs.append(x)
        ys.append(y)
        print(f"walk-through {seed}: {len(y)} tracks ({time.time() - t0:.0f} s)", file=sys.stderr)
    cv = [cross_validate(xs, ys, args.folds, l2) for l2 in L2_GRID]
    for r in cv:
        print(f"l2 {r['l2']:g}: held-out log loss {r['log_loss']:.3f}, accuracy {r['accuracy']:.3f}")
    best = min(cv, key=lambda r: r["log_loss"])
    x, y = np.concatenate(xs), np.concatenate(ys)
    meta = {"command": "shape-detector train-track-classifier " + " ".join(
                f"--{k.replace('_', '-')} {v}" for k, v in sorted(vars(args).items())
                if k in ("sequences", "frames", "seed", "folds")) + (f" --weights {weights}" if det_config.weights else ""),
            "seeds": [seeds[0], seeds[-1]], "frames": args.frames, "examples": int(len(y)),
            "examples_per_output": {o: int((y == i).sum()) for i, o in enumerate(OUTPUTS)},
            "detector_weights_sha256": sha256_file(weights), "detector_preset": "realtime",
            "l2": best["l2"], "cross_validation": cv, "date": time.strftime("%Y-%m-%d")}
    model = fit(x, y, best["l2"], meta)
    model.meta["train_accuracy"] = float((model.probabilities(x).argmax(1) == y).mean())
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    model.save(args.out)
    print(f"wrote {args.out}: {len(y)} tracks from {len(seeds)} walk-throughs, l2 {best['l2']:g}, "
          f"held-out accuracy {best['accuracy']:.3f}, {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="shape-detector train-track-classifier", description=__doc__)
    configure_parser(parser)
    sys.exit(main(parser.parse_args()))
