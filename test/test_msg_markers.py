"""Object3D -> MarkerArray, and rotation <-> quaternion."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from msg_conversion import (
    objects_to_markers,
    quaternion_to_rotation,
    rosbags_types,
    rotation_to_quaternion,
    stamp_to_ns,
)
from shape_detector.classes import class_color
from shape_detector.geometry import BOX_EDGES, box_corners, heading_to_rotation
from shape_detector.types import Cuboid, Object3D

CUBE, LINE_LIST, TEXT_VIEW_FACING, ADD, DELETEALL = 1, 5, 9, 0, 3
RCLPY_MSGS = "visualization_msgs"  # for conftest's ``types`` fixture


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _axis_angle(axis, angle) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def test_rotation_to_quaternion_known_values():
    assert rotation_to_quaternion(np.eye(3)) == pytest.approx((0, 0, 0, 1))
    s = np.sqrt(0.5)
    assert rotation_to_quaternion(_axis_angle([0, 0, 1], np.pi / 2)) == pytest.approx((0, 0, s, s))
    assert rotation_to_quaternion(_axis_angle([1, 0, 0], np.pi)) == pytest.approx((1, 0, 0, 0), abs=1e-12)
    assert rotation_to_quaternion(_axis_angle([0, 1, 0], np.pi)) == pytest.approx((0, 1, 0, 0), abs=1e-12)
    assert rotation_to_quaternion(_axis_angle([0, 0, 1], np.pi)) == pytest.approx((0, 0, 1, 0), abs=1e-12)


def test_rotation_to_quaternion_round_trips_all_branches():
    rng = np.random.default_rng(0)
    rots = [_random_rotation(rng) for _ in range(200)]
    # near-180-degree rotations exercise every Shepperd branch (trace close to -1)
    rots += [_axis_angle(rng.normal(size=3), np.pi - 1e-9) for _ in range(50)]
    rots += [_axis_angle(ax, np.pi - 1e-3) for ax in np.eye(3)]
    rots += [heading_to_rotation(t, None) for t in np.linspace(-np.pi, np.pi, 13)]
    for R in rots:
        q = np.array(rotation_to_quaternion(R))
        assert np.linalg.norm(q) == pytest.approx(1.0)
        assert q[3] >= 0
        np.testing.assert_allclose(quaternion_to_rotation(q), R, atol=1e-9)


def test_rotation_to_quaternion_robust_to_noise_and_bad_input():
    rng = np.random.default_rng(1)
    R = _random_rotation(rng)
    noisy = R + rng.normal(scale=1e-4, size=(3, 3))
    np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(noisy)), R, atol=1e-3)
    with pytest.raises(ValueError):
        rotation_to_quaternion(np.full((3, 3), np.nan))
    with pytest.raises(ValueError):
        rotation_to_quaternion(np.eye(4))


def _objects():
    R1 = heading_to_rotation(0.6, None)
    R2 = heading_to_rotation(-2.0, np.array([0.0, -0.95, 0.3]))
    chair = Object3D(
        "chair", 0.871, [0.4, 0.3, 2.2], [0.6, 0.55, 0.85], R1,
        primitives=[Cuboid([0.4, 0.35, 2.2], [0.5, 0.5, 0.08], R1), Cuboid([0.2, 0.1, 2.2], [0.08, 0.5, 0.5], R1)],
    )
    table = Object3D("table", 0.5, [-0.8, 0.5, 3.0], [1.2, 0.8, 0.72], R2, primitives=[Cuboid([-0.8, 0.15, 3.0], [1.2, 0.8, 0.04], R2)])
    return [chair, table]


def _xyz(p) -> np.ndarray:
    return np.array([p.x, p.y, p.z])


def test_marker_array_content(types):
    objs = _objects()
    arr = objects_to_markers(objs, types, stamp_ns=1_234_567_890_123, frame_id="camera_color_optical_frame", lifetime_s=0.5)
    ms = list(arr.markers)
    assert len(ms) == 1 + 3 * 2 + 3
    first = ms[0]
    assert (first.action, first.ns, first.id) == (DELETEALL, "", 0)
    by_ns = defaultdict(list)
    for m in ms:
        assert stamp_to_ns(m.header.stamp) == 1_234_567_890_123
        assert m.header.frame_id == "camera_color_optical_frame"
        assert m.color.a > 0
        by_ns[m.ns].append(m)
    for ns, group in by_ns.items():
        ids = [m.id for m in group]
        assert len(ids) == len(set(ids)), ns
    assert {ns: len(g) for ns, g in by_ns.items()} == {"": 1, "boxes": 2, "wireframes": 2, "labels": 2, "primitives": 3}
    for m in ms[1:]:
        assert m.action == ADD
        assert (m.lifetime.sec, m.lifetime.nanosec) == (0, 500_000_000)
    for i, obj in enumerate(objs):
        rgb = np.array(class_color(obj.class_name))
        box = by_ns["boxes"][i]
        assert box.type == CUBE and box.id == i
        np.testing.assert_allclose(_xyz(box.pose.position), obj.center)
        np.testing.assert_allclose(quaternion_to_rotation(box.pose.orientation), obj.rotation, atol=1e-6)
        np.testing.assert_allclose(_xyz(box.scale), obj.size)
        np.testing.assert_allclose([box.color.r, box.color.g, box.color.b], rgb, atol=1e-6)
        assert box.color.a == pytest.approx(0.35)
        wire = by_ns["wireframes"][i]
        assert wire.type == LINE_LIST and len(wire.points) == 24 and wire.scale.x > 0
        corners = box_corners(obj.center, obj.size, obj.rotation)
        expected = np.array([corners[j] for e in BOX_EDGES for j in e])
        np.testing.assert_allclose(np.array([_xyz(p) for p in wire.points]), expected, atol=1e-12)
        np.testing.assert_allclose([wire.color.r, wire.color.g, wire.color.b, wire.color.a], [*rgb, 1.0], atol=1e-6)
        assert wire.pose.orientation.w == 1.0
        label = by_ns["labels"][i]
        assert label.type == TEXT_VIEW_FACING and label.scale.z > 0
        assert label.text == f"{obj.class_name} {obj.score:.2f}"
        up = obj.rotation[:, 2]
        height = (_xyz(label.pose.position) - obj.center) @ up
        assert height > obj.size[2] / 2
        np.testing.assert_allclose([label.color.r, label.color.g, label.color.b], rgb, atol=1e-6)
    assert by_ns["labels"][0].text == "chair 0.87"
    prims = [p for o in objs for p in o.primitives]
    for m, p, owner in zip(by_ns["primitives"], prims, ["chair", "chair", "table"]):
        assert m.type == CUBE
        np.testing.assert_allclose(_xyz(m.pose.position), p.center)
        np.testing.assert_allclose(_xyz(m.scale), p.size)
        np.testing.assert_allclose(quaternion_to_rotation(m.pose.orientation), p.rotation, atol=1e-6)
        np.testing.assert_allclose([m.color.r, m.color.g, m.color.b], class_color(owner), atol=1e-6)


def test_marker_options(types):
    arr = objects_to_markers(_objects(), types, 0, "f", show_primitives=False, box_alpha=0.9)
    assert not [m for m in arr.markers if m.ns == "primitives"]
    assert all(m.color.a == pytest.approx(0.9) for m in arr.markers if m.ns == "boxes")
    empty = objects_to_markers([], types, 0, "f")
    assert len(empty.markers) == 1 and empty.markers[0].action == DELETEALL
    unknown = objects_to_markers([Object3D("lamp", 0.3, [0, 0, 1], [0, 0.1, 0.1], np.eye(3))], types, 0, "f")
    box = [m for m in unknown.markers if m.ns == "boxes"][0]
    assert box.scale.x > 0  # zero extents clamped, RViz rejects zero-size cubes
    assert [box.color.r, box.color.g, box.color.b] == pytest.approx(class_color("lamp"))
    with pytest.raises(ValueError):
        objects_to_markers([], types, 0, "f", box_alpha=0.0)


def test_rosbags_cdr_round_trip():
    types = rosbags_types()
    ts = types.typestore
    arr = objects_to_markers(_objects(), types, 99, "cam")
    name = "visualization_msgs/msg/MarkerArray"
    back = ts.deserialize_cdr(ts.serialize_cdr(arr, name), name)
    assert len(back.markers) == len(arr.markers)
    for a, b in zip(arr.markers, back.markers):
        assert (a.ns, a.id, a.type, a.action, a.text) == (b.ns, b.id, b.type, b.action, b.text)
        assert stamp_to_ns(b.header.stamp) == 99 and b.header.frame_id == "cam"
        np.testing.assert_allclose(_xyz(b.pose.position), _xyz(a.pose.position))
        np.testing.assert_allclose([b.color.r, b.color.a], [a.color.r, a.color.a], rtol=1e-6)
        if a.points:
            np.testing.assert_allclose([_xyz(p) for p in b.points], [_xyz(p) for p in a.points])
