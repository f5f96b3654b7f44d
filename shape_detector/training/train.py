"""Training loop of FrustumShapeNet (end-to-end multi-task, task flags for ablations).

:func:`train` takes frustum datasets (see :mod:`.frustum_dataset`), trains with Adam,
cosine (or step) LR decay and Frustum-PointNets-style BatchNorm momentum decay, validates
every epoch and writes to ``out_dir``::

    checkpoint.pt      resumable (model, optimiser, epoch, step, RNG, history, configs)
    weights.pt         last epoch, inference only (float16, temperature-calibrated)
    best.pt            best validation epoch, inference only (calibrated)
    log.csv, log.json  one row per epoch (train losses, val metrics, lr, time)
    loss_curve.png     train losses per logged step + validation metrics per epoch
    val_metrics.json   final validation metrics of best.pt and weights.pt + calibration

Everything runs on ``device`` (a GPU when available with ``--device auto``); the whole
dataset is held as tensors on that device and batches are augmented there:
mirror x in frame F (heading -> pi - heading, canonical y of parts/surface flipped),
random isotropic scale, point jitter, colour jitter, and the class one-hot dropped
(zeros) with probability ``onehot_drop_prob`` (negatives get a random class one-hot when
not dropped, like a wrong 2D detection).
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..evaluation.iou import box3d_iou
from ..geometry import rot_z
from ..model.config import ModelConfig
from ..model.io import load_checkpoint, load_weights, model_from_state, save_checkpoint, save_weights
from ..model.losses import ALL_TASKS, LossWeights, compute_losses, parse_tasks
from ..model.network import FrustumShapeNet
from ..model.pointnet import set_bn_momentum
from ..model.primitives import consistency_loss, coverage_loss, primitive_params, shape_iou_mc
from . import frustum_dataset as fds


@dataclass
class TrainConfig:
    model: dict = field(default_factory=dict)  # ModelConfig overrides
    data: dict = field(default_factory=dict)  # FrustumDatasetConfig overrides
    epochs: int = 12
    batch_size: int = 32
    lr: float = 2e-3
    lr_schedule: str = "cosine"  # "cosine" | "step"
    lr_min_frac: float = 0.02
    lr_step_epochs: int = 4
    lr_gamma: float = 0.5
    weight_decay: float = 0.0
    grad_clip: float = 10.0
    bn_momentum_init: float = 0.5
    bn_momentum_min: float = 0.01
    bn_decay_samples: int = 60000
    tasks: str = "box,shape,cls"
    loss_weights: dict = field(default_factory=dict)
    onehot_drop_prob: float = 0.5
    coverage_l_schedule: list = field(default_factory=lambda: [3, 2, 1])
    consistency_per_face: int = 25
    # noise on the GT box that canonicalises the shape branch's input while training:
    # centre (fraction of the size), heading (rad), size (fraction)
    shape_box_noise: list = field(default_factory=lambda: [0.05, 0.15, 0.08])
    # frame of the shape losses (model.losses.SHAPE_FRAMES): "gt_box", "predicted_box" (the
    # network's own box, as at inference) or "both" (their mean); with either of the last two the
    # shape branch's input is canonicalised by the network's own box too (no GT-box noise)
    shape_frame: str = "gt_box"
    mirror_prob: float = 0.5
    scale_min: float = 0.9
    scale_max: float = 1.1
    point_jitter: float = 0.005
    color_jitter: float = 0.1
    val_fraction: float = 0.1
    val_max_frustums: int = 3000
    val_batch_size: int = 128
    shape_iou_max: int = 600
    shape_iou_samples: int = 2048
    log_every: int = 25
    trainable: list[str] | None = None  # module-name prefixes to train (None = all); the rest frozen, BN in eval
    # module-name prefixes that start from a fresh initialisation instead of the --init weights
    # (re-initialising "shape_head" also allows a different primitive mapping than the init's)
    reinit: list[str] | None = None
    num_threads: int = 1  # 2 only on an idle machine: oversubscribed OpenMP threads are ~20x slower

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "TrainConfig":
        d = dict(d or {})
        if "train" in d:  # {"model": .., "data": .., "train": {..}} layout
            t = dict(d.pop("train"))
            t.update({k: v for k, v in d.items() if k in ("model", "data")})
            d = t
        names = set(cls.__dataclass_fields__)
        bad = set(d) - names - {"comment", "_comment"}
        if bad:
            raise ValueError(f"unknown training config keys: {sorted(bad)}")
        return cls(**{k: v for k, v in d.items() if k in names})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def model_config(self) -> ModelConfig:
        return ModelConfig.from_dict(self.model)


# --------------------------------------------------------------------------- data


_FLOAT_KEYS = ("points", "center", "size", "heading", "parts_center", "parts_size", "parts_rotation", "surface")


class TensorData:
    """A frustum dataset as tensors on one device (points kept in float16)."""

    def __init__(self, ds: dict[str, np.ndarray], device: torch.device, num_classes: int) -> None:
        self.n = fds.num_frustums(ds)
        self.device = device
        P = int(ds["parts_center"].shape[1])
        cnt = ds["parts_count"].astype(np.int64)
        parts_mask = np.arange(P)[None, :] < cnt[:, None]
        t: dict[str, torch.Tensor] = {}
        for k in _FLOAT_KEYS:
            a = ds[k]
            dt = torch.float16 if k in ("points", "surface") else torch.float32
            t[k] = torch.as_tensor(np.ascontiguousarray(a)).to(device=device, dtype=dt)
        t["seg"] = torch.as_tensor(ds["seg"].astype(np.uint8)).to(device)
        t["class_id"] = torch.as_tensor(ds["class_id"].astype(np.int64)).to(device)
        t["is_negative"] = torch.as_tensor(ds["is_negative"].astype(bool)).to(device)
        t["has_shape"] = torch.as_tensor(ds["has_shape"].astype(bool) & (cnt > 0)).to(device)
        t["parts_mask"] = torch.as_tensor(parts_mask).to(device)
        t["cls_label"] = torch.as_tensor(fds.cls_labels(ds, num_classes)).to(device)
        self.t = t
        self.num_classes = num_classes

    def batch(
        self,
        idx: torch.Tensor,
        cfg: TrainConfig | None = None,
        augment: bool = False,
        generator: torch.Generator | None = None,
        one_hot_mode: str = "train",
    ) -> dict[str, torch.Tensor]:
        """Batch ``idx`` as float32 tensors; ``one_hot_mode``: train (random drop),
        given (true class for positives, zeros for negatives) or none (all zeros)."""
        idx = idx.to(self.device)
        b = {k: v.index_select(0, idx) for k, v in self.t.items()}
        for k in ("points", "surface"):
            b[k] = b[k].float()
        B = idx.numel()
        dev = self.device
        g = generator

        def rand(*shape):
            return torch.rand(*shape, generator=g, device="cpu").to(dev)

        if augment and cfg is not None:
            pts = b["points"]
            # mirror x in F
            flip = rand(B) < cfg.mirror_prob
            if bool(flip.any()):
                sx = torch.where(flip, -1.0, 1.0).view(B, 1)
                pts[..., 0] = pts[..., 0] * sx
                b["center"][:, 0] = b["center"][:, 0] * sx[:, 0]
                b["heading"] = torch.where(flip, math.pi - b["heading"], b["heading"])
                b["parts_center"][..., 1] = b["parts_center"][..., 1] * sx
                b["surface"][..., 1] = b["surface"][..., 1] * sx
                D = torch.ones(B, 3, device=dev)
                D[:, 1] = sx[:, 0]
                R = b["parts_rotation"]
                b["parts_rotation"] = D.view(B, 1, 3, 1) * R * D.view(B, 1, 1, 3)
            # isotropic scale
            s = (cfg.scale_min + (cfg.scale_max - cfg.scale_min) * rand(B)).view(B, 1)
            pts[..., :3] = pts[..., :3] * s.unsqueeze(-1)
            b["center"] = b["center"] * s
            b["size"] = b["size"] * s
            b["parts_center"] = b["parts_center"] * s.unsqueeze(-1)
            b["parts_size"] = b["parts_size"] * s.unsqueeze(-1)
            b["surface"] = b["surface"] * s.unsqueeze(-1)
            if cfg.point_jitter > 0:
                noise = torch.randn(pts.shape[0], pts.shape[1], 3, generator=g).to(dev)
                pts[..., :3] = pts[..., :3] + cfg.point_jitter * noise
            if cfg.color_jitter > 0:
                c = cfg.color_jitter
                gain = 1 + c * (2 * rand(B, 1, 1) - 1)
                bias = 0.5 * c * (2 * rand(B, 1, 3) - 1)
                pts[..., 3:6] = (pts[..., 3:6] * gain + bias).clamp(0, 1)
            b["points"] = pts
        cid = b["class_id"]
        neg = b["is_negative"]
        oh = torch.zeros(B, self.num_classes, device=dev)
        if one_hot_mode == "train":
            drop_p = cfg.onehot_drop_prob if cfg is not None else 0.5
            rnd_cls = (rand(B) * self.num_classes).long().clamp_max(self.num_classes - 1)
            label = torch.where(neg, rnd_cls, cid.clamp_min(0))
            keep = rand(B) >= drop_p
            oh[keep, label[keep]] = 1.0
        elif one_hot_mode == "given":
            pos = ~neg
            oh[pos, cid[pos]] = 1.0
        b["one_hot"] = oh
        b["size_cluster"] = cid.clamp_min(0)
        b["seg"] = b["seg"].long()
        return b


# --------------------------------------------------------------------------- helpers


def shape_box_from_gt(b: dict[str, torch.Tensor], noise=None, generator: torch.Generator | None = None):
    """(centre, heading, size) of the GT boxes of a batch, optionally jittered."""
    c, h, s = b["center"], b["heading"], b["size"]
    if noise is not None and any(float(v) > 0 for v in noise):
        B, dev = c.shape[0], c.device
        n = lambda *sh: torch.randn(*sh, generator=generator).to(dev)  # noqa: E731
        c = c + float(noise[0]) * s * n(B, 3)
        h = h + float(noise[1]) * n(B)
        s = s * (1 + float(noise[2]) * n(B, 3)).clamp(0.7, 1.3)
    return c, h, s


def _lr_at(cfg: TrainConfig, step: int, total_steps: int, steps_per_epoch: int) -> float:
    if cfg.lr_schedule == "step":
        return cfg.lr * cfg.lr_gamma ** int(step / max(1, steps_per_epoch) // max(1, cfg.lr_step_epochs))
    p = min(1.0, step / max(1, total_steps))
    return cfg.lr * (cfg.lr_min_frac + (1 - cfg.lr_min_frac) * 0.5 * (1 + math.cos(math.pi * p)))


def _l_at(cfg: TrainConfig, progress: float) -> int:
    sched = list(cfg.coverage_l_schedule) or [1]
    return int(sched[min(int(progress * len(sched)), len(sched) - 1)])


def _bn_momentum(cfg: TrainConfig, samples: int) -> float:
    return max(cfg.bn_momentum_min, cfg.bn_momentum_init * 0.5 ** (samples / max(1, cfg.bn_decay_samples)))


def fit_temperature(logits: np.ndarray, labels: np.ndarray) -> float:
    """Temperature minimising the NLL of ``softmax(logits / T)`` (1D search, log-spaced)."""
    if len(labels) == 0:
        return 1.0
    lg = torch.as_tensor(logits, dtype=torch.float64)
    lb = torch.as_tensor(labels, dtype=torch.long)

    def nll(T: float) -> float:
        return float(torch.nn.functional.cross_entropy(lg / T, lb))

    grid = np.exp(np.linspace(np.log(0.05), np.log(20.0), 121))
    vals = [nll(T) for T in grid]
    i = int(np.argmin(vals))
    lo, hi = grid[max(0, i - 1)], grid[min(len(grid) - 1, i + 1)]
    fine = np.exp(np.linspace(np.log(lo), np.log(hi), 41))
    vals = [nll(T) for T in fine]
    return float(fine[int(np.argmin(vals))])


def calibration_stats(probs: np.ndarray, labels: np.ndarray, bins: int = 15) -> dict[str, float]:
    """Accuracy, NLL and expected calibration error (top-1 confidence, equal-width bins)."""
    if len(labels) == 0:
        return {"acc": float("nan"), "nll": float("nan"), "ece": float("nan")}
    conf = probs.max(1)
    pred = probs.argmax(1)
    correct = (pred == labels).astype(np.float64)
    edges = np.linspace(0, 1, bins + 1)
    ece = 0.0
    for i in range(bins):
        m = (conf > edges[i]) & (conf <= edges[i + 1])
        if m.any():
            ece += m.mean() * abs(correct[m].mean() - conf[m].mean())
    nll = float(-np.mean(np.log(np.clip(probs[np.arange(len(labels)), labels], 1e-12, 1))))
    return {"acc": float(correct.mean()), "nll": nll, "ece": float(ece)}


def _softmax_np(x: np.ndarray, T: float = 1.0) -> np.ndarray:
    z = x / T
    z = z - z.max(1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(1, keepdims=True)


def _box_iou_F(c1, s1, h1, c2, s2, h2) -> float:
    return box3d_iou(c1, s1, rot_z(float(h1)), c2, s2, rot_z(float(h2)), up=np.array([0.0, 0.0, 1.0]))


# --------------------------------------------------------------------------- validation


@torch.no_grad()
def evaluate(
    model: FrustumShapeNet,
    data: TensorData,
    cfg: TrainConfig,
    tasks,
    max_frustums: int | None = None,
    seed: int = 0,
) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Validation metrics (class-given and class-agnostic passes) and raw class logits."""
    tasks = parse_tasks(tasks)
    model.eval()
    mcfg = model.config
    n = data.n if not max_frustums else min(data.n, int(max_frustums))
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(data.n, generator=g)[:n] if n < data.n else torch.arange(n)
    nc = mcfg.num_classes
    ms = model.mean_sizes
    acc: dict[str, list] = {}

    def push(k, v):
        acc.setdefault(k, []).append(v.detach().float().cpu().numpy() if isinstance(v, torch.Tensor) else v)

    loss_sums: dict[str, float] = {}
    nb = 0
    shape_budget = cfg.shape_iou_max
    for s in range(0, n, cfg.val_batch_size):
        idx = order[s : s + cfg.val_batch_size]
        b = data.batch(idx, cfg, augment=False, one_hot_mode="given")
        out = model(b["points"], b["one_hot"], random_gather=False)
        L = compute_losses(out, b, ms, tasks, LossWeights.from_dict(cfg.loss_weights), 1, cfg.consistency_per_face,
                           mcfg.primitive_min_size_frac, mcfg.primitive_param, cfg.shape_frame)
        for k, v in L.items():
            if not k.startswith("stat_"):
                loss_sums[k] = loss_sums.get(k, 0.0) + float(v)
        nb += 1
        out_a = model(b["points"], torch.zeros_like(b["one_hot"]), random_gather=False)
        pos = ~b["is_negative"]
        push("neg", b["is_negative"])
        push("cls_label", b["cls_label"])
        push("logits_given", out["cls_logits"])
        push("logits_agn", out_a["cls_logits"])
        segp = out["seg_logits"].argmax(-1)
        push("seg_acc", (segp == b["seg"]).float().mean(1))
        inter = ((segp == 1) & (b["seg"] == 1)).float().sum(1)
        uni = ((segp == 1) | (b["seg"] == 1)).float().sum(1)
        push("seg_iou", torch.where(uni > 0, inter / uni.clamp_min(1), torch.ones_like(uni)))
        for tag, o in (("given", out), ("agn", out_a)):
            push(f"heading_{tag}", o["box_heading"])
            push(f"size_{tag}", o["box_size"])
            push(f"center_{tag}", o["center"])
        push("stage1", out["stage1_center"])
        push("gt_center", b["center"])
        push("gt_size", b["size"])
        push("gt_heading", b["heading"])
        # shape metrics, canonical frames normalised by the box diagonal:
        # "gtbox": shape branch and composition with the GT box (decoupled from box errors);
        # realistic: predicted box (class given), predicted primitives in the predicted box
        # frame vs GT parts in the GT box frame (like the evaluation's normalised frame).
        sh = pos & b["has_shape"]
        if "shape" in tasks and bool(sh.any()) and shape_budget > 0:
            ii = sh.nonzero().squeeze(1)[:shape_budget]
            shape_budget -= ii.numel()
            gg = g if data.device.type == "cpu" else None
            gs = b["size"][ii]
            gd = gs.norm(dim=1, keepdim=True)
            args = (b["parts_center"][ii] / gd.unsqueeze(1), b["parts_size"][ii] / gd.unsqueeze(1),
                    b["parts_rotation"][ii], b["parts_mask"][ii])
            out_s = model(b["points"], b["one_hot"], random_gather=False, shape_box=shape_box_from_gt(b))
            for tag, raw_s, bs_ in (("_gtbox", out_s["shape_raw"][ii], gs), ("", out["shape_raw"][ii], out["box_size"][ii])):
                prims = primitive_params(raw_s, bs_, **mcfg.primitive_kwargs())
                d = bs_.norm(dim=1, keepdim=True)
                prims = {"center": prims["center"] / d.unsqueeze(1), "size": prims["size"] / d.unsqueeze(1),
                         "rotation": prims["rotation"]}
                push("shape_iou" + tag, shape_iou_mc(prims, *args, num_samples=cfg.shape_iou_samples, generator=gg))
                push("cov_dist" + tag, coverage_loss(b["surface"][ii] / gd.unsqueeze(1), prims, 1).sqrt())
                push("cons_dist" + tag, consistency_loss(prims, *args, per_face=cfg.consistency_per_face).sqrt())
    cat = {k: np.concatenate([np.atleast_1d(x) for x in v]) for k, v in acc.items()}
    neg = cat["neg"].astype(bool)
    pos = ~neg
    m: dict[str, float] = {f"val_loss_{k}": v / max(1, nb) for k, v in loss_sums.items()}
    m["val_frustums"] = float(n)
    m["seg_acc"] = float(cat["seg_acc"].mean())
    m["seg_iou_pos"] = float(cat["seg_iou"][pos].mean()) if pos.any() else float("nan")
    if "box" in tasks and pos.any():
        gc, gsz, gh = cat["gt_center"][pos], cat["gt_size"][pos], cat["gt_heading"][pos]
        for tag in ("given", "agn"):
            c, sz, h = cat[f"center_{tag}"][pos], cat[f"size_{tag}"][pos], cat[f"heading_{tag}"][pos]
            ious = np.array([_box_iou_F(c[i], sz[i], h[i], gc[i], gsz[i], gh[i]) for i in range(len(c))])
            sfx = "" if tag == "given" else "_agnostic"
            m["box_iou" + sfx] = float(ious.mean())
            m["box_acc25" + sfx] = float((ious >= 0.25).mean())
            m["box_acc50" + sfx] = float((ious >= 0.5).mean())
            if tag == "given":
                m["center_err_median"] = float(np.median(np.linalg.norm(c - gc, axis=1)))
                m["center_err_mean"] = float(np.mean(np.linalg.norm(c - gc, axis=1)))
                dh = np.abs((h - gh + np.pi) % (2 * np.pi) - np.pi)
                m["heading_err_deg_median"] = float(np.degrees(np.median(dh)))
                m["heading_acc_30deg"] = float((dh < np.radians(30)).mean())
                dhs = np.abs((h - gh + np.pi / 2) % np.pi - np.pi / 2)
                m["heading_acc_30deg_mod180"] = float((dhs < np.radians(30)).mean())
                m["stage1_err_median"] = float(np.median(np.linalg.norm(cat["stage1"][pos] - gc, axis=1)))
                m["size_err_rel_mean"] = float(np.mean(np.abs(sz - gsz) / gsz))
    for tag in ("", "_gtbox"):
        if "shape_iou" + tag in cat:
            m["shape_iou" + tag] = float(cat["shape_iou" + tag].mean())
            m["shape_cov_dist" + tag] = float(cat["cov_dist" + tag].mean())
            m["shape_cons_dist" + tag] = float(cat["cons_dist" + tag].mean())
            m["shape_surface_dist" + tag] = 0.5 * (m["shape_cov_dist" + tag] + m["shape_cons_dist" + tag])
    labels = cat["cls_label"].astype(np.int64)
    if "cls" in tasks:
        for tag in ("agn", "given"):
            st = calibration_stats(_softmax_np(cat[f"logits_{tag}"]), labels)
            sfx = "_agnostic" if tag == "agn" else "_given"
            m["cls_acc" + sfx] = st["acc"]
            m["cls_ece" + sfx] = st["ece"]
            m["cls_nll" + sfx] = st["nll"]
        pa = _softmax_np(cat["logits_agn"])
        m["objectness_acc"] = float(((pa[:, nc] < 0.5) == pos).mean())
    m["select"] = _select_metric(m, tasks)
    raw = {"logits_agn": cat["logits_agn"], "logits_given": cat["logits_given"], "labels": labels}
    return m, raw


