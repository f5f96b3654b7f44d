"""detector_node's scene outputs in this process: ~/scene, ~/map and ~/surfaces when fed RGB-D,
camera_info and an Odometry topic on loopback; ~/get_plan (nav_msgs/srv/GetPlan) on an injected grid."""

from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("nav_msgs.srv")

from nav_msgs.msg import OccupancyGrid, Odometry  # noqa: E402
from nav_msgs.srv import GetPlan  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image, rclpy_types  # noqa: E402
from msg_conversion.stamps import ns_to_stamp  # noqa: E402
from shape_detector.node import DetectorNode  # noqa: E402
from shape_detector.poses import matrix_to_quaternion  # noqa: E402
from shape_detector.scene import NavGrid, SceneMap  # noqa: E402
from shape_detector.scene.json_io import scene_to_dict  # noqa: E402
from shape_detector.types import Object3D  # noqa: E402
from ros_spin import spinning  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

K = np.array([[60.0, 0, 79.5], [0, 60.0, 59.5], [0, 0, 1]])  # wide: the whole chair in view
W, H = 160, 120
CAM_HEIGHT = 1.2
#: camera optical axes in the z-up world: looking along +x
R_WORLD_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class ChairDetector:
    """A chair 2 m ahead standing on the floor (camera frame), every frame; ``ups``: the
    gravity each call was given."""

    def __init__(self):
        self.ups = []

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        self.ups.append(up)
        return [Object3D("chair", 0.9, [0.0, CAM_HEIGHT - 0.45, 2.0], [0.5, 0.5, 0.9], np.eye(3))]


def floor_depth() -> np.ndarray:
    """Depth (m) seen by a level camera 1.2 m above a floor (4 m beyond the floor's rows)."""
    v = np.arange(H, dtype=np.float64)[:, None] - K[1, 2]
    d = np.where(v > 0.5, CAM_HEIGHT * K[1, 1] / np.maximum(v, 1e-9), 4.0)
    return np.broadcast_to(np.minimum(d, 4.0), (H, W)).copy()


def odometry(stamp_ns: int, x: float) -> Odometry:
    m = Odometry()
    m.header.stamp = ns_to_stamp(stamp_ns, rclpy_types())
    m.header.frame_id = "odom"
    m.child_frame_id = "cam_optical"
    q = matrix_to_quaternion(R_WORLD_CAM)
    m.pose.pose.position.x, m.pose.pose.position.z = x, CAM_HEIGHT
    o = m.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return m


@pytest.fixture
def scene_node(ros_context):
    name = "sd_scene"
    types = rclpy_types()
    node = DetectorNode(name, context=ros_context, detector=ChairDetector(),
                        parameter_overrides=[Parameter("pose_source", value="odom"),
                                             Parameter("odom_topic", value=f"/{name}/in/odom"),
                                             Parameter("scene_confirm_observations", value=2),
                                             Parameter("inflation_radius", value=0.1),
                                             Parameter("stats_period", value=0.0)],
                        cli_args=["--ros-args", "-r", f"image:=/{name}/in/image", "-r", f"depth:=/{name}/in/depth",
                                  "-r", f"camera_info:=/{name}/in/info"])
    test = rclpy.create_node(f"{name}_tester", context=ros_context)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    h = type("H", (), {})()
    h.node, h.test, h.types = node, test, types
    h.pubs = {k: test.create_publisher(c, f"/{name}/in/{k}", qos) for k, c in
              (("image", types.Image), ("depth", types.Image), ("info", types.CameraInfo), ("odom", Odometry))}
    h.scene, h.maps, h.surfaces = [], [], []
    test.create_subscription(types.MarkerArray, f"/{name}/surfaces", h.surfaces.append, latched)
    test.create_subscription(types.MarkerArray, f"/{name}/scene", h.scene.append, qos)
    test.create_subscription(OccupancyGrid, f"/{name}/map", h.maps.append, latched)
    h.client = test.create_client(GetPlan, f"/{name}/get_plan")
    with spinning(ros_context, (node, test), h.pubs.values()):
        yield h


def wait_for(cond, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)
    return cond()


def test_scene_and_map_from_an_odometry_topic(scene_node):
    h = scene_node
    T = h.types
    rgb = np.full((H, W, 3), 90, np.uint8)
    for k in range(4):
        stamp = time.time_ns()
        h.pubs["odom"].publish(odometry(stamp, x=0.5))
        time.sleep(0.05)  # the pose is in before the frame that needs it
        h.pubs["info"].publish(K_to_camera_info(K, W, H, T, stamp, "cam_optical"))
        h.pubs["image"].publish(numpy_to_image(rgb, "rgb8", T, stamp, "cam_optical"))
        h.pubs["depth"].publish(depth_to_image(floor_depth(), T, "32FC1", stamp, "cam_optical"))
        assert wait_for(lambda k=k: len(h.scene) > k and len(h.maps) > k), (k, h.node.get_stats())
    # counted after the map is published: a subscriber may see the messages first
    assert wait_for(lambda: h.node.get_stats().get("scene_published", 0) >= 4), h.node.get_stats()
    last = h.scene[-1]
    cubes = [m for m in last.markers if m.ns == "objects" and m.type == 1]
    assert len(cubes) == 1 and last.markers[-1].header.frame_id == "odom"
    p = cubes[0].pose.position
    # 2 m ahead of a camera at x = 0.5 looking along +x, centre 0.45 m above the floor
    np.testing.assert_allclose([p.x, p.y, p.z], [2.5, 0.0, 0.45], atol=0.05)
    grid = h.maps[-1]
    assert grid.header.frame_id == "odom" and grid.info.resolution == pytest.approx(0.05)
    cells = np.asarray(grid.data, dtype=np.int8)
    assert cells.size == grid.info.width * grid.info.height and (cells == 0).any() and (cells == 100).any()
    # surfaces: published when the objects change (a DELETEALL first, then outlines if any)
    assert wait_for(lambda: h.surfaces) and h.surfaces[-1].markers[0].action == 3
    assert len(h.surfaces) < len(h.scene)
    # up_source auto: the detector got gravity from each frame's pose (world z in the optical frame)
    ups = h.node.detector.ups
    assert len(ups) >= 4 and all(u is not None for u in ups), ups
    np.testing.assert_allclose(ups[-1], [0.0, -1.0, 0.0], atol=1e-6)


