"""Multi-task losses of FrustumShapeNet (Frustum PointNets v1 + Tulsiani primitives + class).

All losses are computed in the frustum frame ``F`` (shape losses in the GT box's canonical
frame, primitives composed with the **GT** box size so shape learning is decoupled from
box errors). Task flags select the groups:

* always: instance segmentation cross-entropy (all frustums, negatives all background);
* ``box``: Huber on the stage-1 (T-Net) and final centre, heading-bin and size-cluster
  cross-entropy, Huber on the normalised residuals, corner loss (min over the GT box and
  its heading-flipped twin) -- positives only; with a second box stage in the network
  (``out["box2_res"]``) also its corner, centre, log-size and heading terms
  (``box2_*``, against the GT box turned by the quarter turn nearest the prediction);
* ``shape``: coverage (sum of the ``l`` smallest squared distances of GT surface samples to
  the primitives) and consistency (area-weighted squared distance of reparametrised
  primitive-surface samples to the union of GT parts) -- positives with shape GT only;
  plus three auxiliary terms (weight 0 = thesis-only losses): the supervised matched-part
  loss (``part``, :func:`shape_detector.model.primitives.matched_part_loss`), the
  volumetric consistency (``volume``, points sampled inside the primitives,
  :func:`shape_detector.model.primitives.volume_consistency_loss`) and a soft volumetric
  IoU (``occupancy``, :func:`shape_detector.model.primitives.occupancy_iou_loss`, default 0);
* ``cls``: cross-entropy of the classification head (classes + background), all frustums.

``batch`` keys (torch tensors, B = batch): ``seg`` (B,N) long, ``cls_label`` (B,) long
(``num_classes`` = background), ``is_negative`` (B,) bool, ``size_cluster`` (B,) long,
``center`` (B,3), ``size`` (B,3), ``heading`` (B,), ``has_shape`` (B,) bool,
``parts_center`` (B,P,3), ``parts_size`` (B,P,3), ``parts_rotation`` (B,P,3,3),
``parts_mask`` (B,P) bool, ``surface`` (B,S,3).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F

from .box_coder import box_corners_torch, decode_heading, decode_size, encode_heading, encode_size, gather_bin
from .primitives import (
    consistency_loss,
    coverage_loss,
    matched_part_loss,
    occupancy_iou_loss,
    primitive_params,
    volume_consistency_loss,
)


@dataclass
class LossWeights:
    """Weight of each loss term in the total (0 switches a term off); keys as in :func:`compute_losses`."""

    seg: float = 1.0
    center: float = 5.0  # Frustum PointNets uses 1 (KITTI scale); indoor errors are ~5x smaller
    stage1_center: float = 5.0
    heading_cls: float = 1.0
    heading_res: float = 20.0
    size_cls: float = 1.0
    size_res: float = 20.0
    corner: float = 10.0
    coverage: float = 10.0
    consistency: float = 30.0
    part: float = 30.0
    volume: float = 30.0
    occupancy: float = 0.0
    cls: float = 1.0
    box2_corner: float = 10.0
    box2_center: float = 5.0
    box2_size: float = 5.0
    box2_heading: float = 2.0
    # knowledge distillation (:func:`distillation_losses`; 0: off)
    distill_seg: float = 0.0
    distill_heading: float = 0.0
    distill_size: float = 0.0
    distill_cls: float = 0.0
    distill_box: float = 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> LossWeights:
        """Weights from a dict of overrides of the defaults; unknown keys are refused (ValueError)."""
        names = {f.name for f in fields(cls)}
        d = dict(d or {})
        bad = set(d) - names
        if bad:
            raise ValueError(f"unknown loss weights {sorted(bad)}")
        return cls(**{k: float(v) for k, v in d.items()})

    def to_dict(self) -> dict[str, float]:
        """All weights as a plain dict; :meth:`from_dict` reads it back."""
        return asdict(self)


ALL_TASKS = ("box", "shape", "cls")
#: frames the shape losses can compare primitives and GT parts in (see :func:`compute_losses`)
SHAPE_FRAMES = ("gt_box", "predicted_box", "both")


def parse_tasks(tasks) -> frozenset[str]:
    """``"box,shape,cls"`` / iterable -> frozenset, validated."""
    if isinstance(tasks, str):
        tasks = [t.strip() for t in tasks.split(",") if t.strip()]
    out = frozenset(tasks)
    bad = out - set(ALL_TASKS)
    if bad:
        raise ValueError(f"unknown tasks {sorted(bad)}; choose from {ALL_TASKS}")
    return out


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """Elementwise Huber of ``x`` (a residual or a norm), as in Frustum PointNets."""
    a = x.abs()
    q = torch.clamp(a, max=delta)
    return 0.5 * q * q + delta * (a - q)


def _masked_mean(v: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    mf = m.to(v.dtype)
    return (v * mf).sum() / mf.sum().clamp_min(1.0)


def _shape_terms(
    out: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    idx: torch.Tensor,
    frame: str,
    w: LossWeights,
    l_nearest: int,
    consistency_per_face: int,
    min_size_frac: float,
) -> dict[str, torch.Tensor]:
    """The weighted shape terms of the rows ``idx`` in one ``frame`` (see :func:`compute_losses`)."""
    raw = out["shape_raw"][idx]
    gsize = batch["size"][idx]
    # GT parts (canonical frame): centre, size, rotation, validity mask
    parts = (batch["parts_center"][idx], batch["parts_size"][idx], batch["parts_rotation"][idx],
             batch["parts_mask"][idx].bool())
    surface = batch["surface"][idx]
    if frame == "gt_box":
        prims = primitive_params(raw, gsize, min_size_frac)
        scale = gsize.norm(dim=1)
        occ_box = gsize
    else:
        psize = out["box_size"][idx].detach()
        pn = psize.norm(dim=1, keepdim=True).clamp_min(1e-6)
        gn = gsize.norm(dim=1, keepdim=True).clamp_min(1e-6)
        prims = primitive_params(raw, psize / pn, min_size_frac)
        g3 = gn.unsqueeze(-1)
        parts = (parts[0] / g3, parts[1] / g3, parts[2], parts[3])
        surface = surface / g3
        scale = torch.ones_like(gn.squeeze(1))
        occ_box = torch.maximum(psize / pn, gsize / gn)
    terms = {
        "coverage": w.coverage * coverage_loss(surface, prims, l_nearest, scale).mean(),
        "consistency": w.consistency * consistency_loss(prims, *parts, per_face=consistency_per_face, scale=scale).mean(),
    }
    if w.part > 0:
        terms["part"] = w.part * matched_part_loss(prims, *parts, scale=scale).mean()
    if w.volume > 0:
        terms["volume"] = w.volume * volume_consistency_loss(prims, *parts, scale=scale).mean()
    if w.occupancy > 0:
        terms["occupancy"] = w.occupancy * occupancy_iou_loss(prims, *parts, occ_box).mean()
    return terms


def aligned_gt_box(
    heading: torch.Tensor, gt_size: torch.Tensor, gt_heading: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The GT box re-parametrised by the quarter turn (about up) nearest the predicted
    ``heading`` (B,): the same solid, its heading within 45 degrees of the prediction, with
    length and width swapped after an odd number of quarter turns. Returns (size (B,3),
    heading (B,))."""
    k = torch.round((gt_heading - heading) / (0.5 * math.pi))
    h = gt_heading - k * (0.5 * math.pi)
    odd = (k.remainder(2) == 1).unsqueeze(1)
    size = torch.where(odd, gt_size[:, [1, 0, 2]], gt_size)
    return size, h


