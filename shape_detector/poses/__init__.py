"""Camera poses in a fixed world frame: a small TF buffer and pose sources (``/tf``, Odometry, PoseStamped).

No rclpy at import time; :mod:`.tf2_live` wraps ``tf2_ros`` for live nodes where it is installed.
"""

from __future__ import annotations

from .quaternion import camera_up, invert_transform, make_transform, matrix_to_quaternion, quaternion_to_matrix, slerp
from .sources import (
    CAMERA_PLACEHOLDER,
    POSE_KINDS,
    CameraPoseSource,
    odometry_fields,
    pose_fields,
    pose_stamped_fields,
    transform_stamped_fields,
)
from .tf2_live import Tf2PoseLookup, tf2_available, transform_msg_to_matrix
from .tf_buffer import ExtrapolationError, FrameNotFoundError, TransformBuffer, TransformLookupError

__all__ = [
    "CAMERA_PLACEHOLDER",
    "POSE_KINDS",
    "CameraPoseSource",
    "ExtrapolationError",
    "FrameNotFoundError",
    "Tf2PoseLookup",
    "TransformBuffer",
    "TransformLookupError",
    "camera_up",
    "invert_transform",
    "make_transform",
    "matrix_to_quaternion",
    "odometry_fields",
    "pose_fields",
    "pose_stamped_fields",
    "quaternion_to_matrix",
    "slerp",
    "tf2_available",
    "transform_msg_to_matrix",
    "transform_stamped_fields",
]
