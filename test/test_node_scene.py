"""The node's scene feed without ROS: pose sources, skips without a pose, static camera mode
(auto) and its restart once poses arrive, GetPlan answers on a hand-made grid."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from shape_detector.node_params import PARAMETERS
from shape_detector.node_scene import SceneFeed, answer_plan, pose_topics, surfaces_key
from shape_detector.poses import matrix_to_quaternion
from shape_detector.scene import NavGrid, SceneMap
from shape_detector.scene.json_io import scene_to_dict
from shape_detector.types import Object3D

pytestmark = pytest.mark.timeout(60)
K = np.array([[40.0, 0, 39.5], [0, 40.0, 29.5], [0, 0, 1]])  # wide: the whole chair in view
#: camera optical axes in a z-up world: looking along +x, 1.2 m above the floor
R_WORLD_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAM_HEIGHT = 1.2


def params(**kw):
    p = {k: v.default for k, v in PARAMETERS.items()}
    p.update(kw)
    return p


class Warnings:
    def __init__(self):
        self.texts = []

    def __call__(self, kind, text, period=5.0, level="warning", key=None):
        self.texts.append((kind, text))

    def kinds(self):
        return [k for k, _ in self.texts]


def odometry(stamp_ns: int, x: float, child: str = "cam") -> SimpleNamespace:
    """A duck-typed nav_msgs/Odometry: the camera at (x, 0, 1.2) looking along world +x."""
    q = matrix_to_quaternion(R_WORLD_CAM)
    pose = SimpleNamespace(position=SimpleNamespace(x=x, y=0.0, z=CAM_HEIGHT),
                           orientation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3]))
    header = SimpleNamespace(stamp=SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="odom")
    return SimpleNamespace(header=header, child_frame_id=child, pose=SimpleNamespace(pose=pose))


def floor_depth(h: int = 60, w: int = 80) -> np.ndarray:
    """Depth (m) of a level camera 1.2 m above a floor: rows below the horizon see it, the rest 4 m away."""
    v = np.arange(h, dtype=np.float64)[:, None] - K[1, 2]
    with np.errstate(divide="ignore"):
        d = np.where(v > 0.5, CAM_HEIGHT * K[1, 1] / np.maximum(v, 1e-9), 4.0)
    return np.broadcast_to(np.minimum(d, 4.0), (h, w)).astype(np.float32).copy()


def chair(z: float = 2.0) -> Object3D:
    # camera frame: 2 m ahead, its bottom on the floor (camera y down: floor at y = +1.2)
    return Object3D("chair", 0.9, [0.0, CAM_HEIGHT - 0.45, z], [0.5, 0.5, 0.9], np.eye(3))


def test_pose_topics_follow_the_source():
    assert pose_topics("odom", "odom", "pose", True) == [("odometry", "odom")]
    assert pose_topics("tf", "odom", "pose", False) == []
    assert [k for k, _ in pose_topics("auto", "odom", "pose", True)] == ["tf", "tf_static", "odometry", "pose"]
    assert pose_topics("none", "odom", "pose", True) == []


def test_odometry_pose_places_objects_in_the_world_and_confirms_them():
    warn = Warnings()
    feed = SceneFeed(params(pose_source="odom", scene_confirm_observations=2), warn)
    for i in range(3):
        stamp = (i + 1) * 10**8
        feed.add_pose("odometry", odometry(stamp, x=0.5))
        assert feed.update([chair()], floor_depth(), K, stamp, "cam", None)
    objects, grid, stamp = feed.snapshot()
    assert stamp == 3 * 10**8 and len(objects) == 1
    # 2 m ahead of a camera at x = 0.5 looking along +x; centre 0.45 m above the floor
    np.testing.assert_allclose(objects[0].center, [2.5, 0.0, 0.45], atol=0.05)
    assert grid.resolution == pytest.approx(0.05) and (grid.data == 0).any()
    assert "scene_static" not in warn.kinds()


def test_an_explicit_source_without_a_pose_skips_the_update():
    warn = Warnings()
    feed = SceneFeed(params(pose_source="odom"), warn)
    assert not feed.update([chair()], floor_depth(), K, 10**8, "cam", None)
    assert "scene_pose" in warn.kinds() and feed.version == 0
    feed.add_pose("odometry", odometry(10**8, 0.0, child="base_link"))  # no link base_link -> cam
    assert not feed.update([chair()], floor_depth(), K, 10**8, "cam", None)
    assert "base_link" in warn.texts[-1][1] or "cam" in warn.texts[-1][1]


def test_auto_is_static_until_a_pose_arrives_then_restarts_in_the_world_frame():
    warn = Warnings()
    feed = SceneFeed(params(pose_source="auto", scene_confirm_observations=1, scene_publish_score=0.0), warn)
    assert feed.update([chair()], floor_depth(), K, 10**8, "cam", np.array([0.0, -1.0, 0.0]))
    assert "scene_static" in warn.kinds() and len(feed.snapshot()[0]) == 1
    feed.add_pose("odometry", odometry(2 * 10**8, x=3.0))
    assert feed.update([chair()], floor_depth(), K, 2 * 10**8, "cam", None)
    assert "scene_restart" in warn.kinds()
    objects = feed.snapshot()[0]
    assert len(objects) == 1 and objects[0].center[0] == pytest.approx(5.0, abs=0.05)


def test_none_is_static_camera_mode_said_once():
    warn = Warnings()
    feed = SceneFeed(params(pose_source="none"), warn)
    for i in range(3):
        assert feed.update([], floor_depth(), K, (i + 1) * 10**8, "cam", None)
    assert warn.kinds().count("scene_static") == 3  # the node's limiter prints it once (period inf)


def test_a_malformed_pose_message_is_warned_not_raised():
    warn = Warnings()
    feed = SceneFeed(params(pose_source="odom"), warn)
    feed.add_pose("odometry", object())
    assert "pose_msg" in warn.kinds()


def _free_grid_map(blocked: bool = False) -> SceneMap:
    """4 m x 2 m free floor from (0, 0); ``blocked``: a 20 cm deep shelf across x = 2 m with no
    gap (an object: the grid a map reloads marks only objects' footprints occupied)."""
    from ar_scenes import box_object

    data = np.zeros((40, 80), np.int8)
    objects = [box_object(1, "bookshelf", (2.0, 1.0, 0.5), (0.2, 2.2, 1.0))] if blocked else []
    return SceneMap.from_json(scene_to_dict("odom", 1, objects, NavGrid(0.05, np.zeros(2), data)))


def rclpy_types():
    pytest.importorskip("nav_msgs.srv")
    from msg_conversion import rclpy_types as make

    return make()


def _request(start, goal, frame="odom"):
    GetPlan = pytest.importorskip("nav_msgs.srv").GetPlan
    req = GetPlan.Request()
    for ps, (x, y) in ((req.start, start), (req.goal, goal)):
        ps.header.frame_id = frame
        ps.pose.position.x, ps.pose.position.y = x, y
    return req


def test_plan_request_returns_a_path_on_the_grid():
    feed = SceneFeed(params(inflation_radius=0.1), Warnings())
    feed.set_map(_free_grid_map())
    req = _request((0.5, 1.0), (3.5, 1.0))
    path = answer_plan(feed, req, rclpy_types(), 5, Warnings())
    xy = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses])
    assert path.header.frame_id == "odom" and len(xy) >= 2
    np.testing.assert_allclose(xy[0], [0.5, 1.0], atol=0.05)
    np.testing.assert_allclose(xy[-1], [3.5, 1.0], atol=0.05)


