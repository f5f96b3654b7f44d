"""The detector a replay (or the node) runs: ``ShapeDetector(config)`` or a named factory.

A factory (``'package.module:callable'``, for tests and plugins) is called with the keyword
arguments of :func:`factory_kwargs`: the settings it is likely to take (what it loads and how
much it does); everything else of the config stays with ShapeDetector.
"""

from __future__ import annotations

import importlib
from typing import Any

from ..detector_config import DetectorConfig


def load_factory(spec: str) -> Any:
    """``'package.module:callable'`` -> the callable (a detector factory)."""
    if ":" not in spec:
        raise ValueError(f"detector factory {spec!r} must look like 'package.module:callable'")
    mod, _, attr = spec.partition(":")
    obj: Any = importlib.import_module(mod)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def factory_kwargs(config: DetectorConfig) -> dict[str, Any]:
    """The keyword arguments a custom detector factory gets (ShapeDetector's names)."""
    keys = ("weights", "device", "score_threshold", "max_objects", "workers", "precision", "mirror_tta")
    kw = {k: getattr(config, k) for k in keys}
    kw["weights"] = config.weights or None
    kw["proposals"] = "none" if config.proposal_source == "external" else config.proposal_source
    if config.classifier:
        kw["classifier"] = False if config.classifier == "none" else config.classifier
    return kw


def make_detector(config: DetectorConfig | None = None, factory: str | None = None) -> Any:
    """``ShapeDetector(config)`` (default: the realtime preset), or ``factory(**factory_kwargs(config))``."""
    from ..detector_config import preset

    config = config if config is not None else preset("realtime")
    if factory:
        return load_factory(factory)(**factory_kwargs(config))
    from ..detector import ShapeDetector

    return ShapeDetector(config)
