"""``detector_node``: the ROS 2 node, the rclpy wiring around :class:`~shape_detector.node_core.NodeCore`.

Topics (relative, remap them):

* in  ``image`` (sensor_msgs/Image, colour), ``depth`` (sensor_msgs/Image 16UC1 / 32FC1,
  registered to the colour camera), ``camera_info`` (sensor_msgs/CameraInfo of the colour
  camera); optional ``imu`` (sensor_msgs/Imu, with ``up_source:=imu``) and
  ``detections2d`` (vision_msgs/Detection2DArray, with ``proposal_source:=external``);
  camera poses (``pose_source``): ``/tf`` + ``/tf_static``, ``odom_topic``, ``pose_topic``.
* out ``~/markers`` (visualization_msgs/MarkerArray, reliable, one per processed frame,
  the colour image's stamp and frame), where vision_msgs is importable ``~/detections``
  (vision_msgs/Detection3DArray); with ``publish_scene``: ``~/scene`` (MarkerArray) and
  ``~/map`` (nav_msgs/OccupancyGrid) in ``world_frame`` each processed frame, ``~/surfaces``
  (MarkerArray, when they change), the service ``~/get_plan`` (nav_msgs/srv/GetPlan) and,
  where std_srvs is installed, ``~/save_scene`` (std_srvs/srv/Trigger: the map as JSON to
  ``scene_out``; also every ``scene_save_period`` and at shutdown; ``scene_in`` continues one)
  and ``~/clear_scene`` (Trigger: start an empty map).

Image and depth (and external detections) are paired by
:class:`~shape_detector.sync.ApproximateTimeSynchronizer`; sets go to
:class:`~shape_detector.scheduler.FrameScheduler` (newest first, output in input order,
frames the node cannot keep up with dropped and counted). Bad input is logged, each distinct
problem at least once, and answered with an empty MarkerArray; it never stops the node.

Large images: with best-effort QoS (``qos:=sensor_data``) a large message travels in
fragments through the Fast DDS shared-memory segment (shape_detector/config/fastdds_shm.xml);
when fragments do not fit the transport drops the frame unseen; ``qos:=reliable`` delivers it.
"""

from __future__ import annotations

import importlib
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .node_core import NodeCore
from .node_params import PARAMETERS, descriptor_fields, validate_all
from .node_scene import SURFACES_PERIOD, SceneFeed, pose_topics, surfaces_key


def _descriptor(name: str) -> ParameterDescriptor:
    fields = descriptor_fields(PARAMETERS[name])
    if "floating_point_range" in fields:
        lo, hi = fields["floating_point_range"]
        fields["floating_point_range"] = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    if "integer_range" in fields:
        lo, hi = fields["integer_range"]
        fields["integer_range"] = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    return ParameterDescriptor(**fields)


