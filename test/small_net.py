"""A small random FrustumShapeNet saved as a weights file (shared by the model tests)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def save_small_weights(path: Path, **config: Any) -> Path:
    """A seeded random network of ``ModelConfig(**config)`` written to ``path`` as a weights file
    with every task (box, cls, shape); returns ``path``."""
    import torch

    from shape_detector.model.config import ModelConfig
    from shape_detector.model.io import save_weights
    from shape_detector.model.network import FrustumShapeNet

    torch.manual_seed(0)
    save_weights(FrustumShapeNet(ModelConfig(**config)), path, meta={"tasks": ["box", "cls", "shape"]})
    return path