@pytest.mark.parametrize("blocked, frame", [(True, "odom"), (False, "map")])
def test_plan_request_without_a_path_is_empty_and_said(blocked, frame):
    feed = SceneFeed(params(inflation_radius=0.1), Warnings())
    feed.set_map(_free_grid_map(blocked))
    warn = Warnings()
    path = answer_plan(feed, _request((0.5, 1.0), (3.5, 1.0), frame), rclpy_types(), 5, warn)
    assert len(path.poses) == 0 and warn.texts


def test_answer_plan_without_a_scene_is_an_empty_path():
    warn = Warnings()
    assert len(answer_plan(None, _request((0, 0), (1, 1)), rclpy_types(), 5, warn).poses) == 0 and warn.texts


def test_surfaces_key_changes_when_objects_move():
    feed = SceneFeed(params(pose_source="none", scene_confirm_observations=1, scene_publish_score=0.0), Warnings())
    feed.update([chair()], floor_depth(), K, 10**8, "cam", None)
    objects = feed.snapshot()[0]
    key = surfaces_key(objects)
    objects[0].center = objects[0].center + 0.1
    assert surfaces_key(objects) != key and surfaces_key([]) == ()


@pytest.mark.parametrize("timeout", [1.0, 0.0])
def test_a_pose_arriving_after_the_frame_is_waited_for_up_to_pose_timeout(timeout):
    import threading
    import time

    feed = SceneFeed(params(pose_source="odom", pose_timeout=timeout), Warnings())
    feed.add_pose("odometry", odometry(10**8, x=0.5))
    late = threading.Timer(0.2, lambda: feed.add_pose("odometry", odometry(3 * 10**8, x=0.5)))
    late.start()
    t0 = time.monotonic()
    ok = feed.update([chair()], floor_depth(), K, 2 * 10**8, "cam", None)
    late.join()
    assert ok is (timeout > 0) and time.monotonic() - t0 < 0.9


