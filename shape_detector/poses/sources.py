"""Camera poses in a fixed world frame from ``/tf``, ``nav_msgs/Odometry`` or ``geometry_msgs/PoseStamped``.

Messages are read by duck typing (rosbags dataclasses and rclpy classes alike). Every source
feeds one :class:`TransformBuffer`, so an odometry or pose topic combines with ``/tf_static``
(e.g. ``camera_link -> camera_color_optical_frame``) the same way ``/tf`` does.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msg_conversion.stamps import stamp_to_ns

from .tf_buffer import FrameNotFoundError, TransformBuffer

#: The pose kinds a :class:`CameraPoseSource` accepts.
POSE_KINDS = ("tf", "odometry", "pose")

#: Child frame used for ``PoseStamped`` messages when no frame is given: the pose is then
#: taken to be the camera frame's own pose.
CAMERA_PLACEHOLDER = "__camera__"


def _vector(v: Any) -> np.ndarray:
    return np.array([float(v.x), float(v.y), float(v.z)])


def _quaternion(q: Any) -> np.ndarray:
    return np.array([float(q.x), float(q.y), float(q.z), float(q.w)])


def transform_stamped_fields(ts: Any) -> tuple[str, str, int, np.ndarray, np.ndarray]:
    """``(parent, child, stamp_ns, translation (3,), quaternion xyzw (4,))`` of a TransformStamped."""
    tr = ts.transform
    return (
        str(ts.header.frame_id),
        str(ts.child_frame_id),
        stamp_to_ns(ts.header.stamp),
        _vector(tr.translation),
        _quaternion(tr.rotation),
    )


def pose_fields(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(position (3,), orientation xyzw (4,))`` of a ``geometry_msgs/Pose``."""
    return _vector(pose.position), _quaternion(pose.orientation)


def odometry_fields(msg: Any) -> tuple[str, str, int, np.ndarray, np.ndarray]:
    """``(parent, child, stamp_ns, t, q)`` of a ``nav_msgs/Odometry``: the pose of ``child_frame_id``
    in ``header.frame_id`` (the twist is ignored)."""
    t, q = pose_fields(msg.pose.pose)
    return str(msg.header.frame_id), str(msg.child_frame_id), stamp_to_ns(msg.header.stamp), t, q


def pose_stamped_fields(msg: Any) -> tuple[str, int, np.ndarray, np.ndarray]:
    """``(parent, stamp_ns, t, q)`` of a ``geometry_msgs/PoseStamped``."""
    t, q = pose_fields(msg.pose)
    return str(msg.header.frame_id), stamp_to_ns(msg.header.stamp), t, q


class CameraPoseSource:
    """``T_world_camera`` for a frame stamp from one pose source plus static transforms.

    ``kind`` is ``'tf'`` (``/tf`` + ``/tf_static``), ``'odometry'`` (``nav_msgs/Odometry``: the pose of
    its ``child_frame_id``, or of ``pose_child_frame`` when that is empty) or ``'pose'``
    (``geometry_msgs/PoseStamped``: the pose of ``pose_child_frame``; None means the camera frame
    itself). ``/tf_static`` and ``/tf`` messages may be added for every kind (they give the chain from
    the pose's frame to the camera's optical frame).
    """

    def __init__(
        self,
        world_frame: str = "odom",
        kind: str = "tf",
        max_history_ns: int | None = 10_000_000_000,
        pose_child_frame: str | None = None,
    ) -> None:
        if kind not in POSE_KINDS:
            raise ValueError(f"pose source kind {kind!r} must be one of {POSE_KINDS}")
        if not str(world_frame).strip("/"):
            raise ValueError("world_frame must not be empty")
        self.world_frame = str(world_frame).lstrip("/")
        self.kind = kind
        self.pose_child_frame = pose_child_frame
        self.buffer = TransformBuffer(max_history_ns=max_history_ns)
        self.messages = 0

    def add_tf(self, msg: Any, static: bool = False) -> int:
        """Store a ``tf2_msgs/TFMessage`` (``static`` for ``/tf_static``); returns transforms stored."""
        n = self.buffer.add_tf_message(msg, static=static)
        self.messages += 1 if n else 0
        return n

    def add_odometry(self, msg: Any) -> None:
        """Store the pose of one ``nav_msgs/Odometry``; ``ValueError`` for a malformed message."""
        parent, child, stamp_ns, t, q = odometry_fields(msg)
        child = child or self.pose_child_frame or CAMERA_PLACEHOLDER
        self.buffer.add(parent or self.world_frame, child, stamp_ns, t, q)
        self.messages += 1

    def add_pose(self, msg: Any) -> None:
        """Store one ``geometry_msgs/PoseStamped``; ``ValueError`` for a malformed message."""
        parent, stamp_ns, t, q = pose_stamped_fields(msg)
        child = self.pose_child_frame or CAMERA_PLACEHOLDER
        self.buffer.add(parent or self.world_frame, child, stamp_ns, t, q)
        self.messages += 1

    def add_message(self, msg: Any, topic_kind: str) -> None:
        """Dispatch by ``topic_kind``: ``'tf'``, ``'tf_static'``, ``'odometry'`` or ``'pose'``."""
        if topic_kind in ("tf", "tf_static"):
            self.add_tf(msg, static=topic_kind == "tf_static")
        elif topic_kind == "odometry":
            self.add_odometry(msg)
        elif topic_kind == "pose":
            self.add_pose(msg)
        else:
            raise ValueError(f"unknown pose topic kind {topic_kind!r}")

    def T_world_camera(self, camera_frame: str, stamp_ns: int) -> np.ndarray:
        """(4,4) camera frame -> world frame at ``stamp_ns``.

        Raises :class:`~shape_detector.poses.TransformLookupError` (a ``LookupError``) naming the
        missing link or the stamp outside the stored history.
        """
        frame = str(camera_frame).lstrip("/")
        known = self.buffer.frames()
        if frame not in known and CAMERA_PLACEHOLDER in known:
            frame = CAMERA_PLACEHOLDER
        if not frame:
            raise FrameNotFoundError("the image has an empty frame_id: no camera frame to look up")
        return self.buffer.lookup(self.world_frame, frame, int(stamp_ns))
