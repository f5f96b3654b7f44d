"""Conversions between ROS messages (rclpy or rosbags classes) and numpy / shape_detector types.

Build messages with a :class:`MsgTypes` (``rclpy_types()`` for a live node,
``rosbags_types()`` for bags); read them from either flavour by duck typing. Nothing
here imports rclpy or torch at import time.
"""

from __future__ import annotations

from .camera_info import K_to_camera_info, camera_info_distortion, camera_info_size, camera_info_to_K, scale_K
from .detections import (
    VisionMsgsUnavailableError,
    detection2d_array_to_boxes,
    detection3d_array_to_objects,
    objects_to_detection3d_array,
)
from .image import (
    bytes_per_pixel,
    depth_to_image,
    encoding_info,
    image_to_depth,
    image_to_numpy,
    image_to_rgb,
    numpy_to_image,
)
from .markers import objects_to_markers, quaternion_to_rotation, rotation_to_quaternion
from .msgtypes import MsgTypes, message_type_name, rclpy_types, rosbags_types
from .scene import grid_to_occupancy, occupancy_to_cells, scene_to_markers
from .surfaces import surfaces_to_markers
from .stamps import header_to_ns_frame, make_header, ns_to_duration, ns_to_stamp, seconds_to_duration, stamp_to_ns
from .vision_msgs_defs import VISION_MSGS_DEFS, register_vision_msgs

__all__ = [
    "K_to_camera_info",
    "MsgTypes",
    "VISION_MSGS_DEFS",
    "VisionMsgsUnavailableError",
    "bytes_per_pixel",
    "camera_info_distortion",
    "camera_info_size",
    "camera_info_to_K",
    "depth_to_image",
    "detection2d_array_to_boxes",
    "detection3d_array_to_objects",
    "encoding_info",
    "grid_to_occupancy",
    "header_to_ns_frame",
    "image_to_depth",
    "image_to_numpy",
    "image_to_rgb",
    "make_header",
    "message_type_name",
    "ns_to_duration",
    "ns_to_stamp",
    "numpy_to_image",
    "objects_to_detection3d_array",
    "objects_to_markers",
    "occupancy_to_cells",
    "quaternion_to_rotation",
    "rclpy_types",
    "register_vision_msgs",
    "rosbags_types",
    "rotation_to_quaternion",
    "scale_K",
    "scene_to_markers",
    "surfaces_to_markers",
    "seconds_to_duration",
    "stamp_to_ns",
]
