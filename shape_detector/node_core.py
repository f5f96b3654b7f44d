"""What the live node does between its subscriptions and publishers, without ROS.

:class:`NodeCore` is mixed into the rclpy node (:mod:`shape_detector.node`): parameter
checks and taking new values into use, input callbacks (stamps, size warnings, the
synchroniser, camera_info, IMU gravity), gravity up per frame, rate-limited warnings and the
periodic statistics line. The node provides ``log(level, text)``, ``topic(name)``,
``now_ns()``, ``subscribe_imu()`` and the publishing; everything here runs under a fake
host in the tests (test/test_node_core.py).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

import numpy as np

from .imu_gravity import ImuGravityFilter
from .node_params import DETECTOR_ATTRS, PARAMETERS, REBUILD, apply_to_detector, build_detector, validate
from .node_stats import NodeStats, WarningLimiter, problem_key, stats_line
from .process_detector import close_detector
from .scheduler import FrameScheduler, FrameSet
from .sync import ApproximateTimeSynchronizer, header_stamp_ns


def unit(v: Any) -> np.ndarray:
    """``v`` as a unit float64 vector."""
    a = np.asarray(list(v), dtype=np.float64).reshape(-1)
    return a / np.linalg.norm(a)


class NodeCore:
    """The node's state and callbacks; see the module docstring. Call :meth:`init_core`
    once the parameter values ``p`` are known and before any subscription exists."""

    p: dict[str, Any]
    detector: Any
    external: bool
    _factory: Any = None
    _scheduler: FrameScheduler | None = None
    _imu_sub: Any = None

    # --- provided by the node -------------------------------------------------------------
    def log(self, level: str, text: str) -> None:
        """Write one log line (``level``: info, warning or error)."""
        print(f"[shape_detector] {level}: {text}", file=sys.stderr)

    def topic(self, name: str) -> str:
        """``name`` resolved (remaps, namespace)."""
        return name

    def now_ns(self) -> int:
        """The node's clock, ns."""
        return time.time_ns()

    def subscribe_imu(self) -> None:
        """Subscribe to the ``imu`` topic (called when up_source becomes imu)."""

    # --- set up -------------------------------------------------------------------------
    def init_core(self, p: dict[str, Any], external: bool) -> None:
        """State from the parameter values ``p``; ``external``: 2D boxes come from a topic."""
        self.p, self.external = p, external
        self.stats = NodeStats()
        self._limiter = WarningLimiter()
        self._period_start = time.monotonic()
        self._last_reported_synced = -1
        self._camera_info: Any = None
        self.info_event = threading.Event()
        self.imu_filter = ImuGravityFilter(p["imu_time_constant"], p["imu_to_camera"])
        self.sync = ApproximateTimeSynchronizer(3 if external else 2, p["sync_queue_size"], p["sync_slop"])
        self.sync.register_callback(self.on_synced)

    def start_worker(self) -> None:
        """Start the worker thread(s) (after the detector and the publishers exist)."""
        self._scheduler = FrameScheduler(self, bool(self.p["pipeline"]))

    def build_detector(self) -> Any:
        """A detector built from the parameters (``detector_factory`` or ShapeDetector), warmed up."""
        return build_detector(self.p, self.external, self._factory, lambda t: self.log("info", t),
                              lambda t: self.log("warning", t))

    @property
    def counters(self) -> Any:
        """The statistics counters (a Counter; read-only use)."""
        return self.stats.counters

    @property
    def mailbox(self) -> Any:
        """The scheduler's input mailbox (None before the worker starts)."""
        return self._scheduler.mailbox if self._scheduler else None

    @property
    def _worker(self) -> threading.Thread | None:
        return self._scheduler.worker if self._scheduler else None

    @property
    def _finisher(self) -> threading.Thread | None:
        return self._scheduler.finisher if self._scheduler else None

    def camera_info(self) -> Any:
        """The latest camera_info message (None before one arrived)."""
        return self._camera_info

    # --- parameters -------------------------------------------------------------------
    def set_parameters_checked(self, changes: list[tuple[str, Any]]) -> str | None:
        """Validate and take into use ``(name, value)`` changes; the reason when refused."""
        problems = [p for p in (validate(name, value) for name, value in changes) if p]
        if problems:
            return "; ".join(problems)
        try:
            for name, value in changes:
                if name in PARAMETERS:
                    self.apply(name, value)
        except (ValueError, TypeError) as e:
            return str(e)
        return None

    def apply(self, name: str, value: Any) -> None:
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
            self.subscribe_imu()

    # --- callbacks (executor thread; never raise) ----------------------------------------
    def on_input(self, name: str, index: int, msg: Any) -> None:
        """An image / depth / detections2d message: checked, then to the synchroniser."""
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

    def on_camera_info(self, msg: Any) -> None:
        """Keep the latest camera_info."""
        self.stats.count("received_camera_info")
        self._camera_info = msg
        self.info_event.set()

    def on_imu(self, msg: Any) -> None:
        """An IMU sample into the gravity filter (rejected ones warned about)."""
        self.stats.count("received_imu")
        try:
            a = msg.linear_acceleration
            if not self.imu_filter.update((a.x, a.y, a.z), header_stamp_ns(msg)):
                self.warn("imu_rejected", "IMU sample rejected (non-finite or far from 1 g: moving?)", period=30.0)
        except Exception as e:  # noqa: BLE001
            self.warn("imu", f"IMU message unusable: {type(e).__name__}: {e}")

    def on_synced(self, *msgs: Any) -> None:
        """A synchronised (image, depth[, detections2d]) set to the worker, with the current up."""
        fs = FrameSet(image=msgs[0], depth=msgs[1], camera_info=self._camera_info,
                      detections2d=msgs[2] if len(msgs) > 2 else None, up=self.current_up(),
                      synced_at=time.monotonic())
        if self._scheduler is not None:
            self._scheduler.offer(fs)

    def frame_up(self, fs: FrameSet, stamp_ns: int, frame_id: str) -> np.ndarray | None:
        """Gravity up (camera optical frame) for a frame about to be detected: the value taken
        at synchronisation (``fixed``, ``imu``), else with ``auto`` / ``pose`` the scene's
        camera pose at the frame's stamp; None: the detector estimates it."""
        if fs.up is not None or self.p["up_source"] not in ("auto", "pose"):
            return fs.up
        scene = getattr(self, "scene", None)
        up = scene.up_at(frame_id, stamp_ns) if scene is not None else None
        if up is None and self.p["up_source"] == "pose":
            self.warn("no_pose_up", "up_source=pose but no camera pose at the frame's stamp"
                      + ("" if scene is not None else " (publish_scene is off: no poses)")
                      + ": estimating up from the scene")
        return up

    def current_up(self) -> np.ndarray | None:
        """Gravity up (camera frame) taken at synchronisation (``fixed``, ``imu``); None: later
        from the pose (:meth:`frame_up`) or estimated by the detector."""
        src = self.p["up_source"]
        if src == "fixed":
            return unit(self.p["up"])
        if src == "imu":
            up = self.imu_filter.up
            if up is None:
                self.warn("no_imu", "up_source=imu but no usable IMU sample yet: estimating up from the scene")
            return up
        return None

    # --- logging, statistics ------------------------------------------------------------
    def warn(self, kind: str, text: str, period: float = 5.0, level: str = "warning", key: str | None = None) -> None:
        """Log ``text`` the first time its problem (``key``, default: ``kind`` + the text with
        numbers blanked) occurs, then at most every ``period`` s with the count held back."""
        held = self._limiter.admit(key or problem_key(kind, text), time.monotonic(), period)
        if held is None:
            return
        if held:
            text += f" ({held} more since the last report)"
        try:
            self.log(level, text)
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
            self.log("info", stats_line(s, n / dt))

    def stop(self) -> None:
        """Stop the worker threads (idempotent, bounded in time)."""
        if self._scheduler is not None and not self._scheduler.stop():
            print("[shape_detector] a worker thread is still busy at shutdown; leaving it (daemon)", file=sys.stderr)
        close_detector(getattr(self, "detector", None))
