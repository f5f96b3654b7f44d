"""Validation metrics of a FrustumShapeNet on a frustum dataset (class-given and
class-agnostic passes), and the model-selection metric."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..box_iou import box3d_iou
from ..geometry import rot_z
from ..model.losses import LossWeights, compute_losses, parse_tasks
from ..model.network import FrustumShapeNet
from ..model.primitives import consistency_loss, coverage_loss, primitive_params, shape_iou_mc
from .calibration import calibration_stats, softmax_np
from .config import TrainConfig
from .tensor_data import TensorData, shape_box_from_gt


class _Acc:
    """Per-frustum arrays collected over validation batches."""

    def __init__(self) -> None:
        self.d: dict[str, list] = {}

    def push(self, k: str, v: Any) -> None:
        self.d.setdefault(k, []).append(v.detach().float().cpu().numpy() if isinstance(v, torch.Tensor) else v)

    def cat(self) -> dict[str, np.ndarray]:
        return {k: np.concatenate([np.atleast_1d(x) for x in v]) for k, v in self.d.items()}


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
    n = data.n if not max_frustums else min(data.n, int(max_frustums))
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(data.n, generator=g)[:n] if n < data.n else torch.arange(n)
    acc = _Acc()
    loss_sums: dict[str, float] = {}
    nb = 0
    budget = [cfg.shape_iou_max]
    for s in range(0, n, cfg.val_batch_size):
        b = data.batch(order[s : s + cfg.val_batch_size], cfg, augment=False, one_hot_mode="given")
        out = model(b["points"], b["one_hot"], random_gather=False)
        L = compute_losses(out, b, model.mean_sizes, tasks, LossWeights.from_dict(cfg.loss_weights), 1,
                           cfg.consistency_per_face, model.config.primitive_min_size_frac, cfg.shape_frame)
        for k, v in L.items():
            if not k.startswith("stat_"):
                loss_sums[k] = loss_sums.get(k, 0.0) + float(v)
        nb += 1
        _push_batch(model, b, out, acc)
        if "shape" in tasks and budget[0] > 0:
            _push_shape(model, b, out, cfg, acc, budget, g if data.device.type == "cpu" else None)
    cat = acc.cat()
    m: dict[str, float] = {f"val_loss_{k}": v / max(1, nb) for k, v in loss_sums.items()}
    m["val_frustums"] = float(n)
    pos = ~cat["neg"].astype(bool)
    m["seg_acc"] = float(cat["seg_acc"].mean())
    m["seg_iou_pos"] = float(cat["seg_iou"][pos].mean()) if pos.any() else float("nan")
    if "box" in tasks and pos.any():
        m.update(_box_metrics(cat, pos))
    m.update(_shape_metrics(cat))
    labels = cat["cls_label"].astype(np.int64)
    if "cls" in tasks:
        m.update(_cls_metrics(cat, labels, pos, model.config.num_classes))
    m["select"] = select_metric(m, tasks)
    raw = {"logits_agn": cat["logits_agn"], "logits_given": cat["logits_given"], "labels": labels}
    return m, raw


def _push_batch(model: FrustumShapeNet, b: dict[str, torch.Tensor], out: dict[str, torch.Tensor], acc: _Acc) -> None:
    out_a = model(b["points"], torch.zeros_like(b["one_hot"]), random_gather=False)
    acc.push("neg", b["is_negative"])
    acc.push("cls_label", b["cls_label"])
    acc.push("logits_given", out["cls_logits"])
    acc.push("logits_agn", out_a["cls_logits"])
    segp = out["seg_logits"].argmax(-1)
    acc.push("seg_acc", (segp == b["seg"]).float().mean(1))
    inter = ((segp == 1) & (b["seg"] == 1)).float().sum(1)
    uni = ((segp == 1) | (b["seg"] == 1)).float().sum(1)
    acc.push("seg_iou", torch.where(uni > 0, inter / uni.clamp_min(1), torch.ones_like(uni)))
    for tag, o in (("given", out), ("agn", out_a)):
        acc.push(f"heading_{tag}", o["box_heading"])
        acc.push(f"size_{tag}", o["box_size"])
        acc.push(f"center_{tag}", o["center"])
    acc.push("stage1", out["stage1_center"])
    acc.push("gt_center", b["center"])
    acc.push("gt_size", b["size"])
    acc.push("gt_heading", b["heading"])


def _push_shape(model: FrustumShapeNet, b: dict[str, torch.Tensor], out: dict[str, torch.Tensor],
                cfg: TrainConfig, acc: _Acc, budget: list[int], g: torch.Generator | None) -> None:
    """Shape metrics in canonical frames normalised by the box diagonal: ``_gtbox`` with the
    GT box (decoupled from box errors); plain: predicted primitives in the predicted box's
    frame against the GT parts in the GT box's frame (as the evaluation's normalised frame)."""
    sh = ~b["is_negative"] & b["has_shape"]
    if not bool(sh.any()):
        return
    ii = sh.nonzero().squeeze(1)[: budget[0]]
    budget[0] -= ii.numel()
    gs = b["size"][ii]
    gd = gs.norm(dim=1, keepdim=True)
    args = (b["parts_center"][ii] / gd.unsqueeze(1), b["parts_size"][ii] / gd.unsqueeze(1),
            b["parts_rotation"][ii], b["parts_mask"][ii])
    out_s = model(b["points"], b["one_hot"], random_gather=False, shape_box=shape_box_from_gt(b))
    for tag, raw_s, bs_ in (("_gtbox", out_s["shape_raw"][ii], gs), ("", out["shape_raw"][ii], out["box_size"][ii])):
        prims = primitive_params(raw_s, bs_, **model.config.primitive_kwargs())
        d = bs_.norm(dim=1, keepdim=True)
        prims = {"center": prims["center"] / d.unsqueeze(1), "size": prims["size"] / d.unsqueeze(1),
                 "rotation": prims["rotation"]}
        acc.push("shape_iou" + tag, shape_iou_mc(prims, *args, num_samples=cfg.shape_iou_samples, generator=g))
        acc.push("cov_dist" + tag, coverage_loss(b["surface"][ii] / gd.unsqueeze(1), prims, 1).sqrt())
        acc.push("cons_dist" + tag, consistency_loss(prims, *args, per_face=cfg.consistency_per_face).sqrt())


def _box_iou_F(c1, s1, h1, c2, s2, h2) -> float:
    return box3d_iou(c1, s1, rot_z(float(h1)), c2, s2, rot_z(float(h2)), up=np.array([0.0, 0.0, 1.0]))


def _box_metrics(cat: dict[str, np.ndarray], pos: np.ndarray) -> dict[str, float]:
    m: dict[str, float] = {}
    gc, gsz, gh = cat["gt_center"][pos], cat["gt_size"][pos], cat["gt_heading"][pos]
    for tag in ("given", "agn"):
        c, sz, h = cat[f"center_{tag}"][pos], cat[f"size_{tag}"][pos], cat[f"heading_{tag}"][pos]
        ious = np.array([_box_iou_F(c[i], sz[i], h[i], gc[i], gsz[i], gh[i]) for i in range(len(c))])
        sfx = "" if tag == "given" else "_agnostic"
        m["box_iou" + sfx] = float(ious.mean())
        m["box_acc25" + sfx] = float((ious >= 0.25).mean())
        m["box_acc50" + sfx] = float((ious >= 0.5).mean())
        if tag != "given":
            continue
        err = np.linalg.norm(c - gc, axis=1)
        m["center_err_median"] = float(np.median(err))
        m["center_err_mean"] = float(np.mean(err))
        dh = np.abs((h - gh + np.pi) % (2 * np.pi) - np.pi)
        m["heading_err_deg_median"] = float(np.degrees(np.median(dh)))
        m["heading_acc_30deg"] = float((dh < np.radians(30)).mean())
        dhs = np.abs((h - gh + np.pi / 2) % np.pi - np.pi / 2)
        m["heading_acc_30deg_mod180"] = float((dhs < np.radians(30)).mean())
        m["stage1_err_median"] = float(np.median(np.linalg.norm(cat["stage1"][pos] - gc, axis=1)))
        m["size_err_rel_mean"] = float(np.mean(np.abs(sz - gsz) / gsz))
    return m


def _shape_metrics(cat: dict[str, np.ndarray]) -> dict[str, float]:
    m: dict[str, float] = {}
    for tag in ("", "_gtbox"):
        if "shape_iou" + tag in cat:
            m["shape_iou" + tag] = float(cat["shape_iou" + tag].mean())
            m["shape_cov_dist" + tag] = float(cat["cov_dist" + tag].mean())
            m["shape_cons_dist" + tag] = float(cat["cons_dist" + tag].mean())
            m["shape_surface_dist" + tag] = 0.5 * (m["shape_cov_dist" + tag] + m["shape_cons_dist" + tag])
    return m


def _cls_metrics(cat: dict[str, np.ndarray], labels: np.ndarray, pos: np.ndarray, nc: int) -> dict[str, float]:
    m: dict[str, float] = {}
    for tag in ("agn", "given"):
        st = calibration_stats(softmax_np(cat[f"logits_{tag}"]), labels)
        sfx = "_agnostic" if tag == "agn" else "_given"
        m["cls_acc" + sfx] = st["acc"]
        m["cls_ece" + sfx] = st["ece"]
        m["cls_nll" + sfx] = st["nll"]
    pa = softmax_np(cat["logits_agn"])
    m["objectness_acc"] = float(((pa[:, nc] < 0.5) == pos).mean())
    return m


def select_metric(m: dict[str, float], tasks) -> float:
    """The model-selection metric (higher is better) of validation metrics ``m``."""
    vals = []
    if "box" in tasks and "box_iou" in m:
        vals.append(m["box_iou"])
    if "shape" in tasks and "shape_iou_gtbox" in m:
        vals.append(m["shape_iou" if "box" in tasks else "shape_iou_gtbox"])
    if "cls" in tasks and "cls_acc_agnostic" in m:
        vals.append(0.5 * m["cls_acc_agnostic"])
    return float(np.mean(vals)) if vals else -m.get("val_loss_total", 0.0)
