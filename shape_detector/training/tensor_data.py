"""A frustum dataset as tensors on one device, and its augmented training batches.

Augmentation (all in the frustum frame F): mirror x (heading -> pi - heading, the canonical
y of parts and surface samples flipped), random isotropic scale, point jitter (metres),
colour jitter, and the class one-hot dropped (zeros) with probability ``onehot_drop_prob``
(negatives get a random class one-hot when not dropped, like a wrong 2D detection).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from . import frustum_dataset as fds
from .config import TrainConfig

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
            dt = torch.float16 if k in ("points", "surface") else torch.float32
            t[k] = torch.as_tensor(np.ascontiguousarray(ds[k])).to(device=device, dtype=dt)
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
        if augment and cfg is not None:
            _augment(b, cfg, generator)
        B = idx.numel()
        cid, neg = b["class_id"], b["is_negative"]
        oh = torch.zeros(B, self.num_classes, device=self.device)
        if one_hot_mode == "train":
            drop_p = cfg.onehot_drop_prob if cfg is not None else 0.5
            rnd_cls = (_rand(generator, self.device, B) * self.num_classes).long().clamp_max(self.num_classes - 1)
            label = torch.where(neg, rnd_cls, cid.clamp_min(0))
            keep = _rand(generator, self.device, B) >= drop_p
            oh[keep, label[keep]] = 1.0
        elif one_hot_mode == "given":
            pos = ~neg
            oh[pos, cid[pos]] = 1.0
        b["one_hot"] = oh
        b["size_cluster"] = cid.clamp_min(0)
        b["seg"] = b["seg"].long()
        return b


def _rand(g: torch.Generator | None, dev: torch.device, *shape: int) -> torch.Tensor:
    return torch.rand(*shape, generator=g, device="cpu").to(dev)


def _augment(b: dict[str, torch.Tensor], cfg: TrainConfig, g: torch.Generator | None) -> None:
    """Mirror, scale and jitter the batch ``b`` in place (see the module docstring)."""
    pts = b["points"]
    B, dev = pts.shape[0], pts.device
    flip = _rand(g, dev, B) < cfg.mirror_prob
    if bool(flip.any()):
        sx = torch.where(flip, -1.0, 1.0).view(B, 1)
        pts[..., 0] = pts[..., 0] * sx
        b["center"][:, 0] = b["center"][:, 0] * sx[:, 0]
        b["heading"] = torch.where(flip, math.pi - b["heading"], b["heading"])
        b["parts_center"][..., 1] = b["parts_center"][..., 1] * sx
        b["surface"][..., 1] = b["surface"][..., 1] * sx
        D = torch.ones(B, 3, device=dev)
        D[:, 1] = sx[:, 0]
        b["parts_rotation"] = D.view(B, 1, 3, 1) * b["parts_rotation"] * D.view(B, 1, 1, 3)
    s = (cfg.scale_min + (cfg.scale_max - cfg.scale_min) * _rand(g, dev, B)).view(B, 1)
    pts[..., :3] = pts[..., :3] * s.unsqueeze(-1)
    b["center"] = b["center"] * s
    b["size"] = b["size"] * s
    for k in ("parts_center", "parts_size", "surface"):
        b[k] = b[k] * s.unsqueeze(-1)
    if cfg.point_jitter > 0:
        noise = torch.randn(pts.shape[0], pts.shape[1], 3, generator=g).to(dev)
        pts[..., :3] = pts[..., :3] + cfg.point_jitter * noise
    if cfg.color_jitter > 0:
        c = cfg.color_jitter
        gain = 1 + c * (2 * _rand(g, dev, B, 1, 1) - 1)
        bias = 0.5 * c * (2 * _rand(g, dev, B, 1, 3) - 1)
        pts[..., 3:6] = (pts[..., 3:6] * gain + bias).clamp(0, 1)
    b["points"] = pts


def shape_box_from_gt(
    b: dict[str, torch.Tensor], noise: Sequence[float] | None = None, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(centre (B,3), heading (B,), size (B,3)) of the GT boxes of a batch (frame F, metres,
    radians), optionally jittered by ``noise`` = (centre fraction of size, heading rad, size fraction)."""
    c, h, s = b["center"], b["heading"], b["size"]
    if noise is not None and any(float(v) > 0 for v in noise):
        B, dev = c.shape[0], c.device

        def n(*sh: int) -> torch.Tensor:
            return torch.randn(*sh, generator=generator).to(dev)

        c = c + float(noise[0]) * s * n(B, 3)
        h = h + float(noise[1]) * n(B)
        s = s * (1 + float(noise[2]) * n(B, 3)).clamp(0.7, 1.3)
    return c, h, s