def _select_metric(m: dict[str, float], tasks) -> float:
    vals = []
    if "box" in tasks and "box_iou" in m:
        vals.append(m["box_iou"])
    if "shape" in tasks and "shape_iou_gtbox" in m:
        vals.append(m["shape_iou" if "box" in tasks else "shape_iou_gtbox"])
    if "cls" in tasks and "cls_acc_agnostic" in m:
        vals.append(0.5 * m["cls_acc_agnostic"])
    return float(np.mean(vals)) if vals else -m.get("val_loss_total", 0.0)


def calibrate(raw: dict[str, np.ndarray]) -> dict[str, Any]:
    """Fit the class-head temperature on validation logits (both one-hot modes)."""
    logits = np.concatenate([raw["logits_agn"], raw["logits_given"]])
    labels = np.concatenate([raw["labels"], raw["labels"]])
    T = fit_temperature(logits, labels)
    out: dict[str, Any] = {"temperature": T}
    for tag in ("agn", "given"):
        sfx = "agnostic" if tag == "agn" else "given"
        out[f"before_{sfx}"] = calibration_stats(_softmax_np(raw[f"logits_{tag}"]), raw["labels"])
        out[f"after_{sfx}"] = calibration_stats(_softmax_np(raw[f"logits_{tag}"], T), raw["labels"])
    return out