def test_get_plan_answers_on_the_grid(scene_node):
    h = scene_node
    from ar_scenes import box_object

    data = np.zeros((40, 80), np.int8)  # 4 m x 2 m of free floor from (0, 0)
    shelf = box_object(1, "bookshelf", (2.0, 0.75, 0.5), (0.2, 1.5, 1.0))  # across x = 2 m, a gap at y > 1.5 m
    h.node.scene.set_map(SceneMap.from_json(scene_to_dict("odom", 1, [shelf], NavGrid(0.05, np.zeros(2), data))))
    assert h.client.wait_for_service(timeout_sec=5.0)
    req = GetPlan.Request()
    for ps, (x, y) in ((req.start, (0.5, 0.5)), (req.goal, (3.5, 0.5))):
        ps.header.frame_id = "odom"
        ps.pose.position.x, ps.pose.position.y = x, y
    fut = h.client.call_async(req)
    assert wait_for(fut.done, 10.0)
    path = fut.result().plan
    xy = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses])
    assert path.header.frame_id == "odom" and len(xy) >= 3
    np.testing.assert_allclose(xy[0], [0.5, 0.5], atol=0.05)
    np.testing.assert_allclose(xy[-1], [3.5, 0.5], atol=0.05)
    assert xy[:, 1].max() > 1.5  # through the gap


def test_save_scene_service_shutdown_save_and_scene_in(ros_context, tmp_path):
    pytest.importorskip("std_srvs.srv")
    from std_srvs.srv import Trigger

    from ar_scenes import box_object

    out = tmp_path / "scene.json"
    name = "sd_files"
    params = [Parameter("pose_source", value="none"), Parameter("stats_period", value=0.0),
              Parameter("scene_out", value=str(out))]
    node = DetectorNode(name, context=ros_context, detector=ChairDetector(), parameter_overrides=params)
    test = rclpy.create_node(f"{name}_tester", context=ros_context)
    client = test.create_client(Trigger, f"/{name}/save_scene")
    shelf = box_object(7, "bookshelf", (2.0, 0.75, 0.5), (0.2, 1.5, 1.0))
    grid = NavGrid(0.05, np.zeros(2), np.zeros((40, 80), np.int8))
    with spinning(ros_context, (node, test)):  # destroys the nodes on exit
        node.scene.set_map(SceneMap.from_json(scene_to_dict("odom", 5, [shelf], grid)))
        assert client.wait_for_service(timeout_sec=5.0)
        fut = client.call_async(Trigger.Request())
        assert wait_for(fut.done, 10.0)
        assert fut.result().success and "1 objects" in fut.result().message
        saved = SceneMap.from_json(out)
        assert [(o.id, o.class_name) for o in saved.objects()] == [(7, "bookshelf")]
        clear = test.create_client(Trigger, f"/{name}/clear_scene")
        assert clear.wait_for_service(timeout_sec=5.0)
        fut = clear.call_async(Trigger.Request())
        assert wait_for(fut.done, 10.0) and fut.result().message == "cleared 1 objects"
        assert node.scene.snapshot()[0] == []
        # a change after the save is written at shutdown
        node.scene.set_map(SceneMap.from_json(scene_to_dict("odom", 6, [], grid)))
    assert SceneMap.from_json(out).objects() == [] and SceneMap.from_json(out).stamp_ns == 6
    # scene_in continues a saved map; one in another frame is refused and a fresh map started
    SceneMap.from_json(scene_to_dict("odom", 9, [shelf], grid)).save_json(out)
    again = DetectorNode(f"{name}_2", context=ros_context, detector=ChairDetector(),
                         parameter_overrides=[*params[:2], Parameter("scene_in", value=str(out))])
    try:
        assert [o.id for o in again.scene.snapshot()[0]] == [7]
    finally:
        again.destroy_node()
    SceneMap.from_json(scene_to_dict("map", 9, [shelf], grid)).save_json(out)
    other = DetectorNode(f"{name}_3", context=ros_context, detector=ChairDetector(),
                         parameter_overrides=[*params[:2], Parameter("scene_in", value=str(out))])
    try:
        assert other.scene.snapshot()[0] == []
    finally:
        other.destroy_node()
