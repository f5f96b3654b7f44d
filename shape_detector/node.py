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
:class:`~shape_detector.sync.ApproximateTimeSynchronizer`; the latest camera_info is
used. Sets go through a one-slot :class:`~shape_detector.sync.LatestMailbox` to a worker
thread running the detector, so the node never falls behind: a newer set replaces one not
yet processed (counted as dropped). With ``pipeline`` (default) the worker is two threads:
the first checks the input and runs the detector's ``prepare`` (gravity, proposals,
frustums) on frame N+1 while the second runs ``finish`` (network, post-processing) on
frame N and publishes; the network's first pass moves to the first thread when that
balances the two better (``pipeline_split``). The first takes a new frame only when the second has taken the
last one, so output stays in input order and a frame waits for at most one other.

Bad input (wrong encodings, mismatched sizes, missing or zero camera_info, NaN depth,
empty images, detector exceptions) is logged (rate limited) and answered with an empty
MarkerArray; it never stops the node.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .bag_io import FrameError, prepare_frame
from .imu_gravity import ImuGravityFilter
from .sync import ApproximateTimeSynchronizer, LatestMailbox, header_stamp_ns

#: name -> (default, description, read_only, extra descriptor kwargs)
PARAMETERS: dict[str, tuple[Any, str, bool, dict]] = {
    "weights": ("", "network weights file; empty = the packaged default (reloaded when changed)", False, {}),
    "device": ("cpu", "torch device: cpu, cuda, cuda:0 ... (detector reloaded when changed)", False, {}),
    "score_threshold": (0.3, "minimum detection score", False,
                        {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]}),
    "max_objects": (10, "built-in proposals (frustums) per frame, best proposer score first: the speed knob "
                    "(10: real time on 2 cores; ShapeDetector and the offline tools use 25, the accuracy setting)", False,
                    {"integer_range": [IntegerRange(from_value=1, to_value=1000, step=1)]}),
    "nms_decay": (0.1, "built-in proposals: score factor of the boxes 3D NMS suppresses, kept after the others "
                  "(0 = drop them; with score_threshold 0.3 none is published)", False,
                  {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]}),
    "refine": (True, "built-in proposals: run each frustum scored >= refine_min_score a second time with its "
               "predicted class given (that class's box prior)", False, {}),
    "refine_min_score": (0.3, "score (after the proposal classifier) a built-in proposal needs for the class-given "
                         "second pass", False,
                         {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]}),
    "free_space": (True, "shrink boxes out of space the depth map sees through (side faces; the top of "
                   "flat-topped classes), never past measured points", False, {}),
    "classifier": ("", "proposal classifier file that re-decides the class of built-in proposals; empty = the "
                   "packaged one, 'none' = off (the network's class head decides) (detector reloaded when "
                   "changed)", False, {}),
    "workers": (1, "threads the network splits a frame's frustums over (single-threaded ops each; 1 = serial; "
                "2 is faster with pipeline false, slower with it)", True,
                {"integer_range": [IntegerRange(from_value=1, to_value=64, step=1)]}),
    "pipeline": (True, "two worker threads: the next frame's gravity, proposals and frustums run while the "
                 "network finishes the current one (higher throughput, output in input order); false = one thread",
                 True, {}),
    "pipeline_split": ("auto", "with pipeline: where the network's first pass runs: 'prepare' (second thread, "
                       "with the rest of the network), 'network' (first thread, after prepare) or 'auto' (whichever "
                       "balances the two threads better, judged from the last frame's stage times)", True, {}),
    "precision": ("auto", "network arithmetic: 'auto' (bfloat16 for 4 or more frustums on CPUs with AMX, "
                  "else fp32), 'fp32' or 'bf16' (faster with many frustums on AMX / AVX512-BF16 CPUs, "
                  "much slower without)", True, {}),
    "mirror_tta": ("given", "also run each frustum mirrored and average: 'given' (external boxes only), "
                   "'always' or 'never'", True, {}),
    "proposal_source": ("geometric", "2D proposals: 'geometric' (built in) or 'external' (the detections2d "
                        "topic, vision_msgs/Detection2DArray, synchronised with the image)", True, {}),
    "sync_slop": (0.02, "approximate time synchroniser slop between image and depth stamps, seconds", False,
                  {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=10.0, step=0.0)]}),
    "sync_queue_size": (10, "synchroniser queue size per input topic", False,
                        {"integer_range": [IntegerRange(from_value=1, to_value=1000, step=1)]}),
    "depth_scale": (0.0, "metres per raw unit of integer depth images; 0 = by encoding (16UC1: 0.001, 32FC1: 1)",
                    False, {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=1000.0, step=0.0)]}),
    "size_mismatch": ("rescale", "depth and colour of different sizes: 'rescale' (colour resized to the depth "
                      "size, intrinsics scaled) or 'skip' the frame", False, {}),
    "up_source": ("estimate", "gravity direction: 'estimate' (from the scene), 'fixed' (parameter up) or "
                  "'imu' (the imu topic, low-passed)", False, {}),
    "up": ([0.0, -1.0, 0.0], "fixed gravity-up vector in the camera optical frame (up_source=fixed; normalised)",
           False, {"dynamic_typing": True}),
    "imu_to_camera": ([0.0, 0.0, 0.0, 1.0], "rotation IMU frame -> camera optical frame as quaternion x, y, z, w "
                      "(identity: the IMU reports in the camera optical frame)", False, {"dynamic_typing": True}),
    "imu_time_constant": (0.5, "low-pass time constant of the IMU gravity filter, seconds", False,
                          {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=60.0, step=0.0)]}),
    "qos": ("sensor_data", "input QoS: 'sensor_data' (best effort, depth 5) or 'reliable'", True, {}),
    "qos_depth": (5, "input subscription queue depth", True,
                  {"integer_range": [IntegerRange(from_value=1, to_value=100, step=1)]}),
    "publish_detections": (True, "publish ~/detections (vision_msgs/Detection3DArray) when vision_msgs is installed",
                           True, {}),
    "stats_period": (10.0, "seconds between throughput / latency log lines (0 = off)", False,
                     {"floating_point_range": [FloatingPointRange(from_value=0.0, to_value=3600.0, step=0.0)]}),
    "detector_factory": ("", "'package.module:callable' building the detector (same keyword arguments as "
                         "ShapeDetector); empty = shape_detector.detector.ShapeDetector", True, {}),
}

