"""``shape-detector train``: build (or reuse) the frustum dataset and train the network.

Example::

    shape-detector train --config shape_detector/training/configs/default.json \\
        --data data/train --out runs/multitask --seed 0 --max-minutes 35

``--data`` / ``--val-data`` are generator shard directories (read with
``shape_detector.synth.dataset.iter_frames``) or frustum caches (``.npz`` written by
:func:`shape_detector.training.frustum_dataset.save`). Built datasets are cached in the
run directory (``frustums_<train|val>_<hash>.npz``) and reused on ``--resume`` / re-runs.
Without ``--val-data``, ``val_fraction`` of the training frames is held out.
``--tasks`` selects the loss groups: ``box,shape,cls`` (end-to-end multi-task, default),
``box,cls`` (detection only), ``shape,cls`` / ``shape`` (shape-only baseline; segmentation
is always trained).
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

DEFAULT_CONFIG = Path(__file__).resolve().parent / "configs" / "default.json"


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None, help=f"training config JSON (default {DEFAULT_CONFIG.name})")
    p.add_argument("--data", type=Path, required=True, nargs="+",
                   help="shard directories of generated frames and/or frustum .npz files (concatenated)")
    p.add_argument("--val-data", type=Path, default=None, help="held-out shard directory or frustum .npz")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=None, help="override the config's epochs")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/checkpoint.pt")
    p.add_argument("--init", type=Path, default=None, metavar="WEIGHTS",
                   help="start from these weights (.pt; same model config) instead of a random init: fine-tuning")
    p.add_argument("--tasks", default=None, help="comma list of box,shape,cls (default: config)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda[:i]")
    p.add_argument("--max-minutes", type=float, default=None, help="training time budget (epochs are planned to fit)")
    p.add_argument("--max-frames", type=int, default=None, help="use at most this many training frames")
    p.add_argument("--max-val-frames", type=int, default=None, help="use at most this many validation frames")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: config num_threads)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                   help="override a config entry, e.g. --set batch_size=64 --set model.num_points=256")


def load_config(path: Path | None, overrides: list[str] | None = None):
    from .train import TrainConfig

    d: dict[str, Any] = {}
    p = path or DEFAULT_CONFIG
    if p.is_file():
        d = json.loads(p.read_text())
    elif path is not None:
        raise FileNotFoundError(path)
    for item in overrides or []:
        key, _, val = item.partition("=")
        try:
            v = json.loads(val)
        except json.JSONDecodeError:
            v = val
        tgt = d
        ks = key.split(".")
        for k in ks[:-1]:
            tgt = tgt.setdefault(k, {})
        tgt[ks[-1]] = v
    return TrainConfig.from_dict(d)


def _listing_hash(path: Path, extra: dict[str, Any]) -> str:
    h = hashlib.sha1(json.dumps(extra, sort_keys=True).encode())
    h.update(str(path.resolve()).encode())
    files = sorted(path.rglob("*")) if path.is_dir() else [path]
    for f in files:
        if f.is_file():
            st = f.stat()
            h.update(f"{f.relative_to(path) if path.is_dir() else f.name}:{st.st_size}:{int(st.st_mtime)}".encode())
    return h.hexdigest()[:12]


def get_dataset(path: Path, cfg, out_dir: Path, tag: str, max_frames: int | None, seed: int) -> dict:
    """Frustum dataset of ``path`` (npz as is, or built from shards and cached in ``out_dir``)."""
    from . import frustum_dataset as fds

    if path.is_file() and path.suffix == ".npz":
        return fds.load(path)
    data_cfg = fds.FrustumDatasetConfig.from_dict(cfg.data)
    data_cfg.num_points = int(cfg.model_config().num_points)
    if tag == "val":
        data_cfg.augment_copies = 1
    data_cfg.rng_seed = int(data_cfg.rng_seed) + (0 if tag == "train" else 1000)
    key = _listing_hash(path, {"data": data_cfg.to_dict(), "max_frames": max_frames})
    cache = out_dir / f"frustums_{tag}_{key}.npz"
    if cache.is_file():
        print(f"{tag} frustums: cached {cache}")
        return fds.load(cache)
    from ..synth.dataset import iter_frames

    t0 = time.time()
    frames = iter_frames(path)
    if max_frames:
        frames = itertools.islice(frames, int(max_frames))
    print(f"{tag} frustums: building from {path} ...", flush=True)
    ds = fds.build_frustum_dataset(frames, config=data_cfg, num_points=data_cfg.num_points,
                                   augment_copies=data_cfg.augment_copies, rng_seed=data_cfg.rng_seed,
                                   negatives_per_frame=data_cfg.negatives_per_frame, progress=True)
    fds.save(ds, cache)
    print(f"{tag} frustums: {fds.summary(ds)} in {time.time() - t0:.0f}s -> {cache}", flush=True)
    return ds


def main(args: argparse.Namespace) -> int:
    import torch

    from . import frustum_dataset as fds
    from ..model.predictor import resolve_device
    from .train import train

    cfg = load_config(args.config, args.set)
    if args.epochs is not None:
        cfg.epochs = int(args.epochs)
    if args.tasks:
        cfg.tasks = args.tasks
    if args.threads:
        cfg.num_threads = int(args.threads)
    device = resolve_device(args.device)
    if device.type == "cpu" and cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    parts = [get_dataset(d, cfg, out, "train", args.max_frames, args.seed) for d in args.data]
    train_ds = parts[0] if len(parts) == 1 else fds.concat(parts)
    if args.val_data is not None:
        val_ds = get_dataset(args.val_data, cfg, out, "val", args.max_val_frames, args.seed)
    else:
        train_ds, val_ds = fds.split_by_frame(train_ds, cfg.val_fraction, seed=12345)
    print(f"train: {fds.summary(train_ds)}\nval:   {fds.summary(val_ds)}", flush=True)
    final = train(
        cfg, train_ds, val_ds, out, seed=args.seed, device=device, resume=args.resume,
        max_minutes=args.max_minutes, print_fn=lambda s: print(s, flush=True), init_weights=args.init,
        extra_meta={"data": [str(d) for d in args.data], "init": str(args.init) if args.init else None, "val_data": str(args.val_data) if args.val_data else None},
    )
    best = final.get("best.pt", {}).get("metrics", {})
    if best:
        keys = ("seg_acc", "box_iou", "box_acc25", "box_acc50", "box_iou_agnostic", "shape_iou", "shape_iou_gtbox",
                "shape_surface_dist", "shape_surface_dist_gtbox", "cls_acc_agnostic")
        print("best.pt: " + " ".join(f"{k} {best[k]:.3f}" for k in keys if k in best))
    print(f"outputs in {out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser()
    configure_parser(p)
    sys.exit(main(p.parse_args()))
