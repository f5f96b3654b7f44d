"""``shape-detector train-proposer``: the learned 2D proposer from generated frames.

Example (what ``make weights`` runs)::

    shape-detector train-proposer --data data/train data/extra data/extra2 --out shape_detector/weights/proposer2d.onnx --epochs 30

Targets are CenterNet's: per object with at least ``--min-visible`` of it in view, a Gaussian
peak at its 2D box centre on the output grid (spread a sixth of the box per axis), and at
that cell the sub-cell offset and the log box size; focal loss on the heatmap, L1 on the
regression. Augmentation: horizontal flips and colour gain / offset. One-cycle AdamW.
Writes the ONNX graph (``--out``) and beside it ``<out>.json``: the provenance
(:mod:`.provenance`: commit, data, settings, losses, sha256 of the graph); then its int8
version (:mod:`~shape_detector.proposals.learned_int8`, calibrated on the first frames of the
first ``--data``), which ``--int8-only`` rebuilds alone from an existing graph.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``train-proposer``."""
    p.add_argument("--data", type=Path, nargs="+", required=True, help="generator shard directories")
    p.add_argument("--out", type=Path, required=True, help="ONNX file to write (provenance beside it, .json)")
    p.add_argument("--max-frames", type=int, default=None, help="use at most this many frames per --data")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--min-visible", type=float, default=0.1,
                   help="objects with a smaller visible share are not targets (default 0.1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    p.add_argument("--int8-only", action="store_true",
                   help="do not train: write the int8 version of the existing --out network, calibrated on "
                        f"the first {CALIBRATION_FRAMES} frames of --data")


