"""The live node's scene memory without ROS: camera poses from the configured source, the
:class:`~shape_detector.scene.SceneMap` fed after each detection, plans on its grid.

Pose sources (parameter ``pose_source``): ``tf`` (``/tf`` + ``/tf_static``: through tf2_ros
where it is importable, else the node's own subscriptions feeding a
:class:`~shape_detector.poses.CameraPoseSource`; neither works without the tf2_msgs
messages), ``odom`` (``nav_msgs/Odometry`` on ``odom_topic``), ``pose``
(``geometry_msgs/PoseStamped`` on ``pose_topic``), ``none`` (static camera) and ``auto``:
every source that can be subscribed, the map in the camera frame levelled by gravity (static
camera) until one of them delivers a pose, then restarted in the world frame. A frame newer
than the newest pose waits up to ``pose_timeout`` for it; a frame without a pose at its stamp
then skips the scene update (logged); the detections are published all the same.

Thread safety: poses arrive on the executor thread, frames on the worker, plan requests on
the executor again; one lock guards the pose buffer, another the map, so that a frame's pose
lookup never waits for a map update.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .poses import CameraPoseSource, TransformLookupError, camera_up
from .scene import NavGrid, SceneConfig, SceneMap, SceneObject
from .scene.json_io import write_json

#: surfaces are recomputed when an object moves or grows by about this much, m
SURFACE_KEY_STEP = 0.02
#: ... and at most this often, s (while a map settles its objects change every frame)
SURFACES_PERIOD = 1.0
#: values of the pose_source parameter
POSE_SOURCES = ("auto", "tf", "odom", "pose", "none")
#: gravity from a pose this much older than the frame is still used (s): the pose stream may
#: lag the images, and the camera's tilt changes slowly
UP_POSE_LAG = 0.2

Warn = Callable[..., None]


def scene_config(p: dict[str, Any]) -> SceneConfig:
    """The :class:`SceneConfig` of the node's parameter values ``p``."""
    return SceneConfig(world_frame=str(p["world_frame"]).lstrip("/") or "odom",
                       grid_resolution=float(p["grid_resolution"]), inflation_radius=float(p["inflation_radius"]),
                       confirm_observations=int(p["scene_confirm_observations"]),
                       delete_misses=int(p["scene_delete_misses"]),
                       publish_score=float(p["scene_publish_score"]),
                       track_classifier=str(p["scene_track_classifier"]))


def newest_stamp_ns(kind: str, msg: Any) -> int:
    """The newest stamp (ns) of a moving pose message; -1 for /tf_static or when unreadable."""
    from msg_conversion.stamps import stamp_to_ns

    try:
        if kind == "tf":
            return max((stamp_to_ns(t.header.stamp) for t in msg.transforms), default=-1)
        if kind in ("odometry", "pose"):
            return stamp_to_ns(msg.header.stamp)
    except (AttributeError, TypeError, ValueError):
        pass
    return -1


def pose_topics(source: str, odom_topic: str, pose_topic: str, tf_possible: bool) -> list[tuple[str, str]]:
    """``(kind, topic)`` pairs to subscribe for pose source ``source`` (kinds: tf,
    tf_static, odometry, pose); ``tf_possible``: the TF messages can be subscribed."""
    out: list[tuple[str, str]] = []
    if source in ("auto", "tf") and tf_possible:
        out += [("tf", "/tf"), ("tf_static", "/tf_static")]
    if source in ("auto", "odom") and odom_topic:
        out.append(("odometry", odom_topic))
    if source in ("auto", "pose") and pose_topic:
        out.append(("pose", pose_topic))
    return out