def test_feed_saves_and_continues_a_map(tmp_path):
    feed = SceneFeed(params(), Warnings())
    feed.set_map(_free_grid_map())
    out = tmp_path / "scene.json"
    assert feed.version != feed.saved_version
    assert feed.save(out) == len(feed.snapshot()[0])
    assert feed.version == feed.saved_version and not list(tmp_path.glob("*.tmp"))
    again = SceneFeed(params(), Warnings())
    assert again.load(out) == len(feed.snapshot()[0]) and again.version == again.saved_version
    np.testing.assert_array_equal(again.snapshot()[1].data, feed.snapshot()[1].data)
    with pytest.raises(ValueError, match="world_frame"):
        SceneFeed(params(world_frame="map"), Warnings()).load(out)
    with pytest.raises(OSError):
        again.load(tmp_path / "missing.json")


def _tilted_odometry(stamp_ns: int, pitch_deg: float) -> SimpleNamespace:
    """:func:`odometry` with the camera pitched down by ``pitch_deg`` about its x axis."""
    a = -np.radians(pitch_deg)  # about the camera's x (right): its z (forward) turns towards y (down)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    msg = odometry(stamp_ns, 0.0)
    q = matrix_to_quaternion(R_WORLD_CAM @ tilt)
    msg.pose.pose.orientation = SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3])
    return msg


def _up(pitch_deg: float) -> np.ndarray:
    a = np.radians(pitch_deg)  # pitched down: world up leans towards the camera's -z (backwards)
    return np.array([0.0, -np.cos(a), -np.sin(a)])


def test_up_at_is_the_world_z_in_the_camera_at_the_stamp_or_a_little_before():
    feed = SceneFeed(params(pose_source="odom"), Warnings())
    assert feed.up_at("cam", 10**8) is None  # no pose yet
    feed.add_pose("odometry", _tilted_odometry(10**8, 10.0))
    feed.add_pose("odometry", _tilted_odometry(2 * 10**8, 30.0))
    np.testing.assert_allclose(feed.up_at("cam", 10**8), _up(10.0), atol=1e-6)
    np.testing.assert_allclose(feed.up_at("cam", 15 * 10**7), _up(20.0), atol=1e-6)  # interpolated
    # poses lagging the frame by less than UP_POSE_LAG: the pose just before; more: none
    assert feed.up_at("cam", 25 * 10**7) is not None
    assert feed.up_at("cam", 10**9) is None
    assert feed.up_at("other_frame", 10**8) is None  # no chain to that frame: estimated, no error
    assert SceneFeed(params(pose_source="none"), Warnings()).up_at("cam", 10**8) is None
