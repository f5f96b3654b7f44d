"""Proposal classifier: a second, dedicated opinion on what a class-agnostic frustum holds.

The frustum network's class head sees the frustum's points relative to the camera and the
features its segmentation and box branches learned; it knows nothing of the floor, the 2D
box or the proposer. On the built-in proposals it confuses neighbouring classes (desk /
table / chair, dresser / night stand) and scores background (clutter on a table, wall
remnants, pieces of objects) too high: with the true class given to every detection the
validation mAP@0.25 rises from 69 to 80.

:class:`ProposalClassifier` re-scores each candidate after the network's first pass with

* the frustum's points (frame ``F``, see :mod:`shape_detector.frustum`), centred
  horizontally on the first pass's foreground points, with their **height above the
  measured floor** instead of the height relative to the camera, their colour, and the
  first pass's foreground probability (``POINT_CHANNELS`` = 7), through a small PointNet;
* per-candidate cues (``GLOBAL_FEATURES``): the first pass's log class probabilities, its
  box size, the box's bottom and top above the floor, the range, the foreground share,
  the 2D box's size and whether it is cut by the image border, and the proposer's score.

Its output is ``num_classes + 1`` logits (background last), temperature-scaled like the
network's. All inputs are built by :func:`candidate_inputs`, pure numpy.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from ..classes import NUM_CLASSES
from .pointnet import FCHead, SharedMLP
from .traced import TracedModule

CLASSIFIER_FORMAT = "shape_detector.proposal_classifier.v1"

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
        d = asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "ClassifierConfig":
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


class ProposalClassifier(nn.Module):
    """PointNet over :data:`POINT_CHANNELS` per-point inputs, max-pooled, concatenated with
    the :data:`GLOBAL_FEATURES`, and an FC head: ``num_classes + 1`` logits."""

    def __init__(self, config: ClassifierConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or ClassifierConfig()
        n_global = len(GLOBAL_FEATURES)
        self.point_mlp = SharedMLP(POINT_CHANNELS, cfg.widths)
        self.global_bn = nn.BatchNorm1d(n_global)
        self.head = FCHead(self.point_mlp.out_channels + n_global, cfg.fc, cfg.num_classes + 1, dropout=cfg.dropout)
        self.register_buffer("temperature", torch.tensor(1.0))

    def forward(self, points: torch.Tensor, globals_: torch.Tensor) -> torch.Tensor:
        """``points`` (B,N,7), ``globals_`` (B,G) -> logits (B, num_classes + 1), untempered."""
        feat = self.point_mlp.forward_max(points)
        return self.head(torch.cat([feat, self.global_bn(globals_)], 1))

    @torch.no_grad()
    def fuse_batchnorm(self) -> "ProposalClassifier":
        """Fold the BatchNorm of every per-point and head layer into its linear layer (eval
        mode only; the module can no longer be trained or saved as weights): 25 candidates
        10.6 -> 4.7 ms on one thread, logits within 1e-4."""
        from .pointnet import PointLinear

        if self.training:
            raise RuntimeError("fuse_batchnorm() is for eval mode only")
        for m in self.modules():
            if isinstance(m, PointLinear):
                m.fuse_batchnorm()
        return self

    def calibrated(self, points: torch.Tensor, globals_: torch.Tensor) -> tuple[torch.Tensor]:
        """``(probabilities (B, num_classes + 1),)``: the temperature-scaled softmax of
        :meth:`forward`, in float32 (a one-tuple, as :class:`~.traced.TracedModule` runs it)."""
        return (torch.softmax(self(points, globals_).float() / self.temperature.clamp_min(1e-3), 1),)

    @torch.inference_mode()
    def probabilities(self, points: np.ndarray, globals_: np.ndarray) -> np.ndarray:
        """Calibrated probabilities (B, num_classes + 1), background last (eval mode), of
        :func:`candidate_inputs`' arrays; ``config.num_points`` evenly spaced points are
        used."""
        if len(points) == 0:
            return np.zeros((0, self.config.num_classes + 1), np.float64)
        pts, g = _as_inputs(points, globals_, self.config.num_points)
        return self.calibrated(pts, g)[0].double().numpy()


def _as_inputs(points: np.ndarray, globals_: np.ndarray, num_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """float32 tensors of :func:`candidate_inputs`' arrays, with ``num_points`` evenly spaced
    points per candidate where it has more."""
    n = points.shape[1]
    if n > num_points:
        points = points[:, np.linspace(0, n - 1, num_points).round().astype(np.int64)]
    return torch.as_tensor(points, dtype=torch.float32), torch.as_tensor(globals_, dtype=torch.float32)


class _Calibrated(nn.Module):
    def __init__(self, model: ProposalClassifier) -> None:
        super().__init__()
        self.model = model

    def forward(self, points: torch.Tensor, globals_: torch.Tensor) -> tuple[torch.Tensor]:
        return self.model.calibrated(points, globals_)


class ClassifierPredictor:
    """Inference with a loaded :class:`ProposalClassifier`, as
    :class:`~shape_detector.model.predictor.FrustumPredictor` runs the network: BatchNorm
    folded, frozen TorchScript graphs (``trace``: less overhead, no GIL held while they run),
    and bfloat16 for batches from the predictor's threshold on under ``precision``
    (``"auto"``: 4 or more candidates on a CPU with AMX). Same :meth:`probabilities` as the
    classifier; ``model`` is folded in place (eval mode; it can no longer be trained)."""

    def __init__(self, model: ProposalClassifier, precision: str = "fp32", trace: bool = True) -> None:
        from .predictor import bf16_min_batch

        self.model = model.eval().fuse_batchnorm()
        self.precision = precision
        self.bf16_min_batch = bf16_min_batch(precision, torch.device("cpu"))
        self._run = TracedModule(_Calibrated(self.model), enabled=trace)

    @property
    def config(self) -> ClassifierConfig:
        return self.model.config

    def warm_up(self, max_batch: int = 1) -> None:
        """Trace the graphs and build the kernels for every batch of 1 to ``max_batch``
        candidates now (see :meth:`FrustumPredictor.warm_up
        <shape_detector.model.predictor.FrustumPredictor.warm_up>`)."""
        n, g = self.config.num_points, len(GLOBAL_FEATURES)
        for b in range(1, max(1, int(max_batch)) + 1):
            self.probabilities(np.zeros((b, n, POINT_CHANNELS), np.float32), np.zeros((b, g), np.float32))

    @torch.inference_mode()
    def probabilities(self, points: np.ndarray, globals_: np.ndarray) -> np.ndarray:
        """As :meth:`ProposalClassifier.probabilities`."""
        if len(points) == 0:
            return np.zeros((0, self.config.num_classes + 1), np.float64)
        pts, g = _as_inputs(points, globals_, self.config.num_points)
        bf16 = self.bf16_min_batch is not None and len(pts) >= self.bf16_min_batch
        return self._run(pts, g, bf16=bf16)[0].double().numpy()


def save_classifier(model: ProposalClassifier, path, meta: dict[str, Any] | None = None) -> None:
    """A self-describing weights file (float16 floats) for :func:`load_classifier`."""
    from .io import _atomic_save

    sd = {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu()).clone()
          for k, v in model.state_dict().items()}
    _atomic_save({"format": CLASSIFIER_FORMAT, "config": model.config.to_dict(), "state_dict": sd,
                  "meta": dict(meta or {})}, path)


def load_classifier(path) -> tuple[ProposalClassifier, dict[str, Any]]:
    """``(classifier in eval mode, meta)`` from :func:`save_classifier`'s file."""
    blob = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(blob, dict) or blob.get("format") != CLASSIFIER_FORMAT:
        raise ValueError(f"{path}: not a shape_detector proposal-classifier file")
    model = ProposalClassifier(ClassifierConfig.from_dict(blob["config"]))
    model.load_state_dict({k: (v.float() if v.is_floating_point() else v) for k, v in blob["state_dict"].items()})
    return model.eval(), dict(blob.get("meta", {}))


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