class SceneFeed:
    """Poses in, :class:`SceneMap` updates out (see the module docstring). ``warn(kind, text,
    period=, level=)``: the node's rate-limited logger. ``tf2``: an object with
    ``T_world_camera(frame, stamp_ns)`` (tf2_ros lookup) or None."""

    def __init__(self, p: dict[str, Any], warn: Warn, tf2: Any = None) -> None:
        if p["pose_source"] not in POSE_SOURCES:
            raise ValueError(f"pose_source must be one of {POSE_SOURCES}, got {p['pose_source']!r}")
        self.config = scene_config(p)
        self.source_kind = str(p["pose_source"])
        self.map = SceneMap(self.config)
        self.poses = CameraPoseSource(self.config.world_frame, kind="tf")
        self.tf2 = tf2
        self.warn = warn
        self.lock = threading.Lock()  # the map and what is said about it (posed, versions)
        self.pose_lock = threading.Lock()  # the pose buffer and newest_pose_ns
        self._pose_arrived = threading.Condition(self.pose_lock)
        self.newest_pose_ns = -1  # stamp of the newest moving pose (not /tf_static)
        self.pose_timeout = float(p["pose_timeout"])
        self.plan_unknown = str(p.get("plan_unknown", "interior"))  # ~/get_plan's unknown cells
        self.plan_uncertainty = float(p.get("plan_uncertainty", 0.5))  # ~/get_plan's margins (standard deviations)
        self.plan_squeeze = float(p.get("plan_squeeze", 0.02))  # ~/get_plan's squeeze (m)
        self.posed = False  # the map holds world-frame data
        self.static_updates = 0  # updates made without a pose (auto / none)
        self.version = 0  # bumped by every map update
        self.saved_version = 0  # the version last written by save()

    # --- input (executor thread) ------------------------------------------------------------
    def add_pose(self, kind: str, msg: Any) -> None:
        """A pose message of ``kind`` (tf, tf_static, odometry, pose); a bad one is warned about."""
        try:
            with self.pose_lock:
                self.poses.add_message(msg, kind)
                self.newest_pose_ns = max(self.newest_pose_ns, newest_stamp_ns(kind, msg))
                self._pose_arrived.notify_all()
        except Exception as e:  # noqa: BLE001 - malformed messages must not stop the node
            self.warn("pose_msg", f"{kind} message unusable: {type(e).__name__}: {e}")

    # --- frames (worker thread) ---------------------------------------------------------------
    def pose_at(self, camera_frame: str, stamp_ns: int) -> tuple[np.ndarray | None, str | None]:
        """``(T_world_camera or None, why not)``; ``(None, None)``: static camera mode."""
        if self.source_kind == "none":
            return None, None
        errors = []
        if self.tf2 is not None:
            try:
                return self.tf2.T_world_camera(camera_frame, stamp_ns), None
            except TransformLookupError as e:
                errors.append(str(e))
        with self.pose_lock:
            if self.poses.messages > 0 or self.source_kind != "auto":
                # the frame may be ahead of the pose stream: give it pose_timeout to catch up
                self._pose_arrived.wait_for(lambda: self.newest_pose_ns >= stamp_ns or self.poses.messages == 0,
                                            timeout=self.pose_timeout)
                try:
                    return self.poses.T_world_camera(camera_frame, stamp_ns), None
                except TransformLookupError as e:
                    errors.append(str(e))
        if self.source_kind == "auto" and not self.posed and self.poses.messages == 0:
            return None, None  # no pose has ever arrived: static camera
        return None, "; ".join(errors) or "no pose received"

    def up_at(self, camera_frame: str, stamp_ns: int) -> np.ndarray | None:
        """Gravity up (unit vector, camera optical frame) from the world frame's z axis at the
        camera pose of ``stamp_ns`` (ns), or up to :data:`UP_POSE_LAG` s before it when the
        poses lag the frame; None when no pose is known then. Never waits for a pose."""
        if self.source_kind == "none":
            return None
        stamp_ns, lag = int(stamp_ns), int(UP_POSE_LAG * 1e9)
        stamps = [stamp_ns, stamp_ns - lag]
        if 0 < stamp_ns - self.newest_pose_ns <= lag:
            stamps.insert(1, self.newest_pose_ns)
        for stamp in stamps:
            T = None
            if self.tf2 is not None:
                try:
                    T = self.tf2.T_world_camera(camera_frame, stamp)
                except TransformLookupError:
                    pass
            if T is None and self.poses.messages > 0:
                with self.pose_lock:
                    try:
                        T = self.poses.T_world_camera(camera_frame, stamp)
                    except TransformLookupError:
                        pass
            if T is not None and (up := camera_up(T)) is not None:
                return up
        return None

    def update(self, objects: list, depth: np.ndarray | None, K: np.ndarray | None, stamp_ns: int,
               camera_frame: str, up: np.ndarray | None) -> bool:
        """Fold one processed frame into the map; False when skipped (no pose, bad input)."""
        T, why = self.pose_at(camera_frame, stamp_ns)
        if why is not None:
            self.warn("scene_pose", f"no camera pose {self.config.world_frame} <- {camera_frame or '(empty)'} at "
                      f"{stamp_ns / 1e9:.3f} s ({why}): scene not updated for this frame", period=10.0)
            return False
        if T is None:
            self.warn("scene_static", f"pose_source={self.source_kind}: no camera pose, scene map in static camera "
                      f"mode (frame {self.config.world_frame} = the camera frame levelled by gravity, origin at "
                      "the camera)", period=float("inf"), level="info")
        try:
            with self.lock:
                if T is not None and not self.posed:
                    if self.static_updates:
                        self.warn("scene_restart", "camera poses arrived: scene map restarted in the world frame "
                                  f"{self.config.world_frame}", period=float("inf"), level="info")
                        self.map = SceneMap(self.config)
                    self.posed = True
                self.static_updates += T is None
                self.map.update(objects, T, depth, K, int(stamp_ns), up_camera=up)
                self.version += 1
        except Exception as e:  # noqa: BLE001 - the scene must never stop the detections
            self.warn("scene_update", f"scene update failed: {type(e).__name__}: {e}", level="error")
            return False
        return True

    def snapshot(self) -> tuple[list[SceneObject], NavGrid, int]:
        """(confirmed objects, grid, map stamp ns), consistent with each other."""
        with self.lock:
            return self.map.objects(), self.map.grid(), self.map.stamp_ns

    def observed(self) -> tuple[np.ndarray, float] | None:
        """The map's observed surface points (M,3) world and the pad by which an object claims
        them (for ``ArScene.observed``), or None when it keeps none."""
        with self.lock:
            return self.map.observed_surfaces()

    def save(self, path: str | Path) -> int:
        """Write the map as scene JSON to ``path`` (atomically); returns its number of objects.
        The map is serialised under the lock, written outside it."""
        with self.lock:
            doc, version = self.map.to_json(), self.version
        write_json(path, doc)
        self.saved_version = version
        return len(doc["objects"])

    def load(self, path: str | Path) -> int:
        """Continue the map saved at ``path`` (its objects, free floor and observed surfaces);
        returns its number of objects. ValueError when the file is not a scene map or is in
        another frame than ``world_frame``."""
        m = SceneMap.from_json(path, self.config)
        if m.frame_id != self.config.world_frame:
            raise ValueError(f"{path} is a map in frame {m.frame_id!r}, this node's world_frame is "
                             f"{self.config.world_frame!r}")
        self.set_map(m)
        self.saved_version = self.version
        return len(m.objects())

    def clear(self) -> None:
        """Start a fresh, empty map (same settings and world frame)."""
        self.set_map(SceneMap(self.config))

    def set_map(self, scene: SceneMap) -> None:
        """Replace the map (a loaded one, or a test's) and treat it as world-frame data."""
        with self.lock:
            self.map, self.posed = scene, True
            self.version += 1


