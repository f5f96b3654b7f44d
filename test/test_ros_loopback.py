"""Messages built by msg_conversion go through real rclpy publish/subscribe (loopback only).

conftest.py pins ROS traffic to this host (LOCALHOST discovery, shared-memory transport,
a per-run domain id) and provides the ``ros_context`` fixture.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("visualization_msgs.msg")

from msg_conversion import (  # noqa: E402
    K_to_camera_info,
    camera_info_to_K,
    image_to_numpy,
    numpy_to_image,
    objects_to_markers,
    rclpy_types,
    stamp_to_ns,
)
from shape_detector.geometry import heading_to_rotation  # noqa: E402
from shape_detector.types import Cuboid, Object3D  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

TIMEOUT_S = 15.0


def test_environment_is_loopback_only():
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    # both names: Fast DDS 2.x (the Jazzy wheels) reads only the FASTRTPS one
    assert os.environ["FASTDDS_DEFAULT_PROFILES_FILE"].endswith("fastdds_shm.xml")
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_shm.xml")


@pytest.fixture(scope="module")
def pubsub(ros_context):
    """(publisher node, subscriber node, executor) sharing the session context."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    pub_node = rclpy.create_node("msg_conversion_test_pub", context=ros_context)
    sub_node = rclpy.create_node("msg_conversion_test_sub", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(pub_node)
    executor.add_node(sub_node)
    yield pub_node, sub_node, executor
    executor.shutdown()
    pub_node.destroy_node()
    sub_node.destroy_node()


def _exchange(pubsub, msg_type, topic: str, msg):
    """Publish ``msg`` until the subscriber has one; return the received message."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    pub_node, sub_node, executor = pubsub
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    received = []
    sub = sub_node.create_subscription(msg_type, topic, received.append, qos)
    pub = pub_node.create_publisher(msg_type, topic, qos)
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not received and time.monotonic() < deadline:
            if pub.get_subscription_count() > 0:
                pub.publish(msg)
            executor.spin_once(timeout_sec=0.05)
        assert received, f"nothing received on {topic} within {TIMEOUT_S}s"
        return received[0]
    finally:
        pub_node.destroy_publisher(pub)
        sub_node.destroy_subscription(sub)


def _xyz(p):
    return (p.x, p.y, p.z)


def test_marker_array_over_loopback(pubsub):
    types = rclpy_types()
    R = heading_to_rotation(0.4, None)
    objs = [
        Object3D("chair", 0.87, [0.3, 0.2, 2.0], [0.6, 0.55, 0.85], R, primitives=[Cuboid([0.3, 0.3, 2.0], [0.5, 0.5, 0.06], R)]),
        Object3D("bookshelf", 0.66, [-1.0, -0.2, 3.0], [0.4, 1.1, 1.7], np.eye(3)),
    ]
    sent = objects_to_markers(objs, types, stamp_ns=1_700_000_000_000_000_042, frame_id="camera_color_optical_frame", lifetime_s=0.25)
    got = _exchange(pubsub, types.MarkerArray, "/msg_conversion_test/markers", sent)
    assert len(got.markers) == len(sent.markers) == 1 + 3 * 2 + 1
    for a, b in zip(sent.markers, got.markers):
        assert (b.ns, b.id, b.type, b.action, b.text) == (a.ns, a.id, a.type, a.action, a.text)
        assert stamp_to_ns(b.header.stamp) == 1_700_000_000_000_000_042
        assert b.header.frame_id == "camera_color_optical_frame"
        assert _xyz(b.pose.position) == _xyz(a.pose.position)
        assert (b.pose.orientation.x, b.pose.orientation.w) == (a.pose.orientation.x, a.pose.orientation.w)
        assert _xyz(b.scale) == _xyz(a.scale)
        # ColorRGBA is float32 on the wire
        np.testing.assert_array_equal(
            np.float32([b.color.r, b.color.g, b.color.b, b.color.a]), np.float32([a.color.r, a.color.g, a.color.b, a.color.a])
        )
        assert (b.lifetime.sec, b.lifetime.nanosec) == (a.lifetime.sec, a.lifetime.nanosec)
        assert [_xyz(p) for p in b.points] == [_xyz(p) for p in a.points]
    assert got.markers[0].action == 3
    assert [m.text for m in got.markers if m.ns == "labels"] == ["chair 0.87", "bookshelf 0.66"]
    assert len([m for m in got.markers if m.ns == "wireframes"][0].points) == 24


def test_image_and_camera_info_over_loopback(pubsub):
    types = rclpy_types()
    rng = np.random.default_rng(0)
    depth_mm = rng.integers(0, 65535, (24, 32), endpoint=True).astype(np.uint16)
    img = numpy_to_image(depth_mm, "16UC1", types, stamp_ns=5, frame_id="depth", is_bigendian=True, step=32 * 2 + 6)
    got = _exchange(pubsub, types.Image, "/msg_conversion_test/depth", img)
    assert (got.step, got.is_bigendian, got.encoding) == (70, 1, "16UC1")
    np.testing.assert_array_equal(image_to_numpy(got), depth_mm)
    K = np.array([[300.0, 0, 15.5], [0, 301.0, 11.5], [0, 0, 1]])
    info = _exchange(pubsub, types.CameraInfo, "/msg_conversion_test/camera_info", K_to_camera_info(K, 32, 24, types, 5, "depth"))
    np.testing.assert_array_equal(camera_info_to_K(info), K)
