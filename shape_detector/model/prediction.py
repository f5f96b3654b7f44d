"""What the frustum network predicts for one frustum (:class:`FrustumPrediction`) and the
score of a class-agnostic detection after its class-given second pass."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..types import Cuboid


@dataclass
class FrustumPrediction:
    """Network output for one frustum; 3D quantities in the **camera** frame (metres).

    ``class_probs`` (num_classes+1,), background last; ``rotation`` columns = box axes
    (z column = gravity-up); ``primitives`` camera-frame cuboids after pruning;
    ``primitives_canonical`` the same in the canonical object frame (box centre, x =
    heading, z up, metres) for composing with another box (e.g. the GT one);
    ``seg_prob`` (N,) foreground probability of each frustum point; ``center_F`` /
    ``heading_F`` the box in the frustum frame. ``seg_features``: the network's
    class-independent segmentation features of this frustum (torch tensors, only with
    ``predict(..., keep_features=True)``), which let :meth:`FrustumPredictor.refine` skip the
    segmentation PointNet.
    """

    class_name: str
    class_probs: np.ndarray
    score: float
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    heading_U: float
    primitives: list[Cuboid]
    seg_prob: np.ndarray
    num_points_valid: int
    objectness: float = 0.0
    center_F: np.ndarray = field(default_factory=lambda: np.zeros(3))
    heading_F: float = 0.0
    primitives_canonical: list[Cuboid] = field(default_factory=list)
    seg_features: tuple[Any, Any] | None = field(default=None, repr=False, compare=False)


def refined_score(class_prob: float, objectness: float) -> float:
    """Score of a class-agnostic detection after its class-given second pass
    (:meth:`FrustumPredictor.refine`): the geometric mean of the first pass's probability of
    its class and the second pass's objectness (1 - background probability, given that
    class)."""
    return float(np.sqrt(max(class_prob, 0.0) * max(objectness, 0.0)))
