"""``detector_node``: the ROS 2 node, a thin rclpy shell around the pure-Python pipeline.

Topics (relative, remap them):

* in  ``image`` (sensor_msgs/Image, colour), ``depth`` (sensor_msgs/Image 16UC1 / 32FC1,
  registered to the colour camera), ``camera_info`` (sensor_msgs/CameraInfo of the colour
  camera); optional ``imu`` (sensor_msgs/Imu, with ``up_source:=imu``) and
  ``detections2d`` (vision_msgs/Detection2DArray, with ``proposal_source:=external``).
* out ``~/markers`` (visualization_msgs/MarkerArray, reliable, one per processed frame,
  the colour image's stamp and frame) and, where vision_msgs is importable,
  ``~/detections`` (vision_msgs/Detection3DArray).

Image and depth (and external detections) are paired by
:class:`~shape_detector.sync.ApproximateTimeSynchronizer`; the latest camera_info is used.
Sets go to :class:`~shape_detector.scheduler.FrameScheduler`: newest frame first, output in
input order, frames the node cannot keep up with dropped and counted.

Bad input (wrong encodings, mismatched sizes, missing or zero camera_info, NaN depth,
empty images, detector exceptions) is logged, each distinct problem at least once, repeats
rate limited, and answered with an empty MarkerArray; it never stops the node.

Large images: with best-effort QoS (``qos:=sensor_data``) a large message travels in
fragments through the Fast DDS shared-memory segment (shape_detector/config/fastdds_shm.xml);
when fragments do not fit (segment or port queue full) the transport drops the frame before
the node sees it, without a log line anywhere; ``qos:=reliable`` delivers it. Images above
``warn_image_bytes`` are reported once per topic.

Scheduling lives in :mod:`shape_detector.scheduler`, statistics and rate-limited warnings in
:mod:`shape_detector.node_stats`, parameters and their validation in
:mod:`shape_detector.node_params`; this module is the rclpy wiring.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from typing import Any, Callable

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .imu_gravity import ImuGravityFilter
from .node_params import DETECTOR_ATTRS, PARAMETERS, REBUILD, apply_to_detector, build_detector, validate, validate_all
from .node_stats import NodeStats, WarningLimiter, problem_key, stats_line
from .scheduler import FrameScheduler, FrameSet
from .sync import ApproximateTimeSynchronizer, header_stamp_ns


def _unit(v: Any) -> np.ndarray:
    a = np.asarray(list(v), dtype=np.float64).reshape(-1)
    return a / np.linalg.norm(a)


def _descriptor(name: str) -> ParameterDescriptor:
    spec = PARAMETERS[name]
    kwargs: dict[str, Any] = dict(description=spec.doc, read_only=spec.node == "read_only",
                                  dynamic_typing=spec.length is not None)
    if spec.range is not None and spec.kind is float:
        lo, hi = spec.range
        kwargs["floating_point_range"] = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    elif spec.range is not None:
        lo, hi = spec.range
        kwargs["integer_range"] = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    if spec.choices:
        kwargs["additional_constraints"] = "one of: " + ", ".join(spec.choices)
    return ParameterDescriptor(**kwargs)


class DetectorNode(Node):
    """The detector node. ``detector``: an object with ``detect(rgb, depth, K, boxes2d=,
    up=)`` to use instead of building one (tests); ``detector_factory``: a callable taking
    ShapeDetector's keyword arguments (overrides the ``detector_factory`` parameter).
    Other keyword arguments go to :class:`rclpy.node.Node` (``context``,
    ``parameter_overrides``, ``namespace``, ``cli_args``...)."""

    def __init__(self, node_name: str = "shape_detector", *, detector: Any = None,
                 detector_factory: Callable[..., Any] | None = None, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        from msg_conversion.msgtypes import rclpy_types

        self.stats = NodeStats()
        self._limiter = WarningLimiter()
        self._period_start = time.monotonic()
        self._last_reported_synced = -1
        self._scheduler: FrameScheduler | None = None
        for name in PARAMETERS:
            self.declare_parameter(name, PARAMETERS[name].default, _descriptor(name))
        self.p: dict[str, Any] = {name: self.get_parameter(name).value for name in PARAMETERS}
        problems = validate_all(self.p)
        if problems:
            raise ValueError("invalid parameters: " + "; ".join(problems))

        self.types = rclpy_types()
        self._factory = detector_factory
        if self.p["proposal_source"] == "external" and not self.types.has_vision_msgs:
            self.get_logger().error("proposal_source=external needs vision_msgs (Detection2DArray), which is not "
                                    "installed: using geometric proposals")
            self.p["proposal_source"] = "geometric"
        self.external = self.p["proposal_source"] == "external"

        # the detector is ready before any subscription exists (a player waiting for
        # subscribers then knows the node is ready)
        self.detector = detector if detector is not None else self.build_detector()

        self.imu_filter = ImuGravityFilter(self.p["imu_time_constant"], self.p["imu_to_camera"])
        self.sync = ApproximateTimeSynchronizer(3 if self.external else 2, self.p["sync_queue_size"], self.p["sync_slop"])
        self.sync.register_callback(self._on_synced)
        self._camera_info: Any = None
        self.info_event = threading.Event()
        self._scheduler = FrameScheduler(self, bool(self.p["pipeline"]))

        out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                             durability=DurabilityPolicy.VOLATILE)
        self.markers_pub = self.create_publisher(self.types.MarkerArray, "~/markers", out_qos)
        self.detections_pub = None
        if self.p["publish_detections"] and self.types.has_vision_msgs:
            self.detections_pub = self.create_publisher(self.types.Detection3DArray, "~/detections", out_qos)
        reliability = ReliabilityPolicy.BEST_EFFORT if self.p["qos"] == "sensor_data" else ReliabilityPolicy.RELIABLE
        self._in_qos = in_qos = QoSProfile(depth=self.p["qos_depth"], reliability=reliability,
                                           history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
        Image, CameraInfo = self.types.Image, self.types.CameraInfo
        self.create_subscription(Image, "image", lambda m: self._on_input("image", 0, m), in_qos)
        self.create_subscription(Image, "depth", lambda m: self._on_input("depth", 1, m), in_qos)
        self.create_subscription(CameraInfo, "camera_info", self._on_camera_info, in_qos)
        if self.external:
            self.create_subscription(self.types.Detection2DArray, "detections2d",
                                     lambda m: self._on_input("detections2d", 2, m), in_qos)
        self._imu_sub = None
        if self.p["up_source"] == "imu":
            self._subscribe_imu()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f"ready: image={self.topic('image')} depth={self.topic('depth')} "
            f"camera_info={self.topic('camera_info')} -> {self.markers_pub.topic_name}"
            + (f", {self.detections_pub.topic_name}" if self.detections_pub else " (no vision_msgs: no ~/detections)")
            + f"; proposals={self.p['proposal_source']} up={self.p['up_source']} qos={self.p['qos']}"
        )

    # --- what the scheduler uses ------------------------------------------------------
    @property
    def counters(self) -> Any:
        """The statistics counters (a Counter; read-only use)."""
        return self.stats.counters

    @property
    def mailbox(self) -> Any:
        return self._scheduler.mailbox if self._scheduler else None

    @property
    def _worker(self) -> threading.Thread | None:
        return self._scheduler.worker if self._scheduler else None

    @property
    def _finisher(self) -> threading.Thread | None:
        return self._scheduler.finisher if self._scheduler else None

    def topic(self, name: str) -> str:
        """``name`` resolved (remaps, namespace)."""
        return self.resolve_topic_name(name)

    def camera_info(self) -> Any:
        return self._camera_info

    def now_ns(self) -> int:
        """The node's clock (ROS time), ns."""
        return self.get_clock().now().nanoseconds

    def build_detector(self) -> Any:
        """A detector built from the parameters (``detector_factory`` or ShapeDetector), warmed up."""
        return build_detector(self.p, self.external, self._factory, self.get_logger().info,
                              self.get_logger().warning)

    # --- parameters -------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        problems = [p for p in (validate(prm.name, prm.value) for prm in params) if p]
        if problems:
            return SetParametersResult(successful=False, reason="; ".join(problems))
        try:
            for prm in params:
                if prm.name in PARAMETERS:
                    self._apply(prm.name, prm.value)
        except (ValueError, TypeError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _apply(self, name: str, value: Any) -> None:
        """Take a validated new value of parameter ``name`` into use."""
        self.p[name] = value
        if name in ("sync_slop", "sync_queue_size"):
            self.sync.configure(queue_size=self.p["sync_queue_size"], slop=self.p["sync_slop"])
        elif name in DETECTOR_ATTRS and apply_to_detector(self.detector, name, value):
            pass
        elif (name in DETECTOR_ATTRS or name in REBUILD) and self._scheduler is not None:
            self._scheduler.rebuild = True
        elif name == "imu_to_camera":
            self.imu_filter.set_imu_to_camera(list(value))
        elif name == "imu_time_constant":
            self.imu_filter.time_constant = float(value)
        elif name == "up_source" and value == "imu" and self._imu_sub is None:
            self._subscribe_imu()

    def _subscribe_imu(self) -> None:
        from sensor_msgs.msg import Imu

        imu_qos = QoSProfile(depth=50, reliability=self._in_qos.reliability, history=HistoryPolicy.KEEP_LAST)
        self._imu_sub = self.create_subscription(Imu, "imu", self._on_imu, imu_qos)

    # --- callbacks (executor thread; never raise) ----------------------------------------
    def _on_input(self, name: str, index: int, msg: Any) -> None:
        self.stats.count(f"received_{name}")
        try:
            if header_stamp_ns(msg) is None:
                self.warn("headerless", f"{name} message without header.stamp ignored")
                return
            size = len(getattr(msg, "data", b""))
            if size > int(self.p["warn_image_bytes"]):
                self.warn("large_image", f"{self.topic(name)}: {size / 2**20:.1f} MiB messages (over "
                          f"warn_image_bytes={self.p['warn_image_bytes']}); with best-effort QoS, messages larger "
                          "than the shared-memory segment are dropped in transport, unseen: use qos:=reliable",
                          period=float("inf"), key="large_image|" + name)
            self.sync.add(index, msg)
        except Exception as e:  # noqa: BLE001
            self.warn("callback", f"{name} callback failed: {type(e).__name__}: {e}")

    def _on_camera_info(self, msg: Any) -> None:
        self.stats.count("received_camera_info")
        self._camera_info = msg
        self.info_event.set()

    def _on_imu(self, msg: Any) -> None:
        self.stats.count("received_imu")
        try:
            a = msg.linear_acceleration
            if not self.imu_filter.update((a.x, a.y, a.z), header_stamp_ns(msg)):
                self.warn("imu_rejected", "IMU sample rejected (non-finite or far from 1 g: moving?)", period=30.0)
        except Exception as e:  # noqa: BLE001
            self.warn("imu", f"IMU message unusable: {type(e).__name__}: {e}")

    def _on_synced(self, *msgs: Any) -> None:
        fs = FrameSet(image=msgs[0], depth=msgs[1], camera_info=self._camera_info,
                      detections2d=msgs[2] if len(msgs) > 2 else None, up=self._current_up(),
                      synced_at=time.monotonic())
        if self._scheduler is not None:
            self._scheduler.offer(fs)

    def _current_up(self) -> np.ndarray | None:
        src = self.p["up_source"]
        if src == "fixed":
            return _unit(self.p["up"])
        if src == "imu":
            up = self.imu_filter.up
            if up is None:
                self.warn("no_imu", "up_source=imu but no usable IMU sample yet: estimating up from the scene")
            return up
        return None

    # --- output, logging, statistics ----------------------------------------------------
    def publish(self, objects: list, stamp: int, frame_id: str) -> None:
        """Publish ``objects`` as ~/markers (and ~/detections) with the image's stamp (ns) and frame."""
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

    def warn(self, kind: str, text: str, period: float = 5.0, level: str = "warning", key: str | None = None) -> None:
        """Log ``text`` the first time its problem (``key``, default: ``kind`` + the text with
        numbers blanked) occurs, then at most every ``period`` s with the count held back."""
        held = self._limiter.admit(key or problem_key(kind, text), time.monotonic(), period)
        if held is None:
            return
        if held:
            text += f" ({held} more since the last report)"
        # one call site per severity: rclpy's logger refuses a severity change at a call site
        try:
            if level == "error":
                self.get_logger().error(text)
            elif level == "info":
                self.get_logger().info(text)
            else:
                self.get_logger().warning(text)
        except Exception:  # noqa: BLE001 - logging must never take the node down
            print(f"[shape_detector] {level}: {text}", file=sys.stderr)

    def get_stats(self) -> dict[str, Any]:
        """Counters plus latency (stamp -> publish, plausible stamps only), sync -> publish
        and detector time p50/p95, ms."""
        out = self.stats.snapshot()
        out["dropped"] = self.mailbox.dropped if self.mailbox is not None else 0
        out["sync_evicted"] = self.sync.evicted
        return out

    def maybe_report(self, force: bool = False) -> None:
        """Log the statistics line every ``stats_period`` s (``force``: now, on stdout: the
        context, and so the rosout logger, may be shut down)."""
        period = float(self.p["stats_period"])
        now = time.monotonic()
        if not force and (period <= 0 or now - self._period_start < period):
            return
        n = self.stats.take_period()
        dt, self._period_start = max(now - self._period_start, 1e-9), now
        s = self.get_stats()
        if n == 0 and not force:
            received = {k[9:]: v for k, v in s.items() if k.startswith("received_")}
            if not received:
                self.warn("no_input", "no input yet on " + ", ".join(
                    self.topic(t) for t in ("image", "depth", "camera_info")), period=max(period, 30.0))
            elif s.get("synced", 0) == 0:
                self.warn("no_sync", f"receiving messages but none synchronised (counts: {received}); "
                          f"check the stamps and sync_slop={self.p['sync_slop']}", period=max(period, 30.0))
            if s.get("synced", 0) == self._last_reported_synced:
                return
        self._last_reported_synced = s.get("synced", 0)
        if force:
            print(f"[shape_detector] at exit: {stats_line(s, n / dt)}", flush=True)
        else:
            self.get_logger().info(stats_line(s, n / dt))

    # --- shutdown ---------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop the worker threads (idempotent, bounded in time)."""
        if self._scheduler is not None and not self._scheduler.stop():
            print("[shape_detector] a worker thread is still busy at shutdown; leaving it (daemon)", file=sys.stderr)

    def destroy_node(self) -> None:
        self.stop()
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
