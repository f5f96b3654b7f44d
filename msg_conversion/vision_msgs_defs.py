"""vision_msgs (ROS 2 Jazzy, 4.x) message definitions for rosbags typestores.

The rosbags Jazzy typestore ships without vision_msgs; :func:`register_vision_msgs` adds
the detection messages this package reads and writes so bags can hold them. The field
layout follows the public vision_msgs 4.x interface definitions (comments trimmed).
"""

from __future__ import annotations

from typing import Any

#: ROS type name -> .msg text.
VISION_MSGS_DEFS: dict[str, str] = {
    "vision_msgs/msg/Point2D": """
float64 x
float64 y
""",
    "vision_msgs/msg/Pose2D": """
vision_msgs/Point2D position
float64 theta
""",
    "vision_msgs/msg/BoundingBox2D": """
vision_msgs/Pose2D center
float64 size_x
float64 size_y
""",
    "vision_msgs/msg/BoundingBox3D": """
geometry_msgs/Pose center
geometry_msgs/Vector3 size
""",
    "vision_msgs/msg/ObjectHypothesis": """
string class_id
float64 score
""",
    "vision_msgs/msg/ObjectHypothesisWithPose": """
vision_msgs/ObjectHypothesis hypothesis
geometry_msgs/PoseWithCovariance pose
""",
    "vision_msgs/msg/Detection2D": """
std_msgs/Header header
vision_msgs/ObjectHypothesisWithPose[] results
vision_msgs/BoundingBox2D bbox
string id
""",
    "vision_msgs/msg/Detection2DArray": """
std_msgs/Header header
vision_msgs/Detection2D[] detections
""",
    "vision_msgs/msg/Detection3D": """
std_msgs/Header header
vision_msgs/ObjectHypothesisWithPose[] results
vision_msgs/BoundingBox3D bbox
string id
""",
    "vision_msgs/msg/Detection3DArray": """
std_msgs/Header header
vision_msgs/Detection3D[] detections
""",
}


def register_vision_msgs(typestore: Any) -> None:
    """Register the vision_msgs definitions above into a rosbags ``typestore``.

    Idempotent: types the store already knows (e.g. from an earlier call, or from a bag's
    own definitions) are left as they are.
    """
    from rosbags.typesys import get_types_from_msg

    known = getattr(typestore, "fielddefs", {})
    typs: dict[str, Any] = {}
    for name, text in VISION_MSGS_DEFS.items():
        if name in known:
            continue
        typs.update(get_types_from_msg(text, name))
    if typs:
        typestore.register(typs)
