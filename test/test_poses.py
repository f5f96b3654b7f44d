"""CameraPoseSource from TFMessage / Odometry / PoseStamped (rosbags classes and plain objects)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from msg_conversion import rosbags_types
from msg_conversion.stamps import ns_to_stamp
from shape_detector.poses import CameraPoseSource, ExtrapolationError, FrameNotFoundError, TransformLookupError

S = 1_000_000_000
OPTICAL_Q = (-0.5, 0.5, -0.5, 0.5)  # camera_link (x forward, z up) -> optical (z forward, y down)


def _types():
    return rosbags_types()


def _tfs(types, parent: str, child: str, stamp_ns: int, t, q):
    M = types.make_by_name
    return M(
        "geometry_msgs/msg/TransformStamped",
        header=M("std_msgs/msg/Header", stamp=ns_to_stamp(stamp_ns, types), frame_id=parent),
        child_frame_id=child,
        transform=M(
            "geometry_msgs/msg/Transform",
            translation=M("geometry_msgs/msg/Vector3", x=t[0], y=t[1], z=t[2]),
            rotation=M("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def _tf_msg(types, *transforms):
    return types.make_by_name("tf2_msgs/msg/TFMessage", transforms=list(transforms))


def _pose(types, t, q):
    M = types.make_by_name
    return M(
        "geometry_msgs/msg/Pose",
        position=M("geometry_msgs/msg/Point", x=t[0], y=t[1], z=t[2]),
        orientation=M("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _static(types):
    return _tf_msg(types, _tfs(types, "camera_link", "camera_color_optical_frame", 0, (0, 0, 0), OPTICAL_Q))


def test_tf_source_gives_optical_pose_through_static_link() -> None:
    types = _types()
    src = CameraPoseSource(world_frame="odom", kind="tf")
    assert src.add_tf(_static(types), static=True) == 1
    for k in range(3):
        src.add_tf(_tf_msg(types, _tfs(types, "odom", "camera_link", k * S, (float(k), 0, 1.2), (0, 0, 0, 1))))
    T = src.T_world_camera("camera_color_optical_frame", S // 2)
    np.testing.assert_allclose(T[:3, 3], [0.5, 0.0, 1.2], atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], [1.0, 0.0, 0.0], atol=1e-9)  # optical z = world x
    np.testing.assert_allclose(T[:3, 1], [0.0, 0.0, -1.0], atol=1e-9)  # optical y = world down
    with pytest.raises(ExtrapolationError):
        src.T_world_camera("camera_color_optical_frame", 5 * S)


def test_odometry_source_with_static_extrinsics() -> None:
    types = _types()
    M = types.make_by_name
    src = CameraPoseSource(world_frame="odom", kind="odometry")
    src.add_tf(_static(types), static=True)
    for k in range(2):
        odom = M(
            "nav_msgs/msg/Odometry",
            header=M("std_msgs/msg/Header", stamp=ns_to_stamp(k * S, types), frame_id="odom"),
            child_frame_id="camera_link",
            pose=M("geometry_msgs/msg/PoseWithCovariance", pose=_pose(types, (0.0, float(k), 0.0), (0, 0, 0, 1))),
        )
        src.add_message(odom, "odometry")
    T = src.T_world_camera("camera_color_optical_frame", S)
    np.testing.assert_allclose(T[:3, 3], [0.0, 1.0, 0.0], atol=1e-9)


def test_pose_stamped_without_child_frame_is_the_camera_pose() -> None:
    src = CameraPoseSource(world_frame="map", kind="pose")
    for k in range(2):
        msg = SimpleNamespace(
            header=SimpleNamespace(stamp=SimpleNamespace(sec=k, nanosec=0), frame_id="map"),
            pose=SimpleNamespace(
                position=SimpleNamespace(x=float(k), y=0.0, z=0.0),
                orientation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        )
        src.add_pose(msg)
    T = src.T_world_camera("whatever_optical_frame", S // 4)
    np.testing.assert_allclose(T[:3, 3], [0.25, 0.0, 0.0], atol=1e-9)


def test_missing_world_frame_is_a_lookup_error() -> None:
    types = _types()
    src = CameraPoseSource(world_frame="map", kind="tf")
    src.add_tf(_static(types), static=True)
    with pytest.raises(FrameNotFoundError, match="'map'"):
        src.T_world_camera("camera_color_optical_frame", 0)
    with pytest.raises(TransformLookupError):
        src.T_world_camera("", 0)


def test_malformed_tf_entries_are_skipped() -> None:
    types = _types()
    good = _tfs(types, "odom", "camera_link", 0, (0, 0, 0), (0, 0, 0, 1))
    zero_q = _tfs(types, "odom", "x", 0, (0, 0, 0), (0, 0, 0, 0))
    src = CameraPoseSource()
    assert src.add_tf(_tf_msg(types, good, zero_q)) == 1
    with pytest.raises(ValueError):
        CameraPoseSource(kind="gps")
