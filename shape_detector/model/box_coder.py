"""Heading-bin / size-cluster encoding of amodal boxes and box corners, in torch.

Boxes live in the frustum frame ``F`` (z up): centre (3,), size ``(l, w, h)`` and a
yaw ``heading`` (rad) of the box's x axis.

* heading: ``NH`` bins of width ``2 pi / NH`` centred on ``k * 2 pi / NH``; the residual
  to the bin centre is normalised by half the bin width (so it lies in [-1, 1]).
* size: ``NS`` clusters = the class mean sizes; the residual is normalised by the
  cluster mean, ``(size - mean) / mean``.

Box-head output layout (last axis): ``centre(3) | heading scores(NH) | heading
residuals(NH) | size scores(NS) | size residuals(NS*3)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..geometry import CORNER_SIGNS

# same corner order as shape_detector.geometry.box_corners
_CORNER_SIGNS = torch.from_numpy(CORNER_SIGNS).float()


def box_head_channels(nh: int, ns: int) -> int:
    """Width of the box-head output for ``nh`` heading bins and ``ns`` size clusters: 3 + 2NH + 4NS."""
    return 3 + 2 * nh + 4 * ns


def split_box_head(out: torch.Tensor, nh: int, ns: int) -> dict[str, torch.Tensor]:
    """Slice the raw box-head output (B, 3+2NH+4NS) into named tensors."""
    i = 0
    center = out[:, i : i + 3]
    i += 3
    heading_scores = out[:, i : i + nh]
    i += nh
    heading_res = out[:, i : i + nh]
    i += nh
    size_scores = out[:, i : i + ns]
    i += ns
    size_res = out[:, i : i + 3 * ns].reshape(-1, ns, 3)
    return {
        "center_res": center,
        "heading_scores": heading_scores,
        "heading_res_norm": heading_res,
        "size_scores": size_scores,
        "size_res_norm": size_res,
    }


def wrap_2pi(a):
    """Angle(s) wrapped to [0, 2 pi)."""
    if isinstance(a, torch.Tensor):
        return torch.remainder(a, 2 * math.pi)
    return np.remainder(a, 2 * np.pi)


def encode_heading(angle, nh: int):
    """``angle`` (rad, any range) -> (bin index, residual normalised to [-1, 1])."""
    apc = 2 * math.pi / nh
    shifted = wrap_2pi(angle + apc / 2)
    if isinstance(shifted, torch.Tensor):
        cls = torch.clamp(torch.floor(shifted / apc).long(), 0, nh - 1)
        res = shifted - (cls.to(shifted.dtype) * apc + apc / 2)
    else:
        cls = np.clip(np.floor(shifted / apc).astype(np.int64), 0, nh - 1)
        res = shifted - (cls * apc + apc / 2)
    return cls, res / (apc / 2)


def decode_heading(cls, res_norm, nh: int):
    """Inverse of :func:`encode_heading`; returns angles in (-pi, pi]."""
    apc = 2 * math.pi / nh
    if isinstance(res_norm, torch.Tensor):
        a = cls.to(res_norm.dtype) * apc + res_norm * (apc / 2)
        return torch.atan2(torch.sin(a), torch.cos(a))
    a = np.asarray(cls) * apc + np.asarray(res_norm) * (apc / 2)
    return np.arctan2(np.sin(a), np.cos(a))


def encode_size(size, cluster, mean_sizes):
    """Residual ``(size - mean[cluster]) / mean[cluster]`` (same type as ``size``)."""
    if isinstance(size, torch.Tensor):
        m = torch.as_tensor(mean_sizes, dtype=size.dtype, device=size.device)[cluster]
    else:
        m = np.asarray(mean_sizes, dtype=np.float64)[np.asarray(cluster)]
    return (size - m) / m


def decode_size(cluster, res_norm, mean_sizes):
    """Inverse of :func:`encode_size`."""
    if isinstance(res_norm, torch.Tensor):
        m = torch.as_tensor(mean_sizes, dtype=res_norm.dtype, device=res_norm.device)[cluster]
    else:
        m = np.asarray(mean_sizes, dtype=np.float64)[np.asarray(cluster)]
    return m * (1 + res_norm)


def rot_z_torch(theta: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations about +z."""
    c, s = torch.cos(theta), torch.sin(theta)
    z, o = torch.zeros_like(theta), torch.ones_like(theta)
    return torch.stack(
        [torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2
    )


def box_corners_torch(center: torch.Tensor, size: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Corners (B, 8, 3) of yaw-only boxes (centre (B,3), size (B,3), heading (B,))."""
    signs = _CORNER_SIGNS.to(device=center.device, dtype=center.dtype)
    local = signs.unsqueeze(0) * (0.5 * size).unsqueeze(1)  # (B,8,3)
    R = rot_z_torch(heading)  # (B,3,3)
    return local @ R.transpose(1, 2) + center.unsqueeze(1)


def gather_bin(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``t[b, idx[b]]`` for ``t`` (B, K) or (B, K, D)."""
    if t.dim() == 2:
        return t.gather(1, idx.view(-1, 1)).squeeze(1)
    return t.gather(1, idx.view(-1, 1, 1).expand(-1, 1, t.shape[2])).squeeze(1)


def decode_boxes(
    center: torch.Tensor,
    heads: dict[str, torch.Tensor],
    mean_sizes,
    size_cluster: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Final boxes from the head outputs: argmax heading bin, size cluster (argmax of the
    size scores unless ``size_cluster`` (B,) long is given, e.g. the known class)."""
    nh = heads["heading_scores"].shape[1]
    hcls = heads["heading_scores"].argmax(1)
    heading = decode_heading(hcls, gather_bin(heads["heading_res_norm"], hcls), nh)
    scls = heads["size_scores"].argmax(1) if size_cluster is None else size_cluster
    size = decode_size(scls, gather_bin(heads["size_res_norm"], scls), mean_sizes)
    return {"center": center, "heading": heading, "size": size, "heading_bin": hcls, "size_cluster": scls}
