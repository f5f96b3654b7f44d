"""Batch helpers of :class:`~shape_detector.model.predictor.FrustumPredictor`: merging the
mirrored test-time augmentation's two passes, and stacking per-frustum features that are
numpy arrays (onnxruntime backend) or torch tensors (torch backend) without importing torch
for the former."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..geometry import stretch_cuboids, wrap_angle

#: the two passes of the mirrored test-time augmentation disagree about the box axes when
#: their headings differ by more than this modulo pi (radians); see :func:`merge_mirrored`
MIRROR_CONFLICT = np.pi / 4

_FLIP_Y = np.diag([1.0, -1.0, 1.0]).astype(np.float32)


def merge_mirrored(arr: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Merge the predictions on B frustums (first half of ``arr``, frame F) with those on the
    same frustums mirrored x -> -x (second half), as :meth:`FrustumPredictor.forward_arrays`
    arrays of batch 2B -> batch B.

    The mirrored centre gets its x negated and its heading ``t`` becomes ``pi - t``; its
    primitives (box-canonical) get their y negated. Class / segmentation probabilities are
    always averaged. The boxes:

    * headings within :data:`MIRROR_CONFLICT` of each other modulo pi: centres, sizes and
      headings are averaged (headings modulo pi when the two point opposite ways: the first
      prediction keeps the front); the primitives are the first prediction's, stretched to
      the averaged size;
    * otherwise the two passes disagree about the box axes (a box turned by ~90 degrees;
      sizes are not swapped to match, so it is not the same box), and the average would be
      a box ~45 degrees off both: the pass with the more confident heading bin
      (``heading_conf``) is kept whole.
    """
    n = arr["center"].shape[0] // 2
    a = {k: v[:n] for k, v in arr.items()}
    b = {k: v[n:] for k, v in arr.items()}
    out = dict(a)
    cb = b["center"].copy()
    cb[:, 0] *= -1.0
    hb = wrap_angle(np.pi - b["heading"])
    d = wrap_angle(hb - a["heading"])
    d = np.where(np.abs(d) > 0.5 * np.pi, wrap_angle(d + np.pi), d)  # opposite fronts: modulo pi
    conflict = np.abs(d) > MIRROR_CONFLICT
    take_b = conflict & (b["heading_conf"] > a["heading_conf"])
    keep_a = conflict & ~take_b
    out["center"] = np.where(take_b[:, None], cb, np.where(keep_a[:, None], a["center"], 0.5 * (a["center"] + cb)))
    out["heading"] = np.where(take_b, hb, wrap_angle(a["heading"] + np.where(conflict, 0.0, 0.5 * d))).astype(
        a["heading"].dtype
    )
    out["size"] = np.where(take_b[:, None], b["size"], np.where(keep_a[:, None], a["size"], 0.5 * (a["size"] + b["size"])))
    for key in ("probs", "seg_prob", "fg_score", "heading_conf"):
        out[key] = 0.5 * (a[key] + b[key])
    # primitives: the first prediction's, or the mirrored one's (y -> -y in the box frame) where it is kept
    base_c, base_s, base_r = a["prim_center"].copy(), a["prim_size"], a["prim_rotation"].copy()
    base_size = np.where(take_b[:, None], b["size"], a["size"])
    base_c[take_b] = b["prim_center"][take_b] * _FLIP_Y.diagonal()
    base_s = np.where(take_b[:, None, None], b["prim_size"], base_s)
    base_r[take_b] = _FLIP_Y @ b["prim_rotation"][take_b] @ _FLIP_Y
    ratio = out["size"] / np.maximum(base_size, 1e-9)  # (B, 3)
    out["prim_rotation"] = base_r
    out["prim_center"], out["prim_size"] = stretch_cuboids(base_c, base_s, base_r, ratio[:, None, :])
    return out


def repeat_first(x: Any, b: int) -> Any:
    """``x[:1]`` repeated ``b`` times along the batch axis (numpy array or torch tensor)."""
    if isinstance(x, np.ndarray):
        return np.repeat(x[:1], b, axis=0)
    return x[:1].expand(b, *x.shape[1:])


def stack(items: list[Any]) -> Any:
    """Stack per-frustum features (numpy arrays or torch tensors) along a new batch axis."""
    if all(isinstance(t, np.ndarray) for t in items):
        return np.stack(items)
    import torch

    return torch.stack([torch.as_tensor(t) for t in items])


def concat(items: list[Any]) -> Any:
    """Concatenate batch chunks (numpy arrays or torch tensors) along the batch axis."""
    if all(isinstance(t, np.ndarray) for t in items):
        return np.concatenate(items, 0)
    import torch

    return torch.cat([torch.as_tensor(t) for t in items], 0)
