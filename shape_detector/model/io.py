"""Saving / loading weights (versioned, self-describing) and training checkpoints.

A **weights file** (``weights.pt`` / ``best.pt`` / the packaged ``default.pt``) is a
``torch.save`` of plain types and tensors only, so it loads with
``torch.load(path, weights_only=True)`` (no pickled objects)::

    {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
     "model_config": ModelConfig.to_dict(),
     "state_dict": {name: tensor (float16 floats unless saved otherwise)},
     "meta": {...},          # training config, tasks, epoch, calibration, validation metrics
     "provenance": {...}}    # see :mod:`.provenance`

A **checkpoint** (``checkpoint.pt``) additionally holds the optimiser, epoch, RNG states and
log; it is for resuming, not shipping (same rules: plain types and tensors).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import ModelConfig
from .network import FrustumShapeNet

WEIGHTS_FORMAT = "shape_detector.frustum_shape_net"
CHECKPOINT_FORMAT = "shape_detector.frustum_shape_net.checkpoint"
WEIGHTS_VERSION = 2


def default_weights_path() -> Path:
    """The packaged weights file ``shape_detector/weights/default.pt`` (may not exist)."""
    return Path(__file__).resolve().parents[1] / "weights" / "default.pt"


def plain(obj: Any) -> Any:
    """``obj`` as JSON-like plain types (dict / list / str / int / float / bool / None) and
    tensors, the only things ``torch.load(weights_only=True)`` accepts back: numpy values
    become Python numbers or lists, paths strings, tuples lists."""
    if obj is None or isinstance(obj, torch.Tensor):
        return obj
    for base in (bool, int, float, str):  # subclasses (TorchVersion, IntEnum) as their base type
        if isinstance(obj, base):
            return base(obj)
    if isinstance(obj, dict):
        return {(k if isinstance(k, (str, int)) else str(k)): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not storable in a weights file: {type(obj).__name__}")


def atomic_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to a temporary name, then rename (readers never see half a file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


_atomic_save = atomic_save  # the classifier's saver imports this name


def read_blob(path: str | Path) -> dict[str, Any]:
    """The raw dict of a weights / checkpoint / classifier file, loaded with
    ``weights_only=True``; a clear error for anything else."""
    try:
        blob = torch.load(Path(path), map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # pickle errors of files that are not plain weights
        raise ValueError(f"{path}: not a shape_detector weights file ({type(e).__name__}: {e})") from e
    if not isinstance(blob, dict) or "state_dict" not in blob:
        raise ValueError(f"{path}: not a shape_detector weights file")
    return blob


def half_state(model: torch.nn.Module, half: bool = True) -> dict[str, torch.Tensor]:
    """The model's state on the CPU, floats as float16 when ``half``."""
    sd = {}
    for k, v in model.state_dict().items():
        v = v.detach().cpu()
        if half and v.is_floating_point():
            v = v.half()
        sd[k] = v.clone()
    return sd


def save_weights(
    model: FrustumShapeNet,
    path: str | Path,
    half: bool = True,
    meta: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
) -> Path:
    """Inference-only weights (float16 floats by default, a few MB) with the model config,
    ``meta`` and ``provenance`` (plain types only)."""
    return save_state(model.config, half_state(model, half), path, meta, provenance)


def save_state(
    config: ModelConfig,
    state_dict: dict[str, torch.Tensor],
    path: str | Path,
    meta: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
) -> Path:
    """Write a weights file from a config and a state dict (tensors stored as given)."""
    atomic_save(
        {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "model_config": config.to_dict(),
         "state_dict": dict(state_dict), "meta": plain(dict(meta or {})), "provenance": plain(dict(provenance or {}))},
        path,
    )
    return Path(path)


def model_from_state(blob: dict[str, Any], device: str | torch.device = "cpu") -> FrustumShapeNet:
    """Build the network described by a weights/checkpoint dict and load its state."""
    cfg = ModelConfig.from_dict(blob["model_config"])
    model = FrustumShapeNet(cfg)
    sd = {k: (v.float() if v.is_floating_point() else v) for k, v in blob["state_dict"].items()}
    model.load_state_dict(sd)
    return model.to(device)


def _check_version(blob: dict[str, Any], fmt: str, path: str | Path) -> None:
    if blob.get("format") != fmt:
        raise ValueError(f"{path}: format {blob.get('format')!r}, expected {fmt!r}")
    if blob.get("version") != WEIGHTS_VERSION:
        raise ValueError(f"{path}: weights version {blob.get('version')!r}, this code reads version "
                         f"{WEIGHTS_VERSION} (older files: load with the release that wrote them and re-save)")


def load_weights(path: str | Path, device: str | torch.device = "cpu") -> tuple[FrustumShapeNet, dict[str, Any]]:
    """``(model in eval mode, meta)`` from a weights file; ``meta["provenance"]`` is the
    file's provenance block."""
    blob = read_blob(path)
    _check_version(blob, WEIGHTS_FORMAT, path)
    model = model_from_state(blob, device).eval()
    meta = dict(blob.get("meta", {}))
    meta["provenance"] = dict(blob.get("provenance", {}))
    return model, meta


def save_checkpoint(path: str | Path, model: torch.nn.Module, **state: Any) -> Path:
    """Resumable checkpoint: float32 model state, model config and anything in ``state``
    (plain types, tensors and optimiser state dicts)."""
    blob = {
        "format": CHECKPOINT_FORMAT,
        "version": WEIGHTS_VERSION,
        "model_config": model.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
    }
    blob.update(plain(state))
    atomic_save(blob, path)
    return Path(path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """The dict :func:`save_checkpoint` wrote."""
    blob = read_blob(path)
    _check_version(blob, CHECKPOINT_FORMAT, path)
    return blob