def surfaces_key(objects: list[SceneObject], step: float = SURFACE_KEY_STEP) -> tuple:
    """What the surfaces depend on, quantised by ``step`` m: equal keys, equal surfaces."""
    return tuple((o.id, o.class_name, tuple(np.round(np.concatenate([o.center, o.size]) / step).astype(int)),
                  len(o.primitives)) for o in objects)


def answer_plan(feed: SceneFeed | None, request: Any, types: Any, stamp_ns: int, warn: Warn) -> Any:
    """The ``nav_msgs/Path`` answering a GetPlan ``request`` on the feed's current map (agent
    radius ``inflation_radius``; :mod:`shape_detector.ar.plan_service`); an empty path, with
    the reason logged, when there is none."""
    from .ar import SceneQueries
    from .ar.plan_service import PlanResult, path_message, plan_request
    from .ar.scene_data import ArScene, load_scene

    if feed is None:
        result = PlanResult(False, np.zeros((0, 4)), "the scene is off (publish_scene false)")
        frame = ""
    else:
        frame = feed.config.world_frame
        with feed.lock:  # a plan needs no observed surfaces: skip the pass over them
            queries = SceneQueries(ArScene(load_scene(feed.map.objects()).objects, feed.map.grid(), frame))
        result = plan_request(queries, request, frame, agent_radius=feed.config.inflation_radius,
                              unknown=feed.plan_unknown, uncertainty=feed.plan_uncertainty,
                              squeeze=feed.plan_squeeze)
    if not result.ok:
        warn("get_plan", f"get_plan: no path ({result.message})", level="info")
    return path_message(result, types, stamp_ns, frame)
