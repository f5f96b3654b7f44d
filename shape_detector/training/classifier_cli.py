"""``shape-detector train-classifier``: candidates from generated frames -> the proposal classifier.

Example (what ``make weights`` runs after the network's stages)::

    shape-detector train-classifier --data data/train --out runs/cls --seed 0

Each ``--data`` shard directory goes through the detector's built-in-proposal path with
``--weights`` (default: the packaged network) and is labelled as the evaluation would
(:mod:`shape_detector.training.classifier_data`); the candidates are cached in the run
directory (``candidates_<i>.npz``, reused when present). ``--workers`` processes build
them, one per shard group. The classifier (``RUN/classifier.pt``, the epoch with the
lowest held-out NLL, temperature-calibrated) is then trained on them; copy it to
``shape_detector/weights/classifier.pt`` to ship it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..detector_config import BUILTIN_PROPOSAL_SOURCES


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``train-classifier``."""
    p.add_argument("--data", type=Path, nargs="+", required=True, help="generator shard directories")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--weights", type=Path, default=None, help="network weights (default: the packaged ones)")
    p.add_argument("--max-frames", type=int, default=None, help="use at most this many frames per --data")
    p.add_argument("--workers", type=int, default=2, help="processes building candidates (default 2)")
    p.add_argument("--proposals", type=int, default=20,
                   help="built-in proposals per frame made candidates, best first (default 20)")
    p.add_argument("--proposal-source", default="geometric", choices=BUILTIN_PROPOSAL_SOURCES,
                   help="built-in proposer whose candidates the classifier learns from (default geometric); "
                        "the detector picks the classifier trained on its proposer")
    p.add_argument("--epochs", type=int, default=12)
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads while training (default 2)")


def _build(job: tuple[list[str], str | None, int | None, int, str, str]) -> str:
    """One worker: candidates of some shard files -> an .npz (returns its path)."""
    files, weights, max_frames, proposals, out, source = job
    import cv2
    import torch

    torch.set_num_threads(1)  # one process per core: no thread of OpenCV's or torch's beyond it
    cv2.setNumThreads(1)
    from ..detector import ShapeDetector
    from ..synth.dataset import iter_frames
    from .classifier_data import build_candidates

    det = ShapeDetector(weights=weights, score_threshold=0.0, workers=1, classifier=False, refine=False,
                        max_objects=proposals, proposal_source=source)
    frames = itertools.chain.from_iterable(iter_frames(f) for f in files)
    if max_frames is not None:
        frames = itertools.islice(frames, max_frames)
    ds = build_candidates(det, frames)
    tmp = out + ".tmp.npz"
    np.savez(tmp, **ds)
    Path(tmp).replace(out)
    return out


def build_all(
    data: list[Path], out_dir: Path, weights: Path | None, max_frames: int | None, workers: int, proposals: int = 20,
    proposal_source: str = "geometric",
) -> list[Path]:
    """Candidate files of every shard directory, built by ``workers`` processes (cached)."""
    from ..synth.dataset import shard_paths

    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = []
    for d_i, d in enumerate(data):
        shards = [str(s) for s in shard_paths(d)]
        groups = np.array_split(np.arange(len(shards)), max(1, min(workers, len(shards))))
        per = None if max_frames is None else -(-max_frames // len(groups))
        for g_i, g in enumerate(groups):
            out = out_dir / f"candidates_{d_i}_{g_i}.npz"
            if not out.is_file():
                jobs.append(([shards[k] for k in g], str(weights) if weights else None, per, proposals, str(out),
                             proposal_source))
    if jobs:
        print(f"building candidates: {len(jobs)} jobs on {workers} processes", flush=True)
        if workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            os.environ.setdefault("OMP_NUM_THREADS", "1")  # read by the spawned processes' numpy / torch
            with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
                list(ex.map(_build, jobs))
        else:
            for j in jobs:
                _build(j)
    return sorted(out_dir.glob("candidates_*.npz"))


def load_candidates(paths: list[Path]) -> dict[str, np.ndarray]:
    """Candidate files concatenated (frame indices offset so frames stay distinct)."""
    keys = ("points", "globals", "label", "weight", "frame_index", "iou3d")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    off = 0
    for p in paths:
        with np.load(p) as z:
            for k in keys:
                v = z[k]
                parts[k].append(v + off if k == "frame_index" else v)
            off += int(z["num_frames"])
    return {k: np.concatenate(v) for k, v in parts.items()}


def _candidate_settings(args: argparse.Namespace) -> dict[str, Any]:
    """What the cached candidates in ``--out`` depend on (they are reused by file name)."""
    from ..digests import sha256_file
    from ..detector import DEFAULT_WEIGHTS

    return {"weights": sha256_file(args.weights or DEFAULT_WEIGHTS), "data": [str(d) for d in args.data],
            "max_frames": args.max_frames, "workers": args.workers, "proposals": args.proposals,
            "proposal_source": args.proposal_source}


def main(args: argparse.Namespace) -> int:
    """Build (or reuse) the candidates and train the classifier; exit 2 for missing data."""
    from .train_classifier import ClassifierTrainConfig, train_classifier

    for d in args.data:
        if not d.exists():
            print(f"shape-detector train-classifier: no data directory {str(d)!r}", file=sys.stderr)
            return 2
    settings = _candidate_settings(args)
    stamp = args.out / "candidates.json"
    if stamp.is_file() and json.loads(stamp.read_text()) != settings:
        print(f"shape-detector train-classifier: the candidates in {str(args.out)!r} were built with other "
              f"settings ({stamp}); use another --out or delete them", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps(settings, indent=1))
    t0 = time.time()
    paths = build_all(args.data, args.out, args.weights, args.max_frames, args.workers, args.proposals,
                      args.proposal_source)
    ds = load_candidates(paths)
    n = len(ds["label"])
    print(f"{n} candidates from {len(paths)} files in {time.time() - t0:.0f} s "
          f"(background {np.mean(ds['label'] == ds['label'].max()):.2f})", flush=True)
    cfg = ClassifierTrainConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                                threads=args.threads)
    result = train_classifier(ds, args.out / "classifier.pt", cfg, log=print)
    log_rows: list[dict[str, Any]] = result["history"]
    (args.out / "log.json").write_text(json.dumps({"history": log_rows, "best": result["best"],
                                                   "candidates": n, "seconds": time.time() - t0}, indent=1))
    print(f"best epoch {result['best']['epoch']}: held-out NLL {result['best']['nll']:.4f}, "
          f"accuracy {result['best']['acc']:.3f}; wrote {args.out / 'classifier.pt'} in {time.time() - t0:.0f} s")
    return 0
