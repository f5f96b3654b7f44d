"""Scene objects -> MarkerArray and NavGrid -> OccupancyGrid, both message flavours."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from msg_conversion import grid_to_occupancy, occupancy_to_cells, scene_to_markers, stamp_to_ns
from shape_detector.geometry import rot_z

CUBE, TEXT_VIEW_FACING, ADD, DELETEALL = 1, 9, 0, 3
RCLPY_MSGS = "nav_msgs"  # for conftest's ``types`` fixture


@dataclass
class _Prim:
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray


@dataclass
class _Obj:
    id: int
    class_name: str
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    primitives: list = field(default_factory=list)


@dataclass
class _Grid:
    resolution: float
    origin: np.ndarray
    data: np.ndarray
    floor_z: float = 0.0


def _objects() -> list[_Obj]:
    leg = _Prim(np.array([1.0, 2.0, 0.2]), np.array([0.05, 0.05, 0.4]), np.eye(3))
    top = _Prim(np.array([1.0, 2.0, 0.42]), np.array([0.5, 0.5, 0.04]), np.eye(3))
    return [
        _Obj(7, "table", np.array([1.0, 2.0, 0.22]), np.array([0.5, 0.5, 0.44]), rot_z(0.3), [leg, top]),
        _Obj(3, "chair", np.array([-1.0, 0.5, 0.45]), np.array([0.45, 0.45, 0.9]), np.eye(3)),
    ]


def test_scene_markers_content(types) -> None:
    msg = scene_to_markers(_objects(), types, stamp_ns=1_500_000_000, frame_id="odom")
    m = list(msg.markers)
    assert m[0].action == DELETEALL
    assert all(mk.header.frame_id == "odom" and stamp_to_ns(mk.header.stamp) == 1_500_000_000 for mk in m)
    cubes = [mk for mk in m[1:] if mk.ns == "objects"]
    assert sorted(mk.id for mk in cubes) == [3, 7]
    assert all(mk.type == CUBE and mk.action == ADD for mk in cubes)
    table = next(mk for mk in cubes if mk.id == 7)
    assert (table.pose.position.x, table.pose.position.y, table.pose.position.z) == pytest.approx((1.0, 2.0, 0.22))
    assert (table.scale.x, table.scale.y, table.scale.z) == pytest.approx((0.5, 0.5, 0.44))
    q = table.pose.orientation
    assert (q.z, q.w) == pytest.approx((np.sin(0.15), np.cos(0.15)))
    labels = {mk.id: mk for mk in m if mk.ns == "labels"}
    assert labels[7].text == "table #7" and labels[3].text == "chair #3"
    assert labels[7].type == TEXT_VIEW_FACING
    assert labels[7].pose.position.z > 0.44
    prims = [mk for mk in m if mk.ns == "primitives"]
    assert len(prims) == 2 and sorted(mk.id for mk in prims) == [0, 1]


def test_empty_scene_is_just_deleteall(types) -> None:
    msg = scene_to_markers([], types, 0, "map")
    assert len(msg.markers) == 1 and msg.markers[0].action == DELETEALL


def test_grid_to_occupancy_layout(types) -> None:
    data = np.full((3, 4), -1, dtype=np.int8)
    data[0, :] = 0
    data[2, 3] = 100  # row = y, col = x
    grid = _Grid(0.05, np.array([-1.0, 0.5]), data, floor_z=0.02)
    msg = grid_to_occupancy(grid, types, stamp_ns=42, frame_id="odom")
    assert msg.header.frame_id == "odom" and stamp_to_ns(msg.header.stamp) == 42
    assert (msg.info.width, msg.info.height) == (4, 3)
    assert msg.info.resolution == pytest.approx(0.05)
    o = msg.info.origin.position
    assert (o.x, o.y, o.z) == pytest.approx((-1.0, 0.5, 0.02))
    assert msg.info.origin.orientation.w == pytest.approx(1.0)
    flat = list(msg.data)
    assert len(flat) == 12 and flat[2 * 4 + 3] == 100 and flat[0] == 0 and flat[4] == -1
    np.testing.assert_array_equal(occupancy_to_cells(msg), data)  # serialisation: exact by contract


def test_grid_must_be_2d(types) -> None:
    with pytest.raises(ValueError, match="2-D"):
        grid_to_occupancy(_Grid(0.05, np.zeros(2), np.zeros(5, np.int8)), types, 0, "odom")


def test_scene_messages_serialise_in_a_bag_typestore() -> None:
    from msg_conversion import rosbags_types

    types = rosbags_types()
    store = types.typestore
    grid = _Grid(0.1, np.zeros(2), np.zeros((2, 2), np.int8))
    for msg in (scene_to_markers(_objects(), types, 5, "odom"), grid_to_occupancy(grid, types, 5, "odom")):
        raw = store.serialize_cdr(msg, msg.__msgtype__)
        back = store.deserialize_cdr(raw, msg.__msgtype__)
        assert type(back) is type(msg)
