"""``shape-detector prune``: narrow a trained network's widest per-point layers (structured pruning).

Each PointNet's last per-point layer is max-pooled into a global feature that heads read. An
output channel of such a layer is ranked by its mean pooled activation over real frustums
times the norm of the weights that read it (each reader's first layer, its BatchNorm scale
applied); the best channels stay: the layer keeps their rows, its readers their columns. The
pruned network then needs a fine-tune, distilled from the unpruned one (docs/training.md,
"Pruning the shipped network").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from ..model.config import ModelConfig
from ..model.network import FrustumShapeNet
from ..model.pointnet import fuse_linear_bn

#: the prunable PointNets (child name) -> the model-config key holding their widths
PRUNABLE: dict[str, str] = {
    "seg_mlp": "seg_widths",
    "tnet_mlp": "tnet_widths",
    "box_mlp": "box_widths",
    "ctx_mlp": "box_context_widths",
    "box2_mlp": "box2_widths",
    "shape_mlp": "shape_widths",
    "shape_ctx_mlp": "shape_context_widths",
}


def readers(model: FrustumShapeNet) -> dict[str, list[tuple[str, int]]]:
    """Each prunable PointNet present in ``model`` -> the linear layers that read its pooled
    feature, each with the column where the feature starts in that layer's input (the
    concatenation orders of :meth:`FrustumShapeNet.forward`)."""
    nc = model.config.num_classes
    seg, box = model.seg_mlp.out_channels, model.box_mlp.out_channels
    out: dict[str, list[tuple[str, int]]] = {
        "seg_mlp": [("seg_head_global", 0), ("cls_head.body.0.linear", 0)],
        "tnet_mlp": [("tnet_head.body.0.linear", 0)],
        "box_mlp": [("box_head.body.0.linear", 0), ("shape_head.body.0.linear", 0), ("cls_head.body.0.linear", seg)],
        "shape_mlp": [("shape_head.body.0.linear", box + nc)],
    }
    if model.ctx_mlp is not None:
        out["ctx_mlp"] = [("box_head.body.0.linear", box + nc)]
    if model.box2_mlp is not None:
        out["box2_mlp"] = [("box2_head.body.0.linear", 0)]
        out["box_mlp"].append(("box2_head.body.0.linear", model.box2_mlp.out_channels))
    if model.shape_ctx_mlp is not None:
        out["shape_ctx_mlp"] = [("shape_head.body.0.linear", box + nc + model.shape_mlp.out_channels)]
    return out


def _reader_weight(model: FrustumShapeNet, name: str) -> torch.Tensor:
    """A reader's weight (out, in) with its BatchNorm's per-row scale applied where it has one."""
    linear = model.get_submodule(name)
    bn = model.seg_head_bn if name == "seg_head_global" else model.get_submodule(name.rsplit(".", 1)[0]).bn
    return (linear if bn is None else fuse_linear_bn(linear, bn)).weight.detach()


@torch.no_grad()
def channel_scores(model: FrustumShapeNet, points: np.ndarray, class_ids: np.ndarray,
                   batch: int = 100) -> dict[str, torch.Tensor]:
    """Score of every output channel of each prunable PointNet's last layer: its mean
    max-pooled activation over ``points`` (B, N, >=6; frame F, m) times the norm of the reader
    weights on it. Every other frustum gets its class id (``class_ids`` (B,), < 0 none) as
    the one-hot, the rest none, as the two passes see them."""
    model.eval()
    pooled: dict[str, list[torch.Tensor]] = {n: [] for n in readers(model)}

    def recording(n: str, forward_max):
        def run(*args, **kwargs):
            out = forward_max(*args, **kwargs)
            pooled[n].append(out[0] if isinstance(out, tuple) else out)
            return out
        return run

    for n in pooled:  # the pooled features, however the PointNet computes them (BatchNorm folded or not)
        mlp = getattr(model, n)
        mlp.forward_max = recording(n, mlp.forward_max)
    try:
        nc = model.config.num_classes
        for s in range(0, len(points), batch):
            pts = torch.as_tensor(np.asarray(points[s:s + batch])[..., :6], dtype=torch.float32)
            one_hot = torch.zeros(len(pts), nc)
            for j, c in enumerate(np.asarray(class_ids[s:s + batch])):
                if c >= 0 and (s + j) % 2 == 0:
                    one_hot[j, int(c)] = 1.0
            model(pts, one_hot, random_gather=False)
    finally:
        for n in pooled:
            del getattr(model, n).forward_max  # the class's method again
    scores = {}
    for n, reads in readers(model).items():
        act = torch.cat(pooled[n]).mean(0)
        sq = torch.zeros_like(act)
        for name, col in reads:
            sq += (_reader_weight(model, name)[:, col:col + act.numel()] ** 2).sum(0)
        scores[n] = act * sq.sqrt()
    return scores


def prune_network(model: FrustumShapeNet, widths: dict[str, int], scores: dict[str, torch.Tensor]) -> FrustumShapeNet:
    """A new network whose PointNets named in ``widths`` (keys of :data:`PRUNABLE`) keep that
    many last-layer channels, the best by ``scores`` (:func:`channel_scores`), in their
    original order; every other parameter is copied. ``model`` must not be BatchNorm-folded."""
    if getattr(model, "_fused", False):
        raise ValueError("prune the trained network, not its BatchNorm-folded inference copy")
    bad = sorted(set(widths) - set(PRUNABLE))
    if bad:
        raise ValueError(f"not prunable: {bad} (choose from {sorted(PRUNABLE)})")
    cfg = model.config.to_dict()
    keep: dict[str, torch.Tensor] = {}
    for n, w in widths.items():
        mlp = getattr(model, n)
        if mlp is None:
            raise ValueError(f"{n} is absent from this network")
        if not 0 < int(w) <= mlp.out_channels:
            raise ValueError(f"{n}: width {w} must be in 1..{mlp.out_channels}")
        keep[n] = torch.sort(torch.argsort(scores[n], descending=True)[: int(w)]).values
        cfg[PRUNABLE[n]] = list(cfg[PRUNABLE[n]][:-1]) + [int(w)]
    state = dict(model.state_dict())
    reads = readers(model)
    columns: dict[str, list[tuple[int, int, torch.Tensor]]] = {}
    for n, idx in keep.items():
        mlp = getattr(model, n)
        prefix = f"{n}.layers.{len(mlp.layers) - 1}."
        for key, t in state.items():
            if key.startswith(prefix) and t.dim() >= 1 and t.shape[0] == mlp.out_channels:
                state[key] = t[idx]
        for name, col in reads[n]:
            columns.setdefault(name, []).append((col, mlp.out_channels, idx))
    for name, parts in columns.items():
        w = state[name + ".weight"]
        mask = torch.ones(w.shape[1], dtype=torch.bool)
        for col, width, idx in parts:  # columns refer to the unpruned layout: one mask per reader
            sub = torch.zeros(width, dtype=torch.bool)
            sub[idx] = True
            mask[col:col + width] = sub
        state[name + ".weight"] = w[:, mask]
    out = FrustumShapeNet(ModelConfig.from_dict(cfg))
    out.load_state_dict(state)
    return out.eval()


def prune_on(model: FrustumShapeNet, sets: list[dict], widths: dict[str, int], frustums: int = 600,
             seed: int = 0) -> tuple[FrustumShapeNet, dict[str, torch.Tensor]]:
    """``model`` pruned to ``widths`` by channel scores over ``frustums`` frustums drawn from
    each frustum set in ``sets`` (training caches: ``points``, ``class_id``; seeded draw).
    Returns the pruned network and the scores."""
    rng = np.random.default_rng(seed)
    pts, cls = [], []
    for d in sets:
        idx = np.sort(rng.choice(len(d["class_id"]), min(frustums, len(d["class_id"])), replace=False))
        pts.append(d["points"][idx])
        cls.append(d["class_id"][idx])
    scores = channel_scores(model, np.concatenate(pts), np.concatenate(cls))
    return prune_network(model, widths, scores), scores


def pruned_meta(source_meta: dict | None, source: Path, widths: dict[str, int]) -> dict:
    """Meta of a pruned weights file: only the source's tasks carry over (its training record
    does not describe the pruned network), and where it was pruned from."""
    from ..digests import sha256_file

    return {"tasks": (source_meta or {}).get("tasks"),
            "pruned_from": {"path": str(source), "sha256": sha256_file(source), "widths": dict(widths)}}


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Options of ``shape-detector prune``."""
    p.add_argument("--out", required=True, help="pruned weights file to write")
    p.add_argument("--weights", default=None, help="weights to prune (default: the packaged ones)")
    p.add_argument("--data", nargs="+", required=True, help="frustum .npz files (training caches) to score channels on")
    p.add_argument("--frustums", type=int, default=600, help="frustums drawn from each file (default %(default)s)")
    p.add_argument("--width", action="append", default=[], metavar="NAME=W",
                   help=f"keep W channels of NAME's last layer (repeatable; {', '.join(PRUNABLE)})")
    p.add_argument("--seed", type=int, default=0, help="seed of the frustum draw (default %(default)s)")