def _box2_terms(
    out: dict[str, torch.Tensor],
    gt_c: torch.Tensor,
    gt_s: torch.Tensor,
    gt_h: torch.Tensor,
    pos: torch.Tensor,
    w: LossWeights,
) -> dict[str, torch.Tensor]:
    """Losses of the second box stage (positives): Huber of the refined box's corner
    distances (mean over corners) to the GT box in the parametrisation nearest its heading
    (:func:`aligned_gt_box`), Huber of the centre distance, of the log size ratios and of the
    heading difference to that parametrisation."""
    c, h, s = out["center"], out["box_heading"], out["box_size"]
    a_s, a_h = aligned_gt_box(h.detach(), gt_s, gt_h)
    pc = box_corners_torch(c, s, h)
    gc = box_corners_torch(gt_c, a_s, a_h)
    corner = huber((pc - gc).norm(dim=2), 1.0).mean(1)
    center = huber((c - gt_c).norm(dim=1), 1.0)
    size = huber(torch.log(s / a_s.clamp_min(1e-3)), 1.0).sum(1)
    heading = huber(h - a_h, 1.0)
    return {
        "box2_corner": w.box2_corner * _masked_mean(corner, pos),
        "box2_center": w.box2_center * _masked_mean(center, pos),
        "box2_size": w.box2_size * _masked_mean(size, pos),
        "box2_heading": w.box2_heading * _masked_mean(heading, pos),
    }