def targets(boxes: list[tuple[float, float, float, float]], width: int, height: int,
            out_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(heatmap (1,h,w), reg (4,h,w), mask (1,h,w))`` for pixel boxes of a ``width`` x
    ``height`` frame on an output grid of ``out_size`` = (w, h) cells."""
    ow, oh = out_size
    hm = np.zeros((1, oh, ow), np.float32)
    reg = np.zeros((4, oh, ow), np.float32)
    mask = np.zeros((1, oh, ow), np.float32)
    sx, sy = ow / width, oh / height
    ys, xs = np.mgrid[0:oh, 0:ow]
    # large boxes first: where two centres share a cell, the smaller object's box is kept
    for x1, y1, x2, y2 in sorted(boxes, key=lambda b: -(b[2] - b[0]) * (b[3] - b[1])):
        cx, cy = 0.5 * (x1 + x2) * sx, 0.5 * (y1 + y2) * sy
        w, h = (x2 - x1) * sx, (y2 - y1) * sy
        if w < 0.5 or h < 0.5:
            continue
        ix, iy = min(int(cx), ow - 1), min(int(cy), oh - 1)
        gx, gy = max(w / 6.0, 0.6), max(h / 6.0, 0.6)
        hm[0] = np.maximum(hm[0], np.exp(-((xs - ix) ** 2 / (2 * gx * gx) + (ys - iy) ** 2 / (2 * gy * gy))))
        reg[:, iy, ix] = (cx - ix, cy - iy, math.log(w), math.log(h))
        mask[0, iy, ix] = 1.0
    return hm, reg, mask


def focal_loss(logits: Any, gt: Any) -> Any:
    """CenterNet's penalty-reduced focal loss, per positive cell."""
    import torch

    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = gt.eq(1).float()
    pos_loss = torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = torch.log(1 - p) * p ** 2 * (1 - gt) ** 4 * (1 - pos)
    return -(pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp(min=1)


#: frames of the training data the int8 version is calibrated on
CALIBRATION_FRAMES = 64


def write_int8(out: Path, x: np.ndarray, data: list[Path]) -> Path:
    """The int8 version of the network ``out`` beside it, calibrated on the first
    :data:`CALIBRATION_FRAMES` inputs of ``x``; its provenance names ``data``."""
    from ..proposals.learned_int8 import quantize
    from .provenance import dataset_identity

    path = quantize(out, x[:CALIBRATION_FRAMES], data=[dataset_identity(d) for d in data],
                    command="shape-detector train-proposer " + " ".join(sys.argv[2:]))
    print(f"train-proposer: wrote {path} ({path.stat().st_size} bytes)")
    return path


def load_frames(dirs: list[Path], max_frames: int | None, min_visible: float) -> tuple[np.ndarray, list]:
    """Network inputs (N,5,H,W) and per frame ``(boxes, width, height)``."""
    from ..proposals.learned import prepare_input
    from ..synth.dataset import iter_frames

    xs, boxes = [], []
    for d in dirs:
        for i, f in enumerate(iter_frames(d)):
            if max_frames is not None and i >= max_frames:
                break
            h, w = f.depth.shape
            xs.append(prepare_input(f.rgb, f.depth))
            boxes.append(([tuple(float(v) for v in g.box2d) for g in f.objects
                           if g.visible_fraction >= min_visible], w, h))
    if not xs:
        raise ValueError(f"no frames in {[str(d) for d in dirs]}")
    return np.stack(xs), boxes


def train(x: np.ndarray, frames: list, epochs: int, batch_size: int, lr: float, seed: int,
          log: Any = print) -> tuple[Any, list[float]]:
    """Train a :class:`~shape_detector.model.proposer2d.Proposer2DNet`; returns it (eval mode)
    and the loss of each epoch."""
    import torch
    import torch.nn.functional as F

    from ..model.proposer2d import Proposer2DNet
    from ..proposals.learned import STRIDE

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = Proposer2DNet()
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    n = len(x)
    steps = max(1, epochs * ((n + batch_size - 1) // batch_size))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.15)
    out_size = (x.shape[3] // STRIDE, x.shape[2] // STRIDE)
    plain = [targets(b, w, h, out_size) for b, w, h in frames]
    flipped = [targets([(w - b[2], b[1], w - b[0], b[3]) for b in bs], w, h, out_size) for bs, w, h in frames]
    losses = []
    t0 = time.time()
    for epoch in range(epochs):
        net.train()
        total = 0.0
        perm = rng.permutation(n)
        for start in range(0, n, batch_size):
            idx = perm[start:start + batch_size]
            flip = rng.random(len(idx)) < 0.5
            xb = np.stack([x[i][:, :, ::-1] if f else x[i] for i, f in zip(idx, flip)]).copy()
            xb[:, :3] = (xb[:, :3] * rng.uniform(0.8, 1.2, (len(idx), 1, 1, 1))
                         + rng.uniform(-0.1, 0.1, (len(idx), 3, 1, 1))).astype(np.float32)
            tb = [flipped[i] if f else plain[i] for i, f in zip(idx, flip)]
            hm_t, reg_t, mask = (torch.from_numpy(np.stack([t[k] for t in tb])) for k in range(3))
            hm, reg = net(torch.from_numpy(xb))
            loss = focal_loss(hm, hm_t) + (F.l1_loss(reg, reg_t, reduction="none") * mask).sum() / mask.sum().clamp(min=1)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(idx)
        losses.append(total / n)
        log(f"epoch {epoch + 1}/{epochs}: loss {losses[-1]:.3f} ({time.time() - t0:.0f} s)")
    return net.eval(), losses


def export_onnx(net: Any, path: Path, input_shape: tuple[int, int, int]) -> None:
    """Write ``net`` as an ONNX graph with a dynamic batch axis (``input`` -> ``heatmap``, ``reg``)."""
    import warnings

    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net.eval(), (torch.zeros(1, *input_shape),), str(tmp), input_names=["input"],
                          output_names=["heatmap", "reg"], opset_version=17, dynamo=False,
                          dynamic_axes={"input": {0: "batch"}, "heatmap": {0: "batch"}, "reg": {0: "batch"}})
    tmp.replace(path)


def main(args: argparse.Namespace) -> int:
    """Train, export, write provenance; 0 on success, 2 on bad input."""
    import torch

    from ..digests import sha256_file
    from ..proposals.learned_int8 import provenance_path
    from .provenance import dataset_identity, make_provenance

    for d in args.data:
        if not Path(d).is_dir():
            print(f"train-proposer: no shard directory {d}", file=sys.stderr)
            return 2
    if args.epochs < 1 or args.batch_size < 1:
        print("train-proposer: --epochs and --batch-size must be >= 1", file=sys.stderr)
        return 2
    torch.set_num_threads(max(1, args.threads))
    t0 = time.time()
    if args.int8_only and not args.out.is_file():
        print(f"train-proposer: --int8-only needs an existing network at --out ({args.out})", file=sys.stderr)
        return 2
    limit = CALIBRATION_FRAMES if args.int8_only else args.max_frames
    try:
        x, frames = load_frames(list(args.data)[:1] if args.int8_only else list(args.data), limit,
                                args.min_visible)
    except ValueError as e:
        print(f"train-proposer: {e}", file=sys.stderr)
        return 2
    if args.int8_only:
        write_int8(args.out, x, list(args.data)[:1])
        return 0
    print(f"train-proposer: {len(x)} frames, {sum(len(b) for b, _, _ in frames)} boxes", flush=True)
    net, losses = train(x, frames, args.epochs, args.batch_size, args.lr, args.seed,
                        log=lambda s: print(s, flush=True))
    export_onnx(net, args.out, tuple(x.shape[1:]))
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                if k in ("epochs", "batch_size", "lr", "min_visible", "seed", "max_frames")}
    prov = make_provenance("proposer2d", data=[dataset_identity(d) for d in args.data],
                           metrics={"final_loss": losses[-1]}, settings=settings, losses=losses,
                           minutes=(time.time() - t0) / 60.0, sha256=sha256_file(args.out),
                           command="shape-detector train-proposer " + " ".join(sys.argv[2:]))
    provenance_path(args.out).write_text(json.dumps(prov, indent=2) + "\n")
    write_int8(args.out, x, list(args.data)[:1])
    print(f"train-proposer: wrote {args.out} ({args.out.stat().st_size} bytes) in {(time.time() - t0) / 60:.1f} min")
    return 0


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="shape-detector train-proposer", description=__doc__)
    configure_parser(parser)
    sys.exit(main(parser.parse_args()))
