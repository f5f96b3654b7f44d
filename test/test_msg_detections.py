"""vision_msgs conversions, the vision_msgs typestore definitions, MsgTypes and stamps."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from msg_conversion import (
    VISION_MSGS_DEFS,
    VisionMsgsUnavailableError,
    detection2d_array_to_boxes,
    detection3d_array_to_objects,
    make_header,
    ns_to_duration,
    ns_to_stamp,
    objects_to_detection3d_array,
    quaternion_to_rotation,
    rclpy_types,
    register_vision_msgs,
    rosbags_types,
    stamp_to_ns,
)
from shape_detector.geometry import heading_to_rotation
from shape_detector.types import Object3D


def _objects():
    return [
        Object3D("sofa", 0.93, [1.0, 0.4, 3.5], [0.9, 1.9, 0.85], heading_to_rotation(1.1, None)),
        Object3D("bed", 0.41, [-1.0, 0.6, 4.0], [2.1, 1.6, 0.9], heading_to_rotation(-0.3, np.array([0.0, -0.9, 0.2]))),
    ]


def _vision_types():
    types = [rosbags_types()]
    try:
        r = rclpy_types()
        if r.has_vision_msgs:
            types.append(r)
    except ImportError:
        pass
    return types


@pytest.mark.parametrize("types", _vision_types(), ids=lambda t: t.flavour)
def test_detection3d_array_content_and_round_trip(types):
    objs = _objects()
    msg = objects_to_detection3d_array(objs, types, stamp_ns=8_000_000_009, frame_id="cam")
    assert stamp_to_ns(msg.header.stamp) == 8_000_000_009 and msg.header.frame_id == "cam"
    assert len(msg.detections) == 2
    for i, (det, obj) in enumerate(zip(msg.detections, objs)):
        assert det.header.frame_id == "cam" and det.id == str(i)
        assert len(det.results) == 1
        hyp = det.results[0].hypothesis
        assert hyp.class_id == obj.class_name and hyp.score == pytest.approx(obj.score)
        c = det.bbox.center
        np.testing.assert_allclose([c.position.x, c.position.y, c.position.z], obj.center)
        np.testing.assert_allclose(quaternion_to_rotation(c.orientation), obj.rotation, atol=1e-9)
        np.testing.assert_allclose([det.bbox.size.x, det.bbox.size.y, det.bbox.size.z], obj.size)
        p = det.results[0].pose.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], obj.center)
    back = detection3d_array_to_objects(msg)
    for a, b in zip(objs, back):
        assert (a.class_name, a.score) == (b.class_name, pytest.approx(b.score))
        np.testing.assert_allclose(b.center, a.center)
        np.testing.assert_allclose(b.size, a.size)
        np.testing.assert_allclose(b.rotation, a.rotation, atol=1e-9)


def test_detection3d_array_rosbags_cdr_round_trip():
    types = rosbags_types()
    ts = types.typestore
    name = "vision_msgs/msg/Detection3DArray"
    msg = objects_to_detection3d_array(_objects(), types, 12, "cam")
    back = ts.deserialize_cdr(ts.serialize_cdr(msg, name), name)
    objs = detection3d_array_to_objects(back)
    assert [o.class_name for o in objs] == ["sofa", "bed"]
    np.testing.assert_allclose(objs[1].center, _objects()[1].center)
    assert stamp_to_ns(back.header.stamp) == 12
    assert len(back.detections[0].results[0].pose.covariance) == 36


def test_missing_vision_msgs_is_a_clear_error():
    pytest.importorskip("sensor_msgs.msg")
    types = rclpy_types()
    if types.has_vision_msgs:
        pytest.skip("vision_msgs is installed")
    with pytest.raises(VisionMsgsUnavailableError, match="vision_msgs"):
        objects_to_detection3d_array(_objects(), types, 0, "cam")


def test_detection2d_array_to_boxes():
    types = rosbags_types()
    M = types.make

    def det(cx, cy, sx, sy, hyps):
        results = [M(types.ObjectHypothesisWithPose, hypothesis=M(types.ObjectHypothesis, class_id=c, score=s)) for c, s in hyps]
        center = types.make_by_name("vision_msgs/msg/Pose2D", position=types.make_by_name("vision_msgs/msg/Point2D", x=cx, y=cy))
        return M(types.Detection2D, results=results, bbox=M(types.BoundingBox2D, center=center, size_x=sx, size_y=sy))

    msg = M(types.Detection2DArray, detections=[det(100.0, 50.0, 40.0, 20.0, [("chair", 0.3), ("sofa", 0.8)]), det(10.0, 10.0, 4.0, 6.0, [])])
    ts = types.typestore
    msg = ts.deserialize_cdr(ts.serialize_cdr(msg, "vision_msgs/msg/Detection2DArray"), "vision_msgs/msg/Detection2DArray")
    boxes = detection2d_array_to_boxes(msg)
    assert boxes[0] == (80.0, 40.0, 120.0, 60.0, "sofa", pytest.approx(0.8))
    assert boxes[1] == (8.0, 7.0, 12.0, 13.0, None, 1.0)
    # vision_msgs 3.x layout (Pose2D with x/y, hypotheses with id/score), duck-typed
    old = SimpleNamespace(
        detections=[
            SimpleNamespace(
                results=[SimpleNamespace(id="table", score=0.6)],
                bbox=SimpleNamespace(center=SimpleNamespace(x=5.0, y=6.0, theta=0.0), size_x=2.0, size_y=4.0),
            )
        ]
    )
    assert detection2d_array_to_boxes(old) == [(4.0, 4.0, 6.0, 8.0, "table", 0.6)]


def test_vision_msgs_registration():
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    assert "vision_msgs/msg/Detection3DArray" not in store.types
    register_vision_msgs(store)
    register_vision_msgs(store)  # idempotent
    for name in VISION_MSGS_DEFS:
        assert name in store.types
    fields = [f for f, _ in store.fielddefs["vision_msgs/msg/Detection3D"][1]]
    assert fields == ["header", "results", "bbox", "id"]
    fields = [f for f, _ in store.fielddefs["vision_msgs/msg/BoundingBox2D"][1]]
    assert fields == ["center", "size_x", "size_y"]
    types = rosbags_types(store)
    assert types.typestore is store and types.Detection3DArray is store.types["vision_msgs/msg/Detection3DArray"]


def test_msgtypes_make_defaults():
    types = rosbags_types()
    assert types.flavour == "rosbags" and types.has_vision_msgs
    q = types.make(types.Quaternion)
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    info = types.make(types.CameraInfo, width=3)
    assert info.width == 3 and info.k.shape == (9,) and info.d.shape == (0,) and info.roi.do_rectify is False
    marker = types.make(types.Marker)
    assert marker.points == [] and marker.text == "" and marker.header.frame_id == ""
    with pytest.raises(TypeError, match="no field"):
        types.make(types.Image, nonsense=1)
    with pytest.raises(ValueError):
        types.make(None)


def test_stamps():
    types = rosbags_types()
    for ns in (0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_500_000_000):
        t = ns_to_stamp(ns, types)
        assert 0 <= t.nanosec < 1_000_000_000
        assert stamp_to_ns(t) == ns
        assert stamp_to_ns(ns_to_duration(ns, types)) == ns
    t = ns_to_stamp(-1, types)
    assert (t.sec, t.nanosec) == (-1, 999_999_999)
    h = make_header(types, 2_500_000_000, "base")
    assert (h.stamp.sec, h.stamp.nanosec, h.frame_id) == (2, 500_000_000, "base")
    assert stamp_to_ns(h) == 2_500_000_000
    assert stamp_to_ns(SimpleNamespace(secs=3, nsecs=4)) == 3_000_000_004
    assert stamp_to_ns(SimpleNamespace(nanoseconds=17)) == 17
    assert stamp_to_ns(42) == 42
    with pytest.raises(TypeError):
        stamp_to_ns("1")


def test_stamps_rclpy():
    pytest.importorskip("builtin_interfaces.msg")
    types = rclpy_types()
    h = make_header(types, 1_700_000_000_000_000_001, "cam")
    assert type(h).__module__.startswith("std_msgs")
    assert stamp_to_ns(h.stamp) == 1_700_000_000_000_000_001
