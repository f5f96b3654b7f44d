"""Training hyper-parameters of one run (one recipe phase): :class:`TrainConfig`."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from ..model.config import ModelConfig


@dataclass
class TrainConfig:
    """Everything that decides what a training run computes (no wall-clock settings).

    ``model``: :class:`~shape_detector.model.config.ModelConfig` overrides; ``data``:
    :class:`~shape_detector.training.frustum_dataset.FrustumDatasetConfig` overrides.
    ``batch_size`` is the global batch: with several processes each takes its share of it.
    ``trainable`` / ``reinit``: network parts by name (groups of
    ``FrustumShapeNet.MODULE_GROUPS`` or exact child names); None trains everything.
    """

    model: dict = field(default_factory=dict)
    data: dict = field(default_factory=dict)
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
    random_gather: bool = True  # random foreground subsets while training (False: evenly spread)
    val_fraction: float = 0.1
    val_max_frustums: int = 3000
    val_batch_size: int = 128
    shape_iou_max: int = 600
    shape_iou_samples: int = 2048
    log_every: int = 25
    trainable: list[str] | None = None
    reinit: list[str] | None = None
    num_threads: int = 1  # 2 only on an idle machine: oversubscribed OpenMP threads are ~20x slower
    # knowledge distillation: a trained network ("default": the packaged weights) whose outputs
    # the trained one also learns, by the loss weights ``distill_*`` (model.losses.distillation_losses)
    teacher: str | None = None
    distill_temperature: float = 2.0

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> TrainConfig:
        """Config from overrides of the defaults; unknown keys are refused."""
        d = dict(d or {})
        names = set(cls.__dataclass_fields__)
        bad = set(d) - names - {"comment", "_comment"}
        if bad:
            raise ValueError(f"unknown training config keys: {sorted(bad)}")
        return cls(**{k: v for k, v in d.items() if k in names})

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every field."""
        return asdict(self)

    def model_config(self) -> ModelConfig:
        """The network this run trains."""
        return ModelConfig.from_dict(self.model)