def _box_terms(
    out: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    mean_sizes: torch.Tensor,
    pos: torch.Tensor,
    w: LossWeights,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Box losses of the positives ``pos`` (B,) bool (frame F, m / rad), in the order they
    add up, and the detached ``center_err`` / ``corner_dist`` (m) stats."""
    losses: dict[str, torch.Tensor] = {}
    stats: dict[str, torch.Tensor] = {}
    nh = out["heading_scores"].shape[1]
    gt_c, gt_s, gt_h = batch["center"], batch["size"], batch["heading"]
    scl = batch["size_cluster"].long().clamp_min(0)
    d1 = (out["stage1_center"] - gt_c).norm(dim=1)
    head_c = out.get("center_head", out["center"])
    d2 = (head_c - gt_c).norm(dim=1)
    losses["stage1_center"] = w.stage1_center * _masked_mean(huber(d1, 1.0), pos)
    losses["center"] = w.center * _masked_mean(huber(d2, 2.0), pos)
    hcls, hres = encode_heading(gt_h, nh)
    losses["heading_cls"] = w.heading_cls * _masked_mean(
        F.cross_entropy(out["heading_scores"], hcls, reduction="none"), pos
    )
    pred_hres = gather_bin(out["heading_res_norm"], hcls)
    losses["heading_res"] = w.heading_res * _masked_mean(huber(pred_hres - hres, 1.0), pos)
    losses["size_cls"] = w.size_cls * _masked_mean(
        F.cross_entropy(out["size_scores"], scl, reduction="none"), pos
    )
    sres = encode_size(gt_s, scl, mean_sizes)
    pred_sres = gather_bin(out["size_res_norm"], scl)
    losses["size_res"] = w.size_res * _masked_mean(huber((pred_sres - sres).norm(dim=1), 1.0), pos)
    # corner loss: predicted centre, heading from the GT bin + predicted residual, size
    # from the GT cluster + predicted residual; min over the GT box and its flip.
    ph = decode_heading(hcls, pred_hres, nh)
    ps = decode_size(scl, pred_sres, mean_sizes)
    pc = box_corners_torch(head_c, ps, ph)
    gc = box_corners_torch(gt_c, gt_s, gt_h)
    gcf = box_corners_torch(gt_c, gt_s, gt_h + math.pi)
    dc = torch.minimum((pc - gc).norm(dim=2).mean(1), (pc - gcf).norm(dim=2).mean(1))
    # Frustum PointNets: huber of each corner distance; mean over corners
    dcc = torch.minimum(
        huber((pc - gc).norm(dim=2), 1.0).mean(1), huber((pc - gcf).norm(dim=2), 1.0).mean(1)
    )
    losses["corner"] = w.corner * _masked_mean(dcc, pos)
    with torch.no_grad():
        stats["center_err"] = _masked_mean(d2, pos)
        stats["corner_dist"] = _masked_mean(dc, pos)
    if "box2_res" in out:
        losses.update(_box2_terms(out, gt_c, gt_s, gt_h, pos, w))
    return losses, stats


def _soft_kl(student: torch.Tensor, teacher: torch.Tensor, temperature: float) -> torch.Tensor:
    """Per-row KL divergence (teacher || student) of logits (..., C) softened by
    ``temperature``, times its square (gradients keep their scale as it changes)."""
    t = temperature
    kl = F.kl_div(F.log_softmax(student / t, dim=-1), F.log_softmax(teacher / t, dim=-1), reduction="none",
                  log_target=True)
    return kl.sum(-1) * (t * t)


def distillation_losses(
    out: dict[str, torch.Tensor],
    teacher: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    weights: LossWeights,
    temperature: float = 2.0,
) -> dict[str, torch.Tensor]:
    """Knowledge-distillation terms (each only when its weight is above 0): the softened KL
    of the teacher's segmentation (all points), heading-bin and size-cluster scores
    (positives) and class logits (all frustums), and ``distill_box``: Huber of the distance
    of the final box's centre (m), its log size ratios and its heading difference (rad) to
    the teacher's box in the parametrisation nearest it (:func:`aligned_gt_box`;
    positives). ``teacher``: the outputs of a trained network on the same batch (no
    gradients)."""
    w = weights
    pos = ~batch["is_negative"].bool()
    terms: dict[str, torch.Tensor] = {}
    if w.distill_seg > 0:
        terms["distill_seg"] = w.distill_seg * _soft_kl(out["seg_logits"], teacher["seg_logits"], temperature).mean()
    if w.distill_cls > 0:
        terms["distill_cls"] = w.distill_cls * _soft_kl(out["cls_logits"], teacher["cls_logits"], temperature).mean()
    if not bool(pos.any()):
        return terms
    if w.distill_heading > 0:
        kl = _soft_kl(out["heading_scores"], teacher["heading_scores"], temperature)
        terms["distill_heading"] = w.distill_heading * _masked_mean(kl, pos)
    if w.distill_size > 0:
        kl = _soft_kl(out["size_scores"], teacher["size_scores"], temperature)
        terms["distill_size"] = w.distill_size * _masked_mean(kl, pos)
    if w.distill_box > 0:  # the teacher's box in the parametrisation nearest the student's
        a_s, a_h = aligned_gt_box(out["box_heading"].detach(), teacher["box_size"], teacher["box_heading"])
        dc = huber((out["center"] - teacher["center"]).norm(dim=1), 1.0)
        ds = huber(torch.log(out["box_size"].clamp_min(1e-3) / a_s.clamp_min(1e-3)), 1.0).sum(1)
        terms["distill_box"] = w.distill_box * _masked_mean(dc + ds + huber(out["box_heading"] - a_h, 1.0), pos)
    return terms


def compute_losses(
    out: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    mean_sizes: torch.Tensor,
    tasks=ALL_TASKS,
    weights: LossWeights | None = None,
    l_nearest: int = 1,
    consistency_per_face: int = 25,
    min_size_frac: float = 0.01,
    shape_frame: str = "gt_box",
) -> dict[str, torch.Tensor]:
    """Weighted loss terms, their sum under ``"total"``, and a few detached accuracies.

    ``shape_frame``: where the shape losses compare primitives and GT parts.
    ``"gt_box"``: both in the GT box's canonical frame, the primitives composed with the GT
    box size (shape learning decoupled from box errors). ``"predicted_box"``: as the
    object-frame shape metric and inference see them: the primitives composed with the
    network's own (detached) box size and scaled to unit box diagonal, the GT parts in the
    GT box's frame scaled the same way by the GT box; the head learns to place parts where
    they fall in the box it will be given, box errors included. ``"both"``: the mean of the
    two."""
    if shape_frame not in SHAPE_FRAMES:
        raise ValueError(f"shape_frame must be one of {SHAPE_FRAMES}, not {shape_frame!r}")
    tasks = parse_tasks(tasks)
    w = weights or LossWeights()
    losses: dict[str, torch.Tensor] = {}
    stats: dict[str, torch.Tensor] = {}
    seg_logits = out["seg_logits"]
    seg = batch["seg"].long()
    losses["seg"] = w.seg * F.cross_entropy(seg_logits.reshape(-1, 2), seg.reshape(-1))
    with torch.no_grad():
        stats["seg_acc"] = (seg_logits.argmax(-1) == seg).float().mean()

    pos = ~batch["is_negative"].bool()
    any_pos = bool(pos.any())
    if "box" in tasks and any_pos:
        box_losses, box_stats = _box_terms(out, batch, mean_sizes, pos, w)
        losses.update(box_losses)
        stats.update(box_stats)

    if "shape" in tasks:
        sh = pos & batch["has_shape"].bool()
        if bool(sh.any()):
            idx = sh.nonzero().squeeze(1)
            frames = ("gt_box", "predicted_box") if shape_frame == "both" else (shape_frame,)
            for frame in frames:
                terms = _shape_terms(out, batch, idx, frame, w, l_nearest, consistency_per_face, min_size_frac)
                for k, v in terms.items():
                    losses[k] = losses.get(k, 0.0) + v / len(frames)

    if "cls" in tasks:
        cl = batch["cls_label"].long()
        losses["cls"] = w.cls * F.cross_entropy(out["cls_logits"], cl)
        with torch.no_grad():
            stats["cls_acc"] = (out["cls_logits"].argmax(1) == cl).float().mean()

    total = sum(losses.values())
    result = dict(losses)
    result["total"] = total  # type: ignore[assignment]
    for k, v in stats.items():
        result["stat_" + k] = v
    return result
