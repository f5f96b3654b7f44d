"""``shape-detector train``: run a training recipe, or one ad-hoc training run.

A recipe (see :mod:`.recipe`; the shipped weights' is ``recipes/shipped.json``)::

    shape-detector train --recipe shipped --data-root data --out runs/shipped \\
        [--phase NAME ...] [--max-minutes M] [--export shape_detector/weights] [--adopt WEIGHTS ...]

runs its phases in order; each is skipped when its weights exist with a matching key and
resumes from its checkpoint otherwise. ``--max-minutes`` stops the run (exit status 3;
the same command continues it), it never changes what a finished phase computes. Under
``torchrun --nproc_per_node N shape-detector train ...`` the network phases run
data-parallel (gloo on CPUs, nccl on GPUs); see docs/training.md.

One ad-hoc run (experiments) takes a TrainConfig JSON (default: the recipe base's
``defaults``) and data directories or frustum ``.npz`` files::

    shape-detector train --config my.json --data data/train --val-data data/val --out runs/x
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``train``."""
    p.add_argument("--recipe", default=None, help="recipe JSON (a path, or a name under training/recipes)")
    p.add_argument("--phase", action="append", default=None, metavar="NAME",
                   help="run only this phase (repeatable; its parents must have finished)")
    p.add_argument("--data-root", type=Path, default=Path("data"), help="where the recipe's data sets live")
    p.add_argument("--export", type=Path, default=None, metavar="DIR",
                   help="after the recipe, copy the results it exports (e.g. default.pt) into DIR")
    p.add_argument("--adopt", type=Path, nargs="+", default=None, metavar="WEIGHTS",
                   help="take these runner-written weights (e.g. shape_detector/weights/default.pt) as the results "
                        "of the phases their provenance names, where the run directory has none")
    p.add_argument("--config", type=Path, default=None, help="ad-hoc run: training config JSON")
    p.add_argument("--data", type=Path, nargs="+", default=None,
                   help="ad-hoc run: shard directories and/or frustum .npz files (concatenated)")
    p.add_argument("--val-data", type=Path, default=None, help="ad-hoc run: held-out shard directory or .npz")
    p.add_argument("--out", type=Path, default=None, help="run directory (recipe default runs/<recipe name>)")
    p.add_argument("--seed", type=int, default=0, help="ad-hoc run: seed")
    p.add_argument("--epochs", type=int, default=None, help="ad-hoc run: override the config's epochs")
    p.add_argument("--resume", action="store_true", help="ad-hoc run: continue from RUN_DIR/checkpoint.pt")
    p.add_argument("--init", type=Path, default=None, metavar="WEIGHTS", help="ad-hoc run: start from these weights")
    p.add_argument("--tasks", default=None, help="ad-hoc run: comma list of box,shape,cls")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda[:i]")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this long (resumable: run the same command again)")
    p.add_argument("--max-frames", type=int, default=None, help="ad-hoc run: at most this many training frames")
    p.add_argument("--max-val-frames", type=int, default=None, help="ad-hoc run: at most this many val frames")
    p.add_argument("--threads", type=int, default=None, help="ad-hoc run: torch CPU threads")
    p.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                   help="ad-hoc run: override a config entry, e.g. --set batch_size=64 --set model.num_points=256")


def load_config(path: Path | None, overrides: list[str] | None = None):
    """TrainConfig of an ad-hoc run: ``path`` (default: the base recipe's defaults) with
    ``KEY=JSON`` overrides (dotted keys reach into ``model`` / ``data``)."""
    from .config import TrainConfig
    from .recipe import load_recipe

    if path is not None:
        if not path.is_file():
            raise FileNotFoundError(path)
        d: dict[str, Any] = json.loads(path.read_text())
    else:
        d = load_recipe("base")["defaults"]
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


def _resolve_device(name: str):
    from ..model.devices import resolve_device

    return resolve_device(name)


