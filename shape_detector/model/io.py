"""Saving / loading weights (self-describing) and training checkpoints.

A **weights file** (``weights.pt`` / ``best.pt`` / the packaged ``default.pt``) is a
``torch.save`` of a plain dict::

    {"format": WEIGHTS_FORMAT, "model_config": ModelConfig.to_dict(),
     "state_dict": {name: tensor (float16 unless saved otherwise)}, "meta": {...}}

``meta`` holds e.g. the training config, tasks, epoch, calibration temperature and
validation metrics. A **checkpoint** (``checkpoint.pt``) additionally holds the optimiser,
scheduler, epoch, RNG states and log; it is for resuming, not shipping.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from .config import ModelConfig
from .network import FrustumShapeNet

WEIGHTS_FORMAT = "shape_detector.frustum_shape_net.v1"


def default_weights_path() -> Path:
    """The packaged weights file ``shape_detector/weights/default.pt`` (may not exist)."""
    return Path(__file__).resolve().parents[1] / "weights" / "default.pt"


def _atomic_save(obj: Any, path: str | Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def save_weights(
    model: FrustumShapeNet,
    path: str | Path,
    half: bool = True,
    meta: dict[str, Any] | None = None,
) -> Path:
    """Inference-only weights (float16 floats by default, a few MB) with the model config."""
    sd = {}
    for k, v in model.state_dict().items():
        v = v.detach().cpu()
        if half and v.is_floating_point():
            v = v.half()
        sd[k] = v.clone()
    _atomic_save(
        {"format": WEIGHTS_FORMAT, "model_config": model.config.to_dict(), "state_dict": sd, "meta": dict(meta or {})},
        path,
    )
    return Path(path)


def model_from_state(blob: dict[str, Any], device: str | torch.device = "cpu") -> FrustumShapeNet:
    """Build the network described by a weights/checkpoint dict and load its state."""
    mc = dict(blob["model_config"])
    mc.setdefault("primitive_param", "sigmoid_tanh")  # weights saved before the field existed
    cfg = ModelConfig.from_dict(mc)
    model = FrustumShapeNet(cfg)
    sd = {k: (v.float() if v.is_floating_point() else v) for k, v in blob["state_dict"].items()}
    model.load_state_dict(sd)
    return model.to(device)


def load_weights(path: str | Path, device: str | torch.device = "cpu") -> tuple[FrustumShapeNet, dict[str, Any]]:
    """``(model in eval mode, meta)`` from a weights file or a training checkpoint."""
    blob = torch.load(Path(path), map_location="cpu", weights_only=False)
    if not isinstance(blob, dict) or "model_config" not in blob or "state_dict" not in blob:
        raise ValueError(f"{path}: not a shape_detector weights file")
    model = model_from_state(blob, device).eval()
    return model, dict(blob.get("meta", {}))


def save_checkpoint(path: str | Path, model: FrustumShapeNet, **state: Any) -> Path:
    """Resumable checkpoint: float32 model state, model config and anything in ``state``."""
    blob = {
        "format": WEIGHTS_FORMAT + ".checkpoint",
        "model_config": model.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
    }
    blob.update(state)
    _atomic_save(blob, path)
    return Path(path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    return torch.load(Path(path), map_location="cpu", weights_only=False)
