"""The proposal classifier's inputs (pure numpy, no torch): configuration, per-point and
per-candidate features (see :mod:`shape_detector.model.classifier`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from ..classes import NUM_CLASSES

#: per-point inputs: dx, dy (m, horizontal, about the foreground mean), height above the
#: floor (m), r, g, b in [0, 1], first-pass foreground probability
POINT_CHANNELS = 7
#: per-candidate inputs, in this order (see :func:`candidate_inputs`)
GLOBAL_FEATURES = (
    [f"logp_{i}" for i in range(NUM_CLASSES + 1)]
    + ["size_l", "size_w", "size_h", "bottom", "top", "floor_known", "range", "fg_share", "log_valid"]
    + ["box_w", "box_h", "cut_left", "cut_right", "cut_top", "cut_bottom", "proposal_score"]
)


@dataclass
class ClassifierConfig:
    """``num_points``: points per candidate the PointNet sees (a random subset of the
    frustum's while training, evenly spaced ones at inference); ``widths``: the per-point
    MLP (max-pooled); ``fc``: the head's hidden layers;
    ``prior_height``: camera height above the floor (m) assumed when no floor is measured
    (the generator's cameras stand 0.8-1.8 m high); ``border_px``: a 2D box edge within
    this many pixels of the image border counts as cut."""

    num_points: int = 256
    widths: tuple[int, ...] = (64, 128, 256)
    fc: tuple[int, ...] = (256, 128)
    dropout: float = 0.3
    num_classes: int = NUM_CLASSES
    prior_height: float = 1.3
    border_px: float = 3.0

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples as lists); :meth:`from_dict` reads it back."""
        d = asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> ClassifierConfig:
        """Config from a dict of overrides of the defaults; unknown keys are refused (ValueError)."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown ClassifierConfig keys: {sorted(unknown)}")
        for k in ("widths", "fc"):
            if k in d:
                d[k] = tuple(int(x) for x in d[k])
        return cls(**d)


def candidate_inputs(
    points: np.ndarray,
    seg_prob: np.ndarray,
    center_F: np.ndarray,
    size: np.ndarray,
    class_probs: np.ndarray,
    valid: np.ndarray,
    boxes2d: np.ndarray,
    proposal_score: np.ndarray,
    image_size: tuple[int, int],
    floor_height: float | None,
    config: ClassifierConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Classifier inputs of B candidates of one frame: ``(points (B,N,7), globals (B,G))``
    float32.

    ``points`` (B,N,>=6) frustum points, frame F (x, y horizontal, z up from the camera,
    metres) + rgb in [0, 1]; ``seg_prob`` (B,N) the first pass's foreground probability;
    ``center_F`` (B,3), ``size`` (B,3) its box (frame F, metres); ``class_probs`` (B,C+1)
    its calibrated class probabilities (background last); ``valid`` (B,) valid pixels in
    each 2D box; ``boxes2d`` (B,4) pixel edges; ``proposal_score`` (B,); ``image_size``
    ``(width, height)``; ``floor_height`` the camera's height above the floor (m), None =
    not measured (then ``config.prior_height`` is used and ``floor_known`` is 0).
    """
    cfg = config or ClassifierConfig()
    pts = np.asarray(points, np.float32)
    B, N = pts.shape[:2]
    seg = np.asarray(seg_prob, np.float32).reshape(B, N)
    known = floor_height is not None and np.isfinite(floor_height)
    h0 = np.float32(floor_height if known else cfg.prior_height)
    fg = seg > 0.5
    none = ~fg.any(1)
    fg[none] = True  # no foreground: centre on all points
    w = fg.astype(np.float32)
    mean_xy = (pts[..., :2] * w[..., None]).sum(1) / w.sum(1, keepdims=True)
    out = np.empty((B, N, POINT_CHANNELS), np.float32)
    out[..., :2] = pts[..., :2] - mean_xy[:, None, :]
    out[..., 2] = pts[..., 2] + h0
    out[..., 3:6] = pts[..., 3:6]
    out[..., 6] = seg
    c = np.asarray(center_F, np.float32).reshape(B, 3)
    s = np.asarray(size, np.float32).reshape(B, 3)
    W, H = float(image_size[0]), float(image_size[1])
    b2 = np.asarray(boxes2d, np.float32).reshape(B, 4)
    bp = cfg.border_px
    g = np.concatenate(
        [
            np.log(np.clip(np.asarray(class_probs, np.float32).reshape(B, -1), 1e-4, 1.0)),
            s,
            (c[:, 2] - 0.5 * s[:, 2] + h0)[:, None],
            (c[:, 2] + 0.5 * s[:, 2] + h0)[:, None],
            np.full((B, 1), 1.0 if known else 0.0, np.float32),
            np.linalg.norm(c[:, :2], axis=1, keepdims=True),
            (seg > 0.5).mean(1, keepdims=True),
            (np.log1p(np.asarray(valid, np.float32).reshape(B, 1)) / 10.0),
            ((b2[:, 2] - b2[:, 0]) / W)[:, None],
            ((b2[:, 3] - b2[:, 1]) / H)[:, None],
            (b2[:, 0:1] <= bp).astype(np.float32),
            (b2[:, 2:3] >= W - bp).astype(np.float32),
            (b2[:, 1:2] <= bp).astype(np.float32),
            (b2[:, 3:4] >= H - bp).astype(np.float32),
            np.asarray(proposal_score, np.float32).reshape(B, 1),
        ],
        axis=1,
    )
    return out, g.astype(np.float32)


def subsample_points(points: np.ndarray, num_points: int) -> np.ndarray:
    """``num_points`` evenly spaced points per candidate of ``points`` (B,N,C) where N is
    larger; float32."""
    points = np.asarray(points, np.float32)
    n = points.shape[1]
    if n > num_points:
        points = points[:, np.linspace(0, n - 1, num_points).round().astype(np.int64)]
    return points


def frame_inputs(
    frustums: Sequence[Any], preds: Sequence[Any], boxes2d: Sequence[Sequence[float]], scores: Sequence[float],
    image_size: tuple[int, int], floor_height: float | None, config: ClassifierConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`candidate_inputs` from :class:`~shape_detector.frustum.Frustum` objects and
    their first-pass :class:`~shape_detector.model.predictor.FrustumPrediction`\\ s."""
    return candidate_inputs(
        np.stack([f.points[:, :6] for f in frustums]),
        np.stack([p.seg_prob for p in preds]),
        np.stack([p.center_F for p in preds]),
        np.stack([p.size for p in preds]),
        np.stack([p.class_probs for p in preds]),
        np.array([f.valid for f in frustums]),
        np.array([list(b)[:4] for b in boxes2d], np.float32),
        np.array(scores, np.float32),
        image_size,
        floor_height,
        config,
    )
