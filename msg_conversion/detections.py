"""Detections <-> vision_msgs (``Detection3DArray`` out, ``Detection2DArray`` in)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from shape_detector.types import Object3D

from .markers import make_pose, quaternion_to_rotation
from .msgtypes import MsgTypes
from .stamps import make_header

Box2DWithClass = tuple[float, float, float, float, "str | None", float]


class VisionMsgsUnavailableError(RuntimeError):
    """The MsgTypes in use has no vision_msgs classes."""


def _require_vision(types: MsgTypes) -> None:
    if not types.has_vision_msgs:
        raise VisionMsgsUnavailableError(
            f"vision_msgs is not available for {types!r}: install ros-<distro>-vision-msgs "
            "(rclpy) or use rosbags_types(), which registers the definitions"
        )


def objects_to_detection3d_array(
    objects: Sequence[Object3D], types: MsgTypes, stamp_ns: int, frame_id: str
) -> Any:
    """A ``vision_msgs/Detection3DArray`` of ``objects`` (camera frame ``frame_id``).

    Per object: ``results[0].hypothesis`` = (class name, score), ``results[0].pose.pose``
    and ``bbox.center`` = box centre + orientation, ``bbox.size`` = (l, w, h),
    ``id`` = index. Raises :class:`VisionMsgsUnavailableError` without vision_msgs.
    """
    _require_vision(types)
    M = types.make
    header = make_header(types, stamp_ns, frame_id)
    pwc_cls = types.get_class("geometry_msgs/msg/PoseWithCovariance")
    detections = []
    for i, obj in enumerate(objects):
        size = np.asarray(obj.size, dtype=np.float64).reshape(3)
        hyp = M(types.ObjectHypothesis, class_id=str(obj.class_name), score=float(obj.score))
        result = M(
            types.ObjectHypothesisWithPose,
            hypothesis=hyp,
            pose=M(pwc_cls, pose=make_pose(types, obj.center, obj.rotation)),
        )
        bbox = M(
            types.BoundingBox3D,
            center=make_pose(types, obj.center, obj.rotation),
            size=M(types.Vector3, x=float(size[0]), y=float(size[1]), z=float(size[2])),
        )
        detections.append(M(types.Detection3D, header=header, results=[result], bbox=bbox, id=str(i)))
    return M(types.Detection3DArray, header=header, detections=detections)


def _best_hypothesis(results: Sequence[Any]) -> tuple[str | None, float | None]:
    """(class id, score) of the highest-scoring result; vision_msgs 4.x or older layouts."""
    best_name: str | None = None
    best_score: float | None = None
    for r in results:
        h = getattr(r, "hypothesis", r)  # 4.x nests (class_id, score); 2.x had (id, score)
        name = getattr(h, "class_id", getattr(h, "id", None))
        score = float(getattr(h, "score", 0.0))
        if best_score is None or score > best_score:
            best_name, best_score = (str(name) if name not in (None, "") else None), score
    return best_name, best_score


def detection3d_array_to_objects(msg: Any) -> list[Object3D]:
    """Objects of a ``Detection3DArray`` (either flavour); inverse of
    :func:`objects_to_detection3d_array` (class = best hypothesis, primitives empty)."""
    out = []
    for det in msg.detections:
        name, score = _best_hypothesis(det.results)
        c, s = det.bbox.center, det.bbox.size
        out.append(
            Object3D(
                class_name=name or "",
                score=1.0 if score is None else score,
                center=np.array([c.position.x, c.position.y, c.position.z], dtype=np.float64),
                size=np.array([s.x, s.y, s.z], dtype=np.float64),
                rotation=quaternion_to_rotation(c.orientation),
            )
        )
    return out


def detection2d_array_to_boxes(msg: Any) -> list[Box2DWithClass]:
    """``[(x1, y1, x2, y2, class_name_or_None, score), ...]`` of a ``Detection2DArray``.

    Reads vision_msgs 4.x (``bbox.center.position.x/y``) and 3.x (``bbox.center.x/y``)
    layouts by duck typing; the class is the highest-scoring hypothesis' ``class_id``
    (None when there are no results or it is empty; score then 1.0). Boxes are pixel edges.
    """
    boxes: list[Box2DWithClass] = []
    for det in msg.detections:
        bb = det.bbox
        center = bb.center
        pos = getattr(center, "position", center)
        cx, cy = float(pos.x), float(pos.y)
        sx, sy = float(bb.size_x), float(bb.size_y)
        name, score = _best_hypothesis(getattr(det, "results", ()))
        boxes.append(
            (cx - 0.5 * sx, cy - 0.5 * sy, cx + 0.5 * sx, cy + 0.5 * sy, name, 1.0 if score is None else score)
        )
    return boxes