# --------------------------------------------------------------------------- plotting


def plot_curves(history: dict[str, Any], path: str | Path) -> None:
    """Loss curves (train, per logged step, log scale) and validation metrics per epoch (cv2)."""
    import cv2

    Wp, Hp, pad = 560, 360, 50
    img = np.full((Hp + 30, 2 * Wp, 3), 255, np.uint8)
    colors = [(200, 30, 30), (30, 140, 30), (30, 30, 200), (200, 130, 0), (150, 0, 150), (0, 150, 150),
              (90, 90, 90), (0, 90, 200), (200, 0, 90), (120, 60, 0), (0, 0, 0), (60, 160, 60)]

    def panel(x0, title, series, log_y):
        cv2.putText(img, title, (x0 + pad, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        L, T, R, B = x0 + pad, 30, x0 + Wp - 15, Hp - 20
        cv2.rectangle(img, (L, T), (R, B), (0, 0, 0), 1)
        pts = [(np.asarray(xs, float), np.asarray(ys, float)) for _, xs, ys in series]
        allx = np.concatenate([p[0] for p in pts]) if pts else np.zeros(0)
        ally = np.concatenate([p[1] for p in pts]) if pts else np.zeros(0)
        ok = np.isfinite(ally) & ((ally > 0) if log_y else True)
        if not ok.any():
            return
        tf = (lambda v: np.log10(np.maximum(v, 1e-6))) if log_y else (lambda v: v)
        ymin, ymax = float(tf(ally[ok]).min()), float(tf(ally[ok]).max())
        if ymax - ymin < 1e-6:
            ymax = ymin + 1
        xmin, xmax = float(allx.min()), float(allx.max())
        if xmax - xmin < 1e-9:
            xmax = xmin + 1
        for j in range(5):
            yv = ymin + (ymax - ymin) * j / 4
            yy = int(B - (B - T) * j / 4)
            lab = f"{10 ** yv:.3g}" if log_y else f"{yv:.2f}"
            cv2.putText(img, lab, (x0 + 2, yy + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (60, 60, 60), 1, cv2.LINE_AA)
            cv2.line(img, (L, yy), (R, yy), (225, 225, 225), 1)
        cv2.putText(img, f"{xmin:.0f}", (L, B + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (60, 60, 60), 1)
        cv2.putText(img, f"{xmax:.0f}", (R - 30, B + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (60, 60, 60), 1)
        for i, (name, xs, ys) in enumerate(series):
            xs, ys = np.asarray(xs, float), np.asarray(ys, float)
            good = np.isfinite(ys) & ((ys > 0) if log_y else True)
            xs, ys = xs[good], ys[good]
            col = colors[i % len(colors)]
            if len(xs) == 0:
                continue
            px = (L + (xs - xmin) / (xmax - xmin) * (R - L)).astype(np.int32)
            py = (B - (tf(ys) - ymin) / (ymax - ymin) * (B - T)).astype(np.int32)
            if len(px) > 1:
                cv2.polylines(img, [np.stack([px, py], 1).reshape(-1, 1, 2)], False, col, 1, cv2.LINE_AA)
            else:
                cv2.circle(img, (int(px[0]), int(py[0])), 3, col, -1)
            cv2.putText(img, name, (L + 8 + 130 * (i % 4), Hp + 2 + 12 * (i // 4)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.38, col, 1, cv2.LINE_AA)

    steps = history.get("steps", [])
    keys = ["total", "seg", "center", "corner", "heading_cls", "size_res", "box2_corner", "coverage", "consistency", "part",
            "volume", "occupancy", "cls"]
    series = []
    for k in keys:
        xs = [r["step"] for r in steps if k in r]
        if xs:
            series.append((k, xs, [r[k] for r in steps if k in r]))
    panel(0, "train losses (per logged step, log)", series, True)
    ep = history.get("epochs", [])
    vkeys = ["seg_acc", "box_iou", "box_acc25", "box_acc50", "box_iou_agnostic", "shape_iou", "shape_iou_gtbox",
             "cls_acc_agnostic",
             "heading_acc_30deg"]
    vs = []
    for k in vkeys:
        xs = [r["epoch"] for r in ep if k in r]
        if xs:
            vs.append((k, xs, [r[k] for r in ep if k in r]))
    panel(Wp, "validation (per epoch)", vs, False)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


# --------------------------------------------------------------------------- training


def _write_logs(out_dir: Path, history: dict[str, Any], meta: dict[str, Any]) -> None:
    rows = history.get("epochs", [])
    with open(out_dir / "log.json", "w") as f:
        json.dump({"meta": meta, "epochs": rows, "steps": history.get("steps", [])}, f, indent=1)
    if rows:
        keys: list[str] = []
        for r in rows:
            for k in r:
                if k not in keys:
                    keys.append(k)
        with open(out_dir / "log.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    try:
        plot_curves(history, out_dir / "loss_curve.png")
    except Exception as e:  # plotting must never kill a run
        print(f"warning: loss curve not written: {e}")


def _fmt_eta(sec: float) -> str:
    sec = max(0, int(sec))
    return f"{sec // 3600:d}:{sec % 3600 // 60:02d}:{sec % 60:02d}"


_SHAPE_MAPPING_KEYS = ("primitive_param", "primitive_min_size_frac")


def _load_init(model: FrustumShapeNet, init_model: FrustumShapeNet, reinit: list[str] | None) -> bool:
    """Copy ``init_model``'s parameters into ``model`` except those under the ``reinit``
    module-name prefixes, which keep their fresh initialisation. The model configs must be
    equal, except the primitive mapping when the shape head is re-initialised or gets its
    first class anchors (``model`` has ``shape_anchors``, ``init_model`` not), and the box
    context branch, second box stage or shape context branch when ``model`` adds them (all
    start as no-ops). Returns whether the class anchors came from ``init_model``."""
    prefixes = tuple(reinit or ())
    a, b = model.config.to_dict(), init_model.config.to_dict()
    new_anchors = model.shape_anchor is not None and init_model.shape_anchor is None
    new_context = model.ctx_mlp is not None and init_model.ctx_mlp is None
    new_box2 = model.box2_mlp is not None and init_model.box2_mlp is None
    new_shape_ctx = model.shape_ctx_mlp is not None and init_model.shape_ctx_mlp is None
    if new_anchors or any("shape_head".startswith(p) for p in prefixes):
        for k in _SHAPE_MAPPING_KEYS:
            a.pop(k), b.pop(k)
    if new_anchors:
        a.pop("shape_anchors"), b.pop("shape_anchors")
    if new_context:
        a.pop("box_context_widths"), b.pop("box_context_widths")
    if new_box2:
        for k in ("box2_widths", "box2_fc"):
            a.pop(k), b.pop(k)
    if new_shape_ctx:
        a.pop("shape_context_widths"), b.pop("shape_context_widths")
    if a != b:
        raise ValueError("--init: its model config differs from the training config's")

    def fresh(key: str) -> bool:
        return (
            (bool(prefixes) and key.startswith(prefixes))
            or (new_anchors and key == "shape_anchor")
            or (new_context and key.startswith("ctx_mlp."))
            or (new_box2 and key.startswith(("box2_mlp.", "box2_head.")))
            or (new_shape_ctx and key.startswith("shape_ctx_mlp."))
        )

    state = {k: v for k, v in init_model.state_dict().items() if not fresh(k)}
    # a new context feature enters its head's first layer (its first weight matrix: body.0,
    # or out without a body) as the last input columns, with zero weights, so the network
    # starts out computing exactly what ``init_model`` did
    for head, new in (("box_head.", new_context), ("shape_head.", new_shape_ctx)):
        if new:
            key = next(k for k, v in state.items() if k.startswith(head) and v.dim() == 2)
            w = torch.zeros_like(model.state_dict()[key])
            w[:, : state[key].shape[1]] = state[key]
            state[key] = w
    missing, unexpected = model.load_state_dict(state, strict=False)
    if unexpected or not all(fresh(k) for k in missing):
        raise ValueError(f"--init: parameters do not match (missing {missing}, unexpected {unexpected})")
    if prefixes and not any(k.startswith(prefixes) for k in missing):
        raise ValueError(f"reinit={list(prefixes)}: no parameter matches")
    return "shape_anchor" in state


@torch.no_grad()
def init_shape_anchors(model: FrustumShapeNet, ds: dict[str, np.ndarray], seed: int = 0) -> np.ndarray:
    """Set ``model.shape_anchor`` to the class templates of ``ds``'s GT parts
    (:func:`shape_detector.model.shape_anchors.class_templates`) and zero the shape head's
    output layer, so every object starts at its class template. Returns the per-class
    bool of classes found (the others keep zero anchors)."""
    from ..model.shape_anchors import class_templates, templates_to_raw

    cfg = model.config
    lo, hi, found = class_templates(
        ds["parts_center"], ds["parts_size"], ds["parts_rotation"],
        np.where(ds["has_shape"] & ~ds["is_negative"], ds["parts_count"], 0), ds["size"], ds["class_id"],
        cfg.num_classes, cfg.num_primitives, seed=seed,
    )
    raw = templates_to_raw(lo, hi, **cfg.primitive_kwargs()).reshape(cfg.num_classes, -1)
    raw[~found] = 0.0
    model.shape_anchor.copy_(torch.as_tensor(raw, dtype=model.shape_anchor.dtype))
    model.shape_head.out.weight.zero_()
    model.shape_head.out.bias.zero_()
    return found


def _class_path_frozen(trainable: list[str] | None) -> bool:
    """Whether a run training only the ``trainable`` prefixes leaves the class logits as they
    were (every prefix lies off the class path)."""
    return bool(trainable) and all(str(p).startswith(FrustumShapeNet.OFF_CLASS_PATH) for p in trainable)


def _freeze(model: torch.nn.Module, trainable: list[str] | None) -> list[torch.nn.Module]:
    """Freeze every parameter outside the ``trainable`` module-name prefixes; returns the
    frozen leaf modules (to keep in eval mode). None or empty: nothing frozen."""
    if not trainable:
        return []
    prefixes = tuple(trainable)
    for name, prm in model.named_parameters():
        prm.requires_grad_(name.startswith(prefixes))
    if not any(p.requires_grad for p in model.parameters()):
        raise ValueError(f"trainable={trainable}: no parameter matches")
    return [m for name, m in model.named_modules() if name and not name.startswith(prefixes)
            and not any(True for _ in m.children())]


def train(
    cfg: TrainConfig,
    train_ds: dict[str, np.ndarray],
    val_ds: dict[str, np.ndarray] | None,
    out_dir: str | Path,
    seed: int = 0,
    device: str | torch.device = "cpu",
    resume: bool = False,
    max_minutes: float | None = None,
    print_fn: Callable[[str], None] = print,
    extra_meta: dict[str, Any] | None = None,
    stop_after_epochs: int | None = None,
    init_weights: str | Path | None = None,
) -> dict[str, Any]:
    """Train (or resume) and return the final validation metrics (see module docstring).

    ``stop_after_epochs`` ends this call after that many epochs (counted in total, the LR
    schedule still planned for ``cfg.epochs``); ``resume=True`` continues from there.
    ``init_weights`` starts from a trained model (its model config must equal ``cfg``'s;
    ignored when resuming from a checkpoint).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    device = torch.device(device)
    if device.type == "cpu" and cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    tasks = parse_tasks(cfg.tasks)
    mcfg = cfg.model_config()
    weights = LossWeights.from_dict(cfg.loss_weights)
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    model = FrustumShapeNet(mcfg).to(device)
    ck_path = out_dir / "checkpoint.pt"
    resuming = resume and ck_path.is_file()
    anchors_ready = resuming
    # the heads the weights carry trained: this run's tasks plus, for a fine-tune, its init's
    # (a box-only fine-tune of a model with a class head still has that class head)
    weight_tasks = set(tasks)
    if init_weights is not None:
        init_model, init_meta = load_weights(init_weights, device)
        weight_tasks |= set(init_meta.get("tasks") or ALL_TASKS)
        if not resuming:
            anchors_ready = _load_init(model, init_model, cfg.reinit)
            print_fn(f"initialised from {init_weights}" + (f" except {cfg.reinit} (fresh)" if cfg.reinit else ""))
    if model.shape_anchor is not None and not anchors_ready:
        found = init_shape_anchors(model, train_ds, seed)
        print_fn(f"shape anchors: class templates of {int(found.sum())} classes; shape head output re-initialised")
    frozen = _freeze(model, cfg.trainable)
    if frozen:
        print_fn(f"training only {cfg.trainable}: {len(frozen)} modules frozen")
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr, weight_decay=cfg.weight_decay)
    tdata = TensorData(train_ds, device, mcfg.num_classes)
    vdata = TensorData(val_ds, device, mcfg.num_classes) if val_ds is not None and fds.num_frustums(val_ds) else None
    bs = int(cfg.batch_size)
    steps_per_epoch = max(1, tdata.n // bs)
    history: dict[str, Any] = {"epochs": [], "steps": []}
    start_epoch, step, planned_epochs = 0, 0, int(cfg.epochs)
    best, elapsed_before = -float("inf"), 0.0
    gen = torch.Generator()
    gen.manual_seed(seed)
    if resuming:
        ck = load_checkpoint(ck_path)
        model.load_state_dict(model_from_state(ck, device).state_dict())
        opt.load_state_dict(ck["optimizer"])
        start_epoch, step = int(ck["epoch"]), int(ck["step"])
        planned_epochs = int(ck.get("planned_epochs", cfg.epochs))
        if cfg.epochs != ck.get("train_config", {}).get("epochs", cfg.epochs):
            planned_epochs = int(cfg.epochs)
        history = ck.get("history", history)
        best = float(ck.get("best", best))
        elapsed_before = float(ck.get("elapsed_s", 0.0))
        torch.set_rng_state(ck["torch_rng"])
        gen.set_state(ck["gen_rng"])
        print_fn(f"resumed from {ck_path} at epoch {start_epoch} (step {step})")
    meta = {
        "tasks": sorted(weight_tasks),
        "seed": seed,
        "train_config": cfg.to_dict(),
        "model_config": mcfg.to_dict(),
        "train_frustums": tdata.n,
        "val_frustums": vdata.n if vdata else 0,
        "device": str(device),
        **(extra_meta or {}),
    }
    print_fn(
        f"training {model.num_parameters() / 1e6:.2f} M params on {device} "
        f"({torch.get_num_threads()} threads): {tdata.n} train / {vdata.n if vdata else 0} val frustums, "
        f"{steps_per_epoch} steps/epoch x {planned_epochs} epochs, tasks {','.join(sorted(tasks))}"
    )
    t_start = time.time()
    budget_s = max_minutes * 60.0 if max_minutes else None
    stopped_early = False
    epoch = start_epoch
    while epoch < planned_epochs:
        if stop_after_epochs is not None and epoch >= stop_after_epochs:
            break
        model.train()
        for m in frozen:
            m.eval()  # frozen BatchNorm keeps its statistics
        t_ep = time.time()
        perm = torch.randperm(tdata.n, generator=gen)
        run: dict[str, float] = {}
        run_n = 0
        ep_sums: dict[str, float] = {}
        for it in range(steps_per_epoch):
            total_steps = planned_epochs * steps_per_epoch
            lr = _lr_at(cfg, step, total_steps, steps_per_epoch)
            for grp in opt.param_groups:
                grp["lr"] = lr
            set_bn_momentum(model, _bn_momentum(cfg, step * bs))
            l_near = _l_at(cfg, step / max(1, total_steps))
            idx = perm[it * bs : (it + 1) * bs]
            b = tdata.batch(idx, cfg, augment=True, generator=gen, one_hot_mode="train")
            gt_frame = "shape" in tasks and cfg.shape_frame == "gt_box"
            sbox = shape_box_from_gt(b, cfg.shape_box_noise, gen) if gt_frame else None
            out = model(b["points"], b["one_hot"], shape_box=sbox)
            L = compute_losses(out, b, model.mean_sizes, tasks, weights, l_near, cfg.consistency_per_face,
                               mcfg.primitive_min_size_frac, mcfg.primitive_param, cfg.shape_frame)
            opt.zero_grad(set_to_none=True)
            L["total"].backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            step += 1
            for k, v in L.items():
                fv = float(v.detach())
                run[k] = run.get(k, 0.0) + fv
                ep_sums[k] = ep_sums.get(k, 0.0) + fv
            run_n += 1
            last = it == steps_per_epoch - 1
            if run_n >= cfg.log_every or last:
                avg = {k: v / run_n for k, v in run.items()}
                history["steps"].append({"step": step, "epoch": epoch + (it + 1) / steps_per_epoch, "lr": lr,
                                         **{k: round(v, 6) for k, v in avg.items() if not k.startswith("stat_")}})
                done = (it + 1) / steps_per_epoch
                spent = time.time() - t_ep
                eta = spent / done * (1 - done) + spent / done * (planned_epochs - epoch - 1)
                bar = "#" * int(done * 20) + "." * (20 - int(done * 20))
                parts = " ".join(f"{k} {v:.3f}" for k, v in avg.items() if k not in ("total",) and not k.startswith("stat_"))
                st = " ".join(f"{k[5:]} {v:.3f}" for k, v in avg.items() if k.startswith("stat_"))
                print_fn(
                    f"ep {epoch + 1}/{planned_epochs} [{bar}] {it + 1}/{steps_per_epoch} loss {avg['total']:.3f} "
                    f"({parts}) [{st}] lr {lr:.2e} l={l_near} {spent / (it + 1):.2f}s/it eta {_fmt_eta(eta)}"
                )
                run, run_n = {}, 0
            if budget_s is not None and (time.time() - t_start) > budget_s * 1.05 and not last:
                stopped_early = True
                break
        if stopped_early:
            print_fn("time budget exceeded mid-epoch; stopping (checkpoint keeps the last full epoch)")
            break
        epoch += 1
        t_train = time.time() - t_ep
        row: dict[str, Any] = {"epoch": epoch, "lr": lr, "train_s": round(t_train, 2)}
        row.update({"train_" + k: v / steps_per_epoch for k, v in ep_sums.items()})
        t_v = time.time()
        raw = None
        if vdata is not None:
            vm, raw = evaluate(model, vdata, cfg, tasks, cfg.val_max_frustums, seed=seed)
            row.update(vm)
        row["val_s"] = round(time.time() - t_v, 2)
        row["elapsed_s"] = round(elapsed_before + time.time() - t_start, 1)
        history["epochs"].append(row)
        sel = row.get("select", -row.get("train_total", 0.0))
        is_best = sel > best
        if is_best:
            best = sel
            save_weights(model, out_dir / "best.pt", meta={**meta, "epoch": epoch, "val": row})
        # time budget: plan the remaining epochs so the LR schedule still completes
        if budget_s is not None:
            used = time.time() - t_start
            per_epoch = used / max(1, epoch - start_epoch)
            can = epoch + int(max(0.0, budget_s - used) // per_epoch)
            if can < planned_epochs:
                planned_epochs = max(epoch, can)
                print_fn(f"time budget: planning {planned_epochs} epochs in total")
        save_checkpoint(
            ck_path, model, optimizer=opt.state_dict(), epoch=epoch, step=step, planned_epochs=planned_epochs,
            history=history, best=best, elapsed_s=elapsed_before + time.time() - t_start,
            torch_rng=torch.get_rng_state(), gen_rng=gen.get_state(), train_config=cfg.to_dict(), meta=meta,
        )
        save_weights(model, out_dir / "weights.pt", meta={**meta, "epoch": epoch, "val": row})
        _write_logs(out_dir, history, meta)
        summ = " ".join(
            f"{k} {row[k]:.3f}" for k in ("seg_acc", "box_iou", "box_acc25", "box_acc50", "box_iou_agnostic",
                                          "heading_acc_30deg", "shape_iou", "shape_iou_gtbox", "shape_surface_dist",
                                          "shape_surface_dist_gtbox", "cls_acc_agnostic", "cls_ece_agnostic") if k in row
        )
        print_fn(f"epoch {epoch}: train {t_train:.1f}s val {row['val_s']:.1f}s  {summ}{'  *best*' if is_best else ''}")

    # final: calibrate the class head of weights.pt and best.pt on the validation set
    final: dict[str, Any] = {"tasks": sorted(tasks), "epochs_done": epoch, "stopped_early": stopped_early}
    if vdata is not None and epoch > 0:
        for name in ("weights.pt", "best.pt"):
            p = out_dir / name
            if not p.is_file():
                continue
            m, wmeta = load_weights(p, device)
            vm, raw = evaluate(m, vdata, cfg, tasks, cfg.val_max_frustums, seed=seed)
            # without the class task, or when nothing the class logits depend on was trained,
            # the class head computes what it did: keep its temperature
            recal = "cls" in tasks and not _class_path_frozen(cfg.trainable)
            cal = calibrate(raw) if recal else {"temperature": float(m.cls_temperature), "kept": True}
            m.cls_temperature.fill_(float(cal["temperature"]))
            wmeta["calibration"] = cal
            wmeta["val"] = vm
            save_weights(m, p, meta=wmeta)
            final[name] = {"epoch": wmeta.get("epoch"), "metrics": vm, "calibration": cal}
        with open(out_dir / "val_metrics.json", "w") as f:
            json.dump(final, f, indent=1)
        if "best.pt" in final:
            cal = final["best.pt"]["calibration"]
            if "after_agnostic" in cal:
                print_fn(
                    f"calibration (best.pt): T = {cal['temperature']:.3f}; agnostic ECE "
                    f"{cal['before_agnostic']['ece']:.3f} -> {cal['after_agnostic']['ece']:.3f}, "
                    f"given ECE {cal['before_given']['ece']:.3f} -> {cal['after_given']['ece']:.3f}"
                )
    _write_logs(out_dir, history, meta)
    return final
