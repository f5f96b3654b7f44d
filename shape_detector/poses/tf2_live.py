"""Live ``/tf`` through ``tf2_ros`` where it is importable (full ROS installs; the pip wheels lack it).

The node uses :class:`Tf2PoseLookup` when :func:`tf2_available` is true and otherwise feeds a
:class:`~shape_detector.poses.CameraPoseSource` from its own topic subscriptions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .quaternion import make_transform
from .tf_buffer import TransformLookupError


def tf2_available() -> bool:
    """True when ``tf2_ros`` can be imported."""
    try:
        import tf2_ros  # type: ignore[import-not-found]  # noqa: F401
    except ImportError:
        return False
    return True


def transform_msg_to_matrix(ts: Any) -> np.ndarray:
    """(4,4) ``T_parent_child`` of a ``geometry_msgs/TransformStamped`` (either flavour)."""
    tr = ts.transform
    t = (tr.translation.x, tr.translation.y, tr.translation.z)
    q = (tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w)
    return make_transform(np.asarray(t, dtype=np.float64), np.asarray(q, dtype=np.float64))


class Tf2PoseLookup:
    """``T_world_camera`` from a ``tf2_ros.Buffer`` filled by a ``TransformListener`` on ``node``.

    ``ImportError`` when tf2_ros is missing (check :func:`tf2_available` first).
    """

    def __init__(self, node: Any, world_frame: str = "odom", cache_time_s: float = 10.0) -> None:
        import tf2_ros  # type: ignore[import-not-found]
        from rclpy.duration import Duration

        self.world_frame = str(world_frame).lstrip("/")
        self._tf2 = tf2_ros
        self.buffer = tf2_ros.Buffer(cache_time=Duration(seconds=float(cache_time_s)))
        self.listener = tf2_ros.TransformListener(self.buffer, node)

    def T_world_camera(self, camera_frame: str, stamp_ns: int) -> np.ndarray:
        """(4,4) camera frame -> world at ``stamp_ns``; :class:`TransformLookupError` on failure."""
        from rclpy.time import Time

        try:
            ts = self.buffer.lookup_transform(self.world_frame, str(camera_frame).lstrip("/"),
                                              Time(nanoseconds=int(stamp_ns)))
        except (self._tf2.LookupException, self._tf2.ConnectivityException,
                self._tf2.ExtrapolationException) as exc:
            raise TransformLookupError(f"tf2: {self.world_frame} <- {camera_frame} at {stamp_ns} ns: {exc}") from exc
        return transform_msg_to_matrix(ts)
