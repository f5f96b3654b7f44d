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

from typing import Any

import numpy as np
import torch
from torch import nn

from .classifier_inputs import (  # noqa: F401 - re-exported: the numpy half lives there, torch-free
    GLOBAL_FEATURES,
    POINT_CHANNELS,
    ClassifierConfig,
    candidate_inputs,
    frame_inputs,
    subsample_points,
)
from .pointnet import FCHead, SharedMLP

CLASSIFIER_FORMAT = "shape_detector.proposal_classifier.v1"


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
    def fuse_batchnorm(self) -> ProposalClassifier:
        """Fold the BatchNorm of every per-point and head layer into its linear layer (eval
        mode only; the module can no longer be trained or saved as weights); logits agree with
        the unfolded module to about 1e-4."""
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
    points = subsample_points(points, num_points)
    return torch.as_tensor(points, dtype=torch.float32), torch.as_tensor(globals_, dtype=torch.float32)


class _Calibrated(nn.Module):
    def __init__(self, model: ProposalClassifier) -> None:
        super().__init__()
        self.model = model

    def forward(self, points: torch.Tensor, globals_: torch.Tensor) -> tuple[torch.Tensor]:
        return self.model.calibrated(points, globals_)


def save_classifier(model: ProposalClassifier, path, meta: dict[str, Any] | None = None,
                    provenance: dict[str, Any] | None = None) -> None:
    """A self-describing, versioned weights file (float16 floats, plain types only) for
    :func:`load_classifier`; ``provenance`` as in :mod:`shape_detector.training.provenance`."""
    from .io import WEIGHTS_VERSION, atomic_save, half_state, plain

    atomic_save({"format": CLASSIFIER_FORMAT, "version": WEIGHTS_VERSION, "config": model.config.to_dict(),
                 "state_dict": half_state(model), "meta": plain(dict(meta or {})),
                 "provenance": plain(dict(provenance or {}))}, path)


def load_classifier(path) -> tuple[ProposalClassifier, dict[str, Any]]:
    """``(classifier in eval mode, meta)`` from :func:`save_classifier`'s file."""
    from .io import WEIGHTS_VERSION, read_blob

    blob = read_blob(path)
    if blob.get("format") != CLASSIFIER_FORMAT or blob.get("version") != WEIGHTS_VERSION:
        raise ValueError(f"{path}: not a version-{WEIGHTS_VERSION} shape_detector proposal-classifier file")
    model = ProposalClassifier(ClassifierConfig.from_dict(blob["config"]))
    model.load_state_dict({k: (v.float() if v.is_floating_point() else v) for k, v in blob["state_dict"].items()})
    return model.eval(), dict(blob.get("meta", {}))


from .classifier_runtime import ClassifierPredictor  # noqa: E402,F401 - re-exported (torch-free module)