def main_recipe(args: argparse.Namespace) -> int:
    """Run a recipe (see the module docstring); exit 3 when the time budget stopped it."""
    from . import distributed as ddp
    from .recipe import load_recipe
    from .runner import Stopped, adopt, export, run_recipe

    r = load_recipe(args.recipe)
    env, dev = ddp.setup(args.device)
    device = dev or _resolve_device(args.device)
    out = args.out or Path("runs") / Path(r["file"]).stem
    say = (lambda s: print(s, flush=True)) if env.is_main else (lambda s: None)
    say(f"recipe {r['file']} (sha256 {r['sha256'][:12]}): {len(r['phases'])} phases -> {out}")
    if args.adopt:
        failed = False
        if env.is_main:
            try:
                adopt(r, out, args.adopt, say)
            except (OSError, ValueError) as e:
                print(f"shape-detector train: --adopt: {e}", file=sys.stderr)
                failed = True
        if ddp.broadcast_flag(env, failed):  # every rank stops, none waits for rank 0
            return 2
    try:
        results = run_recipe(r, out, args.data_root, args.phase, device, args.max_minutes, say)
    except Stopped as e:
        say(f"stopped in phase {e} by --max-minutes; run the same command again to continue")
        return 3
    for res in results:
        say(f"  {res['phase']:<16} {res.get('file', '?'):<14} {res.get('seconds', 0) / 60:7.1f} min  "
            f"sha256 {str(res.get('sha256'))[:12]}")
    if args.export is not None and env.is_main:
        export(r, out, args.export, say)
    return 0


def main_single(args: argparse.Namespace) -> int:
    """One ad-hoc training run."""
    from . import distributed as ddp
    from . import frustum_dataset as fds
    from .data_cache import get_frustums
    from .train import train

    cfg = load_config(args.config, args.set)
    if args.epochs is not None:
        cfg.epochs = int(args.epochs)
    if args.tasks:
        cfg.tasks = args.tasks
    if args.threads:
        cfg.num_threads = int(args.threads)
    env, dev = ddp.setup(args.device)
    device = dev or _resolve_device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    npts = cfg.model_config().num_points
    parts = [get_frustums(d, cfg.data, npts, out, "train", args.max_frames) for d in args.data]
    train_ds = parts[0] if len(parts) == 1 else fds.concat(parts)
    if args.val_data is not None:
        val_ds = get_frustums(args.val_data, cfg.data, npts, out, "val", args.max_val_frames)
    else:
        train_ds, val_ds = fds.split_by_frame(train_ds, cfg.val_fraction, seed=12345)
    final = train(cfg, train_ds, val_ds, out, seed=args.seed, device=device, resume=args.resume,
                  max_minutes=args.max_minutes, print_fn=lambda s: print(s, flush=True), init_weights=args.init,
                  extra_meta={"data": [d.name for d in args.data], "init": args.init.name if args.init else None})
    best = final.get("best.pt", {}).get("metrics", {})
    if best and env.is_main:
        keys = ("seg_acc", "box_iou", "box_iou_agnostic", "shape_iou", "shape_iou_gtbox", "cls_acc_agnostic")
        print("best.pt: " + " ".join(f"{k} {best[k]:.3f}" for k in keys if k in best))
    return 3 if final.get("stopped_early") else 0


#: options of an ad-hoc run (with their "not given" values): a recipe says all of this itself
_AD_HOC = {"config": None, "data": None, "val_data": None, "seed": 0, "epochs": None, "resume": False, "init": None,
           "tasks": None, "max_frames": None, "max_val_frames": None, "threads": None, "set": []}
#: options of a recipe run only
_RECIPE_ONLY = {"phase": None, "export": None, "adopt": None}


def _misplaced(args: argparse.Namespace, options: dict[str, Any]) -> list[str]:
    return ["--" + k.replace("_", "-") for k, unset in options.items() if getattr(args, k, unset) != unset]


def main(args: argparse.Namespace) -> int:
    """``train``: a recipe with ``--recipe``, else one ad-hoc run (needs ``--data`` and ``--out``)."""
    try:
        if args.recipe is not None:
            bad = _misplaced(args, _AD_HOC)
            if bad:
                print(f"shape-detector train: {', '.join(bad)} do not apply to --recipe (the recipe sets them; "
                      "a finished phase is skipped, an unfinished one resumes)", file=sys.stderr)
                return 2
            return main_recipe(args)
        bad = _misplaced(args, _RECIPE_ONLY)
        if bad:
            print(f"shape-detector train: {', '.join(bad)} need --recipe", file=sys.stderr)
            return 2
        if not args.data or args.out is None:
            print("shape-detector train: give --recipe FILE, or --data and --out for one run", file=sys.stderr)
            return 2
        return main_single(args)
    except (FileNotFoundError, ValueError, KeyError, RuntimeError) as e:
        print(f"shape-detector train: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    sys.exit(main(parser.parse_args()))