_CHOICES = {
    "pipeline_split": ("auto", "prepare", "network"),
    "proposal_source": ("geometric", "external"),
    "size_mismatch": ("rescale", "skip"),
    "up_source": ("estimate", "fixed", "imu"),
    "qos": ("sensor_data", "reliable"),
}
_REBUILD = ("weights", "device", "classifier")
#: parameters the node sets on a built detector that has the attribute (custom factories
#: need not take them as constructor arguments); dynamic
_DETECTOR_ATTRS = ("score_threshold", "max_objects", "nms_decay", "refine", "refine_min_score", "free_space")


@dataclass
class FrameSet:
    """One synchronised input set waiting for the worker."""

    image: Any
    depth: Any
    camera_info: Any
    detections2d: Any
    up: np.ndarray | None
    synced_at: float  # time.monotonic()


@dataclass
class _Job:
    """A frame between the worker's two stages: what is left to run and to publish."""

    fs: FrameSet
    stamp: int
    frame_id: str
    detector: Any = None  # the detector that prepared the frame finishes it
    prepared: Any = None  # its prepare() output; None: nothing left to run
    objects: list = field(default_factory=list)
    detect_ms: float | None = None  # detector time so far; None: the detector did not succeed


def _unit(v: Any, what: str) -> np.ndarray:
    a = np.asarray(list(v), dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-9:
        raise ValueError(f"{what} must be 3 finite numbers, not all zero, got {list(v)}")
    return a / np.linalg.norm(a)


class DetectorNode(Node):
    """The detector node. ``detector``: an object with ``detect(rgb, depth, K, boxes2d=,
    up=)`` to use instead of building one (tests); ``detector_factory``: a callable taking
    ShapeDetector's keyword arguments (overrides the ``detector_factory`` parameter).
    Other keyword arguments go to :class:`rclpy.node.Node` (``context``,
    ``parameter_overrides``, ``namespace``, ``cli_args``...)."""

    def __init__(
        self,
        node_name: str = "shape_detector",
        *,
        detector: Any = None,
        detector_factory: Callable[..., Any] | None = None,
        **node_kwargs: Any,
    ) -> None:
        super().__init__(node_name, **node_kwargs)
        from msg_conversion.msgtypes import rclpy_types

        self._lock = threading.Lock()
        self.counters: Counter = Counter()
        self._warned: dict[str, tuple[float, int]] = {}
        self._latency_ms: deque[float] = deque(maxlen=2000)
        self._pipeline_ms: deque[float] = deque(maxlen=2000)
        self._detect_ms: deque[float] = deque(maxlen=2000)
        self._period_processed = 0
        self._period_start = time.monotonic()
        self._last_reported_synced = -1
        self._rebuild = False
        self._running = True

        for name, (default, desc, read_only, extra) in PARAMETERS.items():
            kwargs = dict(description=desc, read_only=read_only, **extra)
            if name in _CHOICES:
                kwargs["additional_constraints"] = "one of: " + ", ".join(_CHOICES[name])
            self.declare_parameter(name, default, ParameterDescriptor(**kwargs))
        self.p: dict[str, Any] = {name: self.get_parameter(name).value for name in PARAMETERS}
        problems = [self._validate(name, value) for name, value in self.p.items()]
        problems = [p for p in problems if p]
        if problems:
            raise ValueError("invalid parameters: " + "; ".join(problems))

        self.types = rclpy_types()
        self._factory = detector_factory
        if self.p["proposal_source"] == "external" and not self.types.has_vision_msgs:
            self.get_logger().error(
                "proposal_source=external needs vision_msgs (Detection2DArray), which is not installed: "
                "using geometric proposals"
            )
            self.p["proposal_source"] = "geometric"
        self.external = self.p["proposal_source"] == "external"

        # the detector is ready before any subscription exists (a player waiting for
        # subscribers then knows the node is ready)
        self.detector = detector if detector is not None else self._build_detector()

        self.imu_filter = ImuGravityFilter(self.p["imu_time_constant"], self.p["imu_to_camera"])
        self.sync = ApproximateTimeSynchronizer(3 if self.external else 2, self.p["sync_queue_size"], self.p["sync_slop"])
        self.sync.register_callback(self._on_synced)
        self.mailbox: LatestMailbox[FrameSet] = LatestMailbox()
        self._camera_info: Any = None
        self._info_event = threading.Event()

        out_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                             durability=DurabilityPolicy.VOLATILE)
        self.markers_pub = self.create_publisher(self.types.MarkerArray, "~/markers", out_qos)
        self.detections_pub = None
        if self.p["publish_detections"] and self.types.has_vision_msgs:
            self.detections_pub = self.create_publisher(self.types.Detection3DArray, "~/detections", out_qos)

        if self.p["qos"] == "sensor_data":
            in_qos = QoSProfile(depth=self.p["qos_depth"], reliability=ReliabilityPolicy.BEST_EFFORT,
                                history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
        else:
            in_qos = QoSProfile(depth=self.p["qos_depth"], reliability=ReliabilityPolicy.RELIABLE,
                                history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
        self._in_qos = in_qos
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

        # second stage (network + publishing) of the pipelined worker; None: one thread does all
        self._handoff: LatestMailbox[_Job] | None = LatestMailbox() if self.p["pipeline"] else None
        self._finisher: threading.Thread | None = None
        if self._handoff is not None:
            self._finisher = threading.Thread(target=self._finish_loop, name="shape_detector_finisher", daemon=True)
            self._finisher.start()
        self._worker = threading.Thread(target=self._work, name="shape_detector_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ready: image={self.resolve_topic_name('image')} depth={self.resolve_topic_name('depth')} "
            f"camera_info={self.resolve_topic_name('camera_info')} -> {self.markers_pub.topic_name}"
            + (f", {self.detections_pub.topic_name}" if self.detections_pub else " (no vision_msgs: no ~/detections)")
            + f"; proposals={self.p['proposal_source']} up={self.p['up_source']} qos={self.p['qos']}"
        )

    # --- detector ---------------------------------------------------------------------
    def _build_detector(self) -> Any:
        from .replay import load_factory

        kwargs = dict(
            weights=self.p["weights"] or None,
            device=self.p["device"],
            score_threshold=float(self.p["score_threshold"]),
            max_objects=int(self.p["max_objects"]),
            workers=int(self.p["workers"]),
            precision=str(self.p["precision"]),
            mirror_tta=str(self.p["mirror_tta"]),
            # external 2D boxes come with every frame: no built-in proposer needed
            proposals="none" if self.external else "geometric",
        )
        from .detector import classifier_option

        if (classifier := classifier_option(self.p["classifier"])) is not None:
            kwargs["classifier"] = classifier
        factory = self._factory
        if factory is None and self.p["detector_factory"]:
            factory = load_factory(self.p["detector_factory"])
        if factory is None:
            from .detector import ShapeDetector

            factory = ShapeDetector
        t = time.perf_counter()
        det = factory(**kwargs)
        for name in ("nms_decay", "refine", "refine_min_score", "free_space"):  # not constructor arguments: custom
            if hasattr(det, name):  # factories need not take them
                setattr(det, name, type(getattr(det, name))(self.p[name]))
        if hasattr(det, "warm_up"):  # first-call costs now, not on the first camera frame
            try:
                det.warm_up()
            except Exception as exc:  # a failed warm-up must not stop the node; frames will tell
                self.get_logger().warning(f"detector warm-up failed: {exc!r}")
        self.get_logger().info(
            f"detector {type(det).__name__} ready in {time.perf_counter() - t:.2f} s "
            f"(weights={kwargs['weights'] or 'default'}, device={kwargs['device']})"
        )
        return det

    # --- parameters -------------------------------------------------------------------
    def _validate(self, name: str, value: Any) -> str | None:
        if name in _CHOICES and value not in _CHOICES[name]:
            return f"{name} must be one of {_CHOICES[name]}, got {value!r}"
        try:
            if name == "up":
                _unit(value, "up")
            elif name == "imu_to_camera":
                ImuGravityFilter(imu_to_camera=list(value))
        except (ValueError, TypeError) as e:
            return f"{name}: {e}"
        return None

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for prm in params:
            if prm.name in PARAMETERS:
                problem = self._validate(prm.name, prm.value)
                if problem:
                    return SetParametersResult(successful=False, reason=problem)
        try:
            for prm in params:
                if prm.name not in PARAMETERS:
                    continue
                self.p[prm.name] = prm.value
                if prm.name in ("sync_slop", "sync_queue_size"):
                    self.sync.configure(queue_size=self.p["sync_queue_size"], slop=self.p["sync_slop"])
                elif prm.name in _DETECTOR_ATTRS:
                    if hasattr(self.detector, prm.name):
                        setattr(self.detector, prm.name, prm.value)
                    else:
                        self._rebuild = True
                elif prm.name in _REBUILD:
                    self._rebuild = True
                elif prm.name == "imu_to_camera":
                    self.imu_filter.set_imu_to_camera(list(prm.value))
                elif prm.name == "imu_time_constant":
                    self.imu_filter.time_constant = float(prm.value)
                elif prm.name == "up_source" and prm.value == "imu" and self._imu_sub is None:
                    self._subscribe_imu()
        except (ValueError, TypeError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _subscribe_imu(self) -> None:
        from sensor_msgs.msg import Imu

        imu_qos = QoSProfile(depth=50, reliability=self._in_qos.reliability, history=HistoryPolicy.KEEP_LAST)
        self._imu_sub = self.create_subscription(Imu, "imu", self._on_imu, imu_qos)

    # --- callbacks (executor thread; never raise) ----------------------------------------
    def _on_input(self, name: str, index: int, msg: Any) -> None:
        with self._lock:
            self.counters[f"received_{name}"] += 1
        try:
            if header_stamp_ns(msg) is None:
                self._warn("headerless", f"{name} message without header.stamp ignored")
                return
            self.sync.add(index, msg)
        except Exception as e:  # noqa: BLE001
            self._warn("callback", f"{name} callback failed: {type(e).__name__}: {e}")

    def _on_camera_info(self, msg: Any) -> None:
        with self._lock:
            self.counters["received_camera_info"] += 1
        self._camera_info = msg
        self._info_event.set()

    def _on_imu(self, msg: Any) -> None:
        with self._lock:
            self.counters["received_imu"] += 1
        try:
            a = msg.linear_acceleration
            if not self.imu_filter.update((a.x, a.y, a.z), header_stamp_ns(msg)):
                self._warn("imu_rejected", "IMU sample rejected (non-finite or far from 1 g: moving?)", period=30.0)
        except Exception as e:  # noqa: BLE001
            self._warn("imu", f"IMU message unusable: {type(e).__name__}: {e}")

    def _on_synced(self, *msgs: Any) -> None:
        fs = FrameSet(
            image=msgs[0],
            depth=msgs[1],
            camera_info=self._camera_info,
            detections2d=msgs[2] if len(msgs) > 2 else None,
            up=self._current_up(),
            synced_at=time.monotonic(),
        )
        with self._lock:
            self.counters["synced"] += 1
        if self.mailbox.put(fs) is not None:
            with self._lock:
                self.counters["dropped"] += 1

    def _current_up(self) -> np.ndarray | None:
        src = self.p["up_source"]
        if src == "fixed":
            return _unit(self.p["up"], "up")
        if src == "imu":
            up = self.imu_filter.up
            if up is None:
                self._warn("no_imu", "up_source=imu but no usable IMU sample yet: estimating up from the scene")
            return up
        return None

    # --- logging helpers ------------------------------------------------------------------
    def _warn(self, key: str, text: str, period: float = 5.0, level: str = "warning") -> None:
        """Log ``text`` at once the first time ``key`` occurs, then at most every ``period``
        seconds (with the number of suppressed repeats)."""
        now = time.monotonic()
        with self._lock:
            last, suppressed = self._warned.get(key, (-1e9, 0))
            if now - last < period:
                self._warned[key] = (last, suppressed + 1)
                return
            self._warned[key] = (now, 0)
        if suppressed:
            text += f" ({suppressed} more since the last report)"
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

    # --- worker -----------------------------------------------------------------------------
    def _work(self) -> None:
        """First stage: input checks and the detector's pre-network work; hands the frame to
        the second stage (or, without ``pipeline``, finishes it itself)."""
        while self._running:
            try:
                # pipelined: take a new frame only once the second stage has taken the last
                # one, so the frame prepared is the newest and waits for at most one other
                if self._handoff is not None and not self._handoff.wait_empty(timeout=0.2):
                    self._maybe_report()
                    continue
                fs = self.mailbox.get(timeout=0.2)
                if fs is not None and self._running:
                    try:
                        job = self._prepare(fs)
                        if self._handoff is None:
                            self._complete(job)
                        else:
                            self._handoff.put(job)
                    except Exception as e:  # noqa: BLE001 - the worker must survive anything
                        self._count_error(e)
                self._maybe_report()
            except Exception as e:  # noqa: BLE001
                print(f"[shape_detector] worker: {type(e).__name__}: {e}", file=sys.stderr)
                time.sleep(0.1)

    def _finish_loop(self) -> None:
        """Second stage of the pipelined worker: network, post-processing, publishing."""
        assert self._handoff is not None
        while self._running:
            job = self._handoff.get(timeout=0.2)
            if job is None:
                continue
            try:
                self._complete(job)
            except Exception as e:  # noqa: BLE001 - the worker must survive anything
                self._count_error(e)

    def _count_error(self, e: Exception) -> None:
        with self._lock:
            self.counters["errors"] += 1
        self._warn("worker", f"frame processing failed: {type(e).__name__}: {e}", level="error")

    def _detector_failed(self, stamp: int, e: Exception) -> None:
        with self._lock:
            self.counters["detector_errors"] += 1
        self._warn("detector", f"detector failed on frame {stamp / 1e9:.3f}: {type(e).__name__}: {e}", level="error")

    def _prepare(self, fs: FrameSet) -> _Job:
        """Input checks and, for a usable frame, the detector's work up to the network (all
        of it without ``pipeline`` or when the detector has no ``prepare``/``finish``)."""
        if self._rebuild:
            self._rebuild = False
            try:
                self.detector = self._build_detector()
            except Exception as e:  # noqa: BLE001
                self._warn("rebuild", f"cannot rebuild the detector, keeping the old one: {type(e).__name__}: {e}",
                           level="error", period=0.0)
        job = _Job(fs, int(header_stamp_ns(fs.image) or 0), str(getattr(fs.image.header, "frame_id", "") or ""))
        if not job.frame_id:
            self._warn("frame_id", "colour image has an empty header.frame_id: markers will have no frame", 60.0)
        info = fs.camera_info
        if info is None:
            # the executor may hand over image + depth before a camera_info that arrived
            # with them: give the first one a moment
            if not self._info_event.is_set():
                self._info_event.wait(0.1)
            info = self._camera_info
        try:
            pf = prepare_frame(
                fs.image, fs.depth, info,
                depth_scale=float(self.p["depth_scale"]) or None,
                size_mismatch=self.p["size_mismatch"],
                detections2d=fs.detections2d,
            )
        except FrameError as e:
            with self._lock:
                self.counters[f"skipped_{e.kind}"] += 1
            if e.kind == "camera_info" and info is None:
                text = f"no camera_info received on {self.resolve_topic_name('camera_info')} yet: frame skipped"
            else:
                text = f"frame skipped: {e}"
            self._warn("skip:" + e.kind, text)
            return job
        for note in pf.notes:
            self._warn("note:" + note.split(":")[0], note, period=30.0)
        if pf.valid_depth_fraction == 0.0:
            with self._lock:
                self.counters["skipped_no_depth"] += 1
            return job
        det = self.detector
        td = time.perf_counter()
        try:
            if self._handoff is not None and hasattr(det, "prepare") and hasattr(det, "finish"):
                job.prepared = det.prepare(pf.rgb, pf.depth, pf.K, boxes2d=pf.boxes2d, up=fs.up)
                job.detector = det
                if hasattr(det, "first_pass") and self._first_pass_early(det):
                    det.first_pass(job.prepared)
                    with self._lock:
                        self.counters["first_pass_early"] += 1
            else:
                job.objects = list(det.detect(pf.rgb, pf.depth, pf.K, boxes2d=pf.boxes2d, up=fs.up))
        except Exception as e:  # noqa: BLE001
            self._detector_failed(job.stamp, e)
        else:
            job.detect_ms = (time.perf_counter() - td) * 1e3
        return job

    def _first_pass_early(self, det: Any) -> bool:
        """Whether this thread (the first stage) also runs the network's first pass."""
        split = self.p["pipeline_split"]
        if split != "auto":
            return split == "network"
        from .detector import first_pass_early

        return first_pass_early(getattr(det, "last_timing", None))

    def _complete(self, job: _Job) -> None:
        """The rest of the detector's work on ``job`` (if any), then publish and count."""
        if job.prepared is not None:
            td = time.perf_counter()
            try:
                job.objects = list(job.detector.finish(job.prepared))
            except Exception as e:  # noqa: BLE001
                job.objects, job.detect_ms = [], None
                self._detector_failed(job.stamp, e)
            else:
                job.detect_ms = (job.detect_ms or 0.0) + (time.perf_counter() - td) * 1e3
            job.prepared = None
        self._publish(job.objects, job.stamp, job.frame_id)
        now_ns = self.get_clock().now().nanoseconds
        with self._lock:
            if job.detect_ms is not None:
                self._detect_ms.append(job.detect_ms)
            self.counters["processed"] += 1
            self.counters["objects"] += len(job.objects)
            self._period_processed += 1
            if job.stamp > 0:
                self._latency_ms.append((now_ns - job.stamp) / 1e6)
            self._pipeline_ms.append((time.monotonic() - job.fs.synced_at) * 1e3)

    def _publish(self, objects: list, stamp: int, frame_id: str) -> None:
        from msg_conversion.markers import objects_to_markers

        try:
            markers = objects_to_markers(objects, self.types, stamp, frame_id)
        except Exception as e:  # noqa: BLE001 - e.g. NaN boxes from a broken detector
            self._warn("markers", f"cannot build markers ({type(e).__name__}: {e}): publishing an empty array",
                       level="error")
            markers = objects_to_markers([], self.types, stamp, frame_id)
            objects = []
        self.markers_pub.publish(markers)
        with self._lock:
            self.counters["published"] += 1
        if self.detections_pub is not None:
            try:
                from msg_conversion.detections import objects_to_detection3d_array

                self.detections_pub.publish(objects_to_detection3d_array(objects, self.types, stamp, frame_id))
            except Exception as e:  # noqa: BLE001
                self._warn("detections", f"cannot publish detections: {type(e).__name__}: {e}", level="error")

    # --- statistics -------------------------------------------------------------------------
    def get_stats(self) -> dict[str, Any]:
        """Counters plus latency (stamp -> publish) and detector time percentiles, ms."""
        with self._lock:
            out: dict[str, Any] = dict(self.counters)
            lat = list(self._latency_ms)
            det = list(self._detect_ms)
            pipe = list(self._pipeline_ms)
        out["dropped"] = self.mailbox.dropped
        out["sync_evicted"] = self.sync.evicted
        for key, vals in (("latency", lat), ("detect", det), ("pipeline", pipe)):
            if vals:
                out[f"{key}_p50_ms"] = float(np.percentile(vals, 50))
                out[f"{key}_p95_ms"] = float(np.percentile(vals, 95))
        return out

    def _maybe_report(self) -> None:
        period = float(self.p["stats_period"])
        now = time.monotonic()
        if period <= 0 or now - self._period_start < period:
            return
        with self._lock:
            n, self._period_processed = self._period_processed, 0
        dt, self._period_start = now - self._period_start, now
        s = self.get_stats()
        received = sum(v for k, v in s.items() if k.startswith("received_"))
        if n == 0:
            if received == 0:
                self._warn("no_input", "no input yet on " + ", ".join(
                    self.resolve_topic_name(t) for t in ("image", "depth", "camera_info")), period=max(period, 30.0))
            elif s.get("synced", 0) == 0:
                self._warn("no_sync", "receiving messages but none synchronised (counts: " + ", ".join(
                    f"{k[9:]} {v}" for k, v in s.items() if k.startswith("received_"))
                    + f"); check the stamps and sync_slop={self.p['sync_slop']}", period=max(period, 30.0))
            if s.get("synced", 0) == self._last_reported_synced:
                return
        self._last_reported_synced = s.get("synced", 0)
        skipped = sum(v for k, v in s.items() if k.startswith("skipped_"))
        line = (
            f"{n / dt:.1f} frames/s; totals: {s.get('synced', 0)} synced, {s.get('processed', 0)} processed, "
            f"{s['dropped']} dropped (busy), {skipped} skipped (bad input), {s.get('detector_errors', 0)} detector errors"
        )
        if "latency_p50_ms" in s and abs(s["latency_p50_ms"]) < 60_000:
            line += f"; latency stamp->publish p50 {s['latency_p50_ms']:.0f} ms, p95 {s['latency_p95_ms']:.0f} ms"
        elif "pipeline_p50_ms" in s:
            line += (f"; latency sync->publish p50 {s['pipeline_p50_ms']:.0f} ms, p95 {s['pipeline_p95_ms']:.0f} ms"
                     " (stamps are not current time)")
        if "detect_p50_ms" in s:
            line += f"; detector p50 {s['detect_p50_ms']:.0f} ms"
        self.get_logger().info(line)

    # --- shutdown ---------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop the worker threads (idempotent)."""
        self._running = False
        self.mailbox.close()
        if self._handoff is not None:
            self._handoff.close()
        for t in (self._worker, self._finisher):
            if t is not None and t.is_alive() and threading.current_thread() is not t:
                t.join(timeout=30.0)

    def destroy_node(self) -> None:
        self.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``detector_node`` (``ros2 run shape_detector detector_node``)."""
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=args)
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
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return rc


if __name__ == "__main__":
    sys.exit(main())