def main(args: argparse.Namespace) -> int:
    """Score, prune and save; prints each layer's width and the share of the score it keeps."""
    from ..model.io import default_weights_path, load_weights, save_weights
    from .frustum_dataset import load

    widths: dict[str, int] = {}
    for item in args.width:
        name, _, w = item.partition("=")
        if not w.isdigit() or name not in PRUNABLE:
            print(f"--width {item!r}: expected NAME=W with NAME one of {', '.join(PRUNABLE)}", file=sys.stderr)
            return 2
        widths[name] = int(w)
    src = Path(args.weights) if args.weights else default_weights_path()
    model, meta = load_weights(src)
    pruned, scores = prune_on(model, [load(f) for f in args.data], widths, args.frustums, args.seed)
    for n, w in widths.items():
        s = scores[n]
        kept = torch.sort(s, descending=True).values[:w].sum() / s.sum()
        print(f"{n}: {s.numel()} -> {w} channels, {float(kept):.3f} of the score kept")
    before = sum(p.numel() for p in model.parameters())
    after = sum(p.numel() for p in pruned.parameters())
    print(f"parameters {before:,} -> {after:,}")
    save_weights(pruned, args.out, meta=pruned_meta(meta, src, widths))
    print(f"wrote {args.out}")
    return 0
