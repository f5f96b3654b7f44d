"""The one registry of 2D proposal sources, used by the detector, the node and replay.

``geometric``: built in, class-agnostic, from the depth alone; ``learned``: built in,
class-agnostic, a small network on colour and depth (``proposal_model`` or the packaged
one, :mod:`shape_detector.proposals.learned`); ``hybrid``: both, the learned network
choosing the objects and the geometric proposer their edges
(:mod:`shape_detector.proposals.hybrid`); ``onnx``: a YOLOv5/v8 ONNX
file (``proposal_model``) run on the colour image; ``external``: boxes come with each
frame (``detect(boxes2d=...)``, the node's detections2d topic, a bag's detections topic),
so the detector builds no proposer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: name -> builder(config) of a proposer called as ``proposer(depth, K, up=, rgb=)``
_BUILDERS: dict[str, Callable[[Any], Any]] = {}


def register(name: str, builder: Callable[[Any], Any]) -> None:
    """Add a proposal source (a builder taking the detector config)."""
    _BUILDERS[name] = builder


def _geometric(config: Any) -> Any:
    from .proposals import get_proposer

    return get_proposer("geometric")


def _onnx(config: Any) -> Any:
    if not config.proposal_model:
        raise ValueError("proposal_source 'onnx' needs proposal_model (a YOLO ONNX file)")
    from .proposals import get_proposer

    return get_proposer("onnx_yolo", model_path=config.proposal_model)


def _network(name: str) -> Callable[[Any], Any]:
    """The builder of a proposer around the learned network (``proposal_model`` or the packaged one)."""

    def build(config: Any) -> Any:
        from .proposals import get_proposer

        return get_proposer(name, model_path=config.proposal_model or None, precision=config.precision)

    return build


register("geometric", _geometric)
register("hybrid", _network("hybrid"))
register("learned", _network("learned"))
register("onnx", _onnx)
register("external", lambda config: None)


def names() -> tuple[str, ...]:
    """The registered sources."""
    return tuple(_BUILDERS)


def make_proposer(config: Any) -> Any:
    """The proposer ``config.proposal_source`` names (None for ``external``); built
    lazily by the proposer itself where that is costly."""
    try:
        builder = _BUILDERS[config.proposal_source]
    except KeyError:
        raise ValueError(f"proposal_source must be one of {names()}, got {config.proposal_source!r}") from None
    return builder(config)
