"""2D box proposals for the frustum network.

* ``geometric`` (:class:`~shape_detector.proposals.geometric.GeometricProposer`): built-in,
  class-agnostic proposals from the depth alone (gravity estimate, floor / wall /
  ceiling removal, gravity-aware clustering); needs no model.
* ``learned`` (:class:`~shape_detector.proposals.learned.LearnedProposer`): built-in,
  class-agnostic proposals from a small CenterNet-style network on colour and depth, trained
  on generated frames (``shape-detector train-proposer``), run as ONNX.
* ``hybrid`` (:class:`~shape_detector.proposals.hybrid.HybridProposer`): both of the
  above, each learned box taking the edges of the geometric box it overlaps
  (:func:`~shape_detector.proposals.hybrid.fuse`).
* ``onnx_yolo`` (:class:`~shape_detector.proposals.onnx_yolo.OnnxYoloProposer`): an
  external YOLOv5 / YOLOv8 ONNX detector run with OpenCV DNN, COCO classes mapped to
  ours (chair, couch -> sofa, bed, dining table -> table, toilet).

Every proposer returns :class:`Proposal` objects; boxes are ``(x1, y1, x2, y2)`` pixel
edges (``x2`` = last column + 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..types import Box2D

__all__ = ["Proposal", "get_proposer", "PROPOSERS"]

PROPOSERS = ("geometric", "learned", "hybrid", "onnx_yolo")


@dataclass
class Proposal:
    """One 2D proposal: pixel-edge box, class (None = class-agnostic), score in [0, 1], source."""

    box2d: Box2D
    class_name: str | None = None
    score: float = 1.0
    source: str = "geometric"

    def __post_init__(self) -> None:
        self.box2d = tuple(float(v) for v in self.box2d)  # type: ignore[assignment]
        self.score = float(self.score)

    def as_tuple(self) -> tuple[float, float, float, float, str | None]:
        """``(x1, y1, x2, y2, class_name)``, the form ``ShapeDetector.detect(boxes2d=...)`` takes."""
        return (*self.box2d, self.class_name)  # type: ignore[return-value]


def get_proposer(name: str, **kw: Any):
    """A proposer by name: 'geometric' (``config=`` or config fields as keywords),
    'learned' (``model_path=``, ``max_proposals=``, ``min_score=``, ``precision=``), 'hybrid'
    (``model_path=`` and ``precision=`` of the learned network, ``match_iou=``,
    ``keep_unmatched=``, ``unmatched_scale=``) or
    'onnx_yolo' (``model_path=``, ``input_size=``, ``conf=``, ``nms=``)."""
    if name == "geometric":
        from .geometric import GeometricConfig, GeometricProposer

        cfg = kw.pop("config", None)
        if cfg is None:
            cfg = GeometricConfig(**kw)
        elif kw:
            raise TypeError("pass either config= or config fields, not both")
        return GeometricProposer(cfg)
    if name == "learned":
        from .learned import LearnedProposer

        return LearnedProposer(**kw)
    if name == "hybrid":
        from .geometric import GeometricProposer
        from .hybrid import HybridProposer
        from .learned import LearnedProposer

        learned = LearnedProposer(model_path=kw.pop("model_path", None), precision=kw.pop("precision", "auto"))
        return HybridProposer(learned, GeometricProposer(), **kw)
    if name in ("onnx_yolo", "onnx", "yolo"):
        from .onnx_yolo import OnnxYoloProposer

        return OnnxYoloProposer(**kw)
    raise ValueError(f"unknown proposer {name!r}; expected one of {PROPOSERS}")