def _qos(depth: int, reliable: bool = True, latched: bool = False) -> QoSProfile:
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class DetectorNode(NodeCore, Node):
    """The detector node. ``detector``: an object with ``detect(rgb, depth, K, boxes2d=,
    up=)`` to use instead of building one (tests); ``detector_factory``: a callable taking
    ShapeDetector's keyword arguments (overrides the ``detector_factory`` parameter).
    Other keyword arguments go to :class:`rclpy.node.Node` (``context``,
    ``parameter_overrides``, ``namespace``, ``cli_args``...)."""

    def __init__(self, node_name: str = "shape_detector", *, detector: Any = None,
                 detector_factory: Callable[..., Any] | None = None, **node_kwargs: Any) -> None:
        Node.__init__(self, node_name, **node_kwargs)
        from msg_conversion.msgtypes import rclpy_types

        for name in PARAMETERS:
            self.declare_parameter(name, PARAMETERS[name].default, _descriptor(name))
        p: dict[str, Any] = {name: self.get_parameter(name).value for name in PARAMETERS}
        problems = validate_all(p)
        if problems:
            raise ValueError("invalid parameters: " + "; ".join(problems))
        self.types = rclpy_types()
        self._factory = detector_factory
        if p["proposal_source"] == "external" and not self.types.has_vision_msgs:
            p["proposal_source"] = PARAMETERS["proposal_source"].default
            self.get_logger().error("proposal_source=external needs vision_msgs (Detection2DArray), which is not "
                                    f"installed: using the built-in proposals ({p['proposal_source']})")
        self.init_core(p, p["proposal_source"] == "external")
        # the detector is ready before any subscription exists (a player waiting for
        # subscribers then knows the node is ready)
        self.detector = detector if detector is not None else self.build_detector()

        self.markers_pub = self.create_publisher(self.types.MarkerArray, "~/markers", _qos(10))
        self.detections_pub = None
        if p["publish_detections"] and self.types.has_vision_msgs:
            self.detections_pub = self.create_publisher(self.types.Detection3DArray, "~/detections", _qos(10))
        self.scene: SceneFeed | None = None
        self.start_worker()
        in_qos = _qos(p["qos_depth"], reliable=p["qos"] != "sensor_data")
        Image, CameraInfo = self.types.Image, self.types.CameraInfo
        self.create_subscription(Image, "image", lambda m: self.on_input("image", 0, m), in_qos)
        self.create_subscription(Image, "depth", lambda m: self.on_input("depth", 1, m), in_qos)
        self.create_subscription(CameraInfo, "camera_info", self.on_camera_info, in_qos)
        if self.external:
            self.create_subscription(self.types.Detection2DArray, "detections2d",
                                     lambda m: self.on_input("detections2d", 2, m), in_qos)
        if p["up_source"] == "imu":
            self.subscribe_imu()
        if p["publish_scene"]:
            self.scene = self._start_scene()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f"ready: image={self.topic('image')} depth={self.topic('depth')} "
            f"camera_info={self.topic('camera_info')} -> {self.markers_pub.topic_name}"
            + (f", {self.detections_pub.topic_name}" if self.detections_pub else " (no vision_msgs: no ~/detections)")
            + f"; proposals={p['proposal_source']} up={p['up_source']} qos={p['qos']}"
            + (f"; scene in {self.scene.config.world_frame}, poses: {p['pose_source']}" if self.scene else "")
        )

    # --- what NodeCore and the scheduler use ------------------------------------------
    def log(self, level: str, text: str) -> None:
        """One line on the node's logger (``level``: info, warning or error)."""
        # one call site per severity: rclpy's logger refuses a severity change at a call site
        if level == "error":
            self.get_logger().error(text)
        elif level == "info":
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)

    def topic(self, name: str) -> str:
        """``name`` resolved (remaps, namespace)."""
        return self.resolve_topic_name(name)

    def now_ns(self) -> int:
        """The node's clock (ROS time), ns."""
        return self.get_clock().now().nanoseconds

    def subscribe_imu(self) -> None:
        """Subscribe to ``imu`` (best effort with ``qos:=sensor_data``)."""
        from sensor_msgs.msg import Imu

        self._imu_sub = self.create_subscription(Imu, "imu", self.on_imu, _qos(50, self.p["qos"] != "sensor_data"))

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        reason = self.set_parameters_checked([(prm.name, prm.value) for prm in params])
        return SetParametersResult(successful=reason is None, reason=reason or "")

    # --- scene ------------------------------------------------------------------------------
    def _start_scene(self) -> SceneFeed:
        """The scene feed, its pose subscriptions, publishers and the plan service."""
        from .poses import Tf2PoseLookup, tf2_available

        p = self.p
        tf2 = None
        if p["pose_source"] in ("auto", "tf") and tf2_available():
            tf2 = Tf2PoseLookup(self, p["world_frame"])
        feed = SceneFeed(p, self.warn, tf2)
        tf_type: Any = None
        if tf2 is None and p["pose_source"] in ("auto", "tf"):
            try:
                tf_type = importlib.import_module("tf2_msgs.msg").TFMessage
            except ImportError:
                self.warn("no_tf", "neither tf2_ros nor tf2_msgs is installed: /tf is not used for camera poses"
                          + ("" if p["pose_source"] == "auto" else " (pose_source=tf: the scene gets no pose)"),
                          period=float("inf"), level="error" if p["pose_source"] == "tf" else "warning")
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry

        classes = {"tf": tf_type, "tf_static": tf_type, "odometry": Odometry, "pose": PoseStamped}
        for kind, topic in pose_topics(p["pose_source"], p["odom_topic"], p["pose_topic"], tf_type is not None):
            # best effort takes reliable and best-effort publishers alike; /tf_static's
            # history reaches reliable late joiners only
            qos = _qos(10, latched=True) if kind == "tf_static" else _qos(50, reliable=False)
            self.create_subscription(classes[kind], topic, lambda m, k=kind: feed.add_pose(k, m), qos)
        OccupancyGrid = self.types.get_class("nav_msgs/msg/OccupancyGrid")
        self.scene_pub = self.create_publisher(self.types.MarkerArray, "~/scene", _qos(10))
        self.map_pub = self.create_publisher(OccupancyGrid, "~/map", _qos(1, latched=True))
        self.surfaces_pub = self.create_publisher(self.types.MarkerArray, "~/surfaces", _qos(1, latched=True))
        from nav_msgs.srv import GetPlan

        self.plan_srv = self.create_service(GetPlan, "~/get_plan", self._on_get_plan)
        self._start_scene_files(feed)
        self._surfaces_key: Any = None
        self._surfaces_at = -float("inf")  # monotonic time of the last ~/surfaces
        return feed

    def _start_scene_files(self, feed: SceneFeed) -> None:
        """``scene_in`` loaded into ``feed``; ``~/save_scene`` (where std_srvs is installed) and
        the periodic save to ``scene_out``."""
        p = self.p
        if p["scene_in"]:
            try:
                n = feed.load(p["scene_in"])
                self.get_logger().info(f"scene: continuing {p['scene_in']} ({n} objects)")
            except (OSError, ValueError) as e:
                self.warn("scene_in", f"scene_in {p['scene_in']}: {e}: starting a fresh map", period=float("inf"),
                          level="error")
        try:
            from std_srvs.srv import Trigger
        except ImportError:
            self.warn("no_std_srvs", "std_srvs is not installed: no ~/save_scene and ~/clear_scene services",
                      period=float("inf"))
        else:
            self.save_srv = self.create_service(Trigger, "~/save_scene", self._on_save_scene)
            self.clear_srv = self.create_service(Trigger, "~/clear_scene", self._on_clear_scene)
        if p["scene_out"] and p["scene_save_period"] > 0:
            self.save_timer = self.create_timer(float(p["scene_save_period"]), lambda: self.save_scene(False))

    def save_scene(self, always: bool = True) -> tuple[bool, str]:
        """Write the map to ``scene_out`` (``always``: even when unchanged since the last save);
        ``(written, what happened)``. Failures are logged, never raised."""
        path = self.p["scene_out"]
        if self.scene is None or not path:
            return False, "no scene_out set" if self.scene is not None else "the scene is off (publish_scene false)"
        if not always and self.scene.version == self.scene.saved_version:
            return False, "unchanged"
        try:
            n = self.scene.save(path)
        except (OSError, ValueError, TypeError) as e:
            self.warn("scene_out", f"cannot write scene_out {path}: {type(e).__name__}: {e}", level="error")
            return False, f"{type(e).__name__}: {e}"
        return True, f"{n} objects written to {path}"

    def _on_save_scene(self, request: Any, response: Any) -> Any:
        """std_srvs/srv/Trigger: write the map to ``scene_out`` now."""
        response.success, response.message = self.save_scene(True)
        return response

    def _on_clear_scene(self, request: Any, response: Any) -> Any:
        """std_srvs/srv/Trigger: forget every object, the floor and the observed surfaces."""
        if self.scene is None:  # the service exists only with the scene
            response.success, response.message = False, "the scene is off (publish_scene false)"
            return response
        n = len(self.scene.snapshot()[0])
        self.scene.clear()
        self.get_logger().info(f"scene: cleared ({n} objects forgotten)")
        response.success, response.message = True, f"cleared {n} objects"
        return response

    def _publish_scene(self, scene: SceneFeed, stamp: int) -> None:
        """~/scene and ~/map (each processed frame), ~/surfaces when they changed, at most every
        ``SURFACES_PERIOD`` s (measuring heights reads the map's stored points: milliseconds)."""
        from msg_conversion.scene import grid_to_occupancy, scene_to_markers

        objects, grid, _ = scene.snapshot()
        frame = scene.config.world_frame
        self.scene_pub.publish(scene_to_markers(objects, self.types, stamp, frame))
        self.map_pub.publish(grid_to_occupancy(grid, self.types, stamp, frame))
        self.stats.count("scene_published")
        key = surfaces_key(objects)
        if key != self._surfaces_key and time.monotonic() - self._surfaces_at >= SURFACES_PERIOD:
            from msg_conversion.surfaces import surfaces_to_markers

            from .ar import ArScene, surfaces

            found = surfaces(ArScene(objects, grid, frame, observed=scene.observed()))  # measured heights
            self.surfaces_pub.publish(surfaces_to_markers(found, self.types, stamp, frame))
            self._surfaces_key, self._surfaces_at = key, time.monotonic()

    def _on_get_plan(self, request: Any, response: Any) -> Any:
        """nav_msgs/srv/GetPlan on the current grid: an empty path when there is none."""
        from .node_scene import answer_plan

        try:
            response.plan = answer_plan(self.scene, request, self.types, self.now_ns(), self.warn)
        except Exception as e:  # noqa: BLE001 - a bad request must not stop the node
            self.warn("get_plan", f"get_plan failed: {type(e).__name__}: {e}", level="error")
        return response

    # --- output --------------------------------------------------------------------------
    def publish(self, objects: list, stamp: int, frame_id: str, frame: Any = None, up: Any = None) -> None:
        """Publish ``objects`` as ~/markers (and ~/detections) with the image's stamp (ns) and
        frame; with the scene on, fold the frame into it and publish the scene outputs."""
        from msg_conversion.markers import objects_to_markers

        try:
            markers = objects_to_markers(objects, self.types, stamp, frame_id)
        except Exception as e:  # noqa: BLE001 - e.g. NaN boxes from a broken detector
            self.warn("markers", f"cannot build markers ({type(e).__name__}: {e}): publishing an empty array",
                      level="error")
            markers = objects_to_markers([], self.types, stamp, frame_id)
            objects = []
        self.markers_pub.publish(markers)
        self.stats.count("published")
        if self.detections_pub is not None:
            try:
                from msg_conversion.detections import objects_to_detection3d_array

                self.detections_pub.publish(objects_to_detection3d_array(objects, self.types, stamp, frame_id))
            except Exception as e:  # noqa: BLE001
                self.warn("detections", f"cannot publish detections: {type(e).__name__}: {e}", level="error")
        if self.scene is None:
            return
        try:
            if frame is not None:
                self.scene.update(objects, frame.depth, frame.K, stamp, frame_id, up)
            self._publish_scene(self.scene, stamp)
        except Exception as e:  # noqa: BLE001 - the scene must never stop the detections
            self.warn("scene", f"cannot publish the scene: {type(e).__name__}: {e}", level="error")

    def destroy_node(self) -> None:
        """Stop the worker threads, write the map to ``scene_out`` if it changed since the last
        save, then destroy the node."""
        self.stop()
        if self.scene is not None and self.p["scene_out"]:
            written, what = self.save_scene(False)
            if written:
                self.get_logger().info(f"scene: {what}")
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``detector_node`` (``ros2 run shape_detector detector_node``). SIGINT
    and SIGTERM stop it cleanly (exit code 0); bad parameters exit with 1."""
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    # rclpy's own handler covers SIGINT and SIGTERM: it shuts the context down, which ends
    # spin() with ExternalShutdownException instead of an exception at an arbitrary line
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.ALL)
    node = None
    rc = 0
    try:
        node = DetectorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as e:  # noqa: BLE001 - configuration errors: say what, exit non-zero
        print(f"detector_node: {type(e).__name__}: {e}", file=sys.stderr)
        rc = 1
    finally:
        # a second signal during the cleanup must not leave a half-shut process behind
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if node is not None:
            node.stop()
            try:
                node.maybe_report(force=True)
            except Exception:  # noqa: BLE001 - the context may be gone already
                pass
            node.destroy_node()
        rclpy.try_shutdown()
    return rc


if __name__ == "__main__":
    sys.exit(main())
