"""The scene map in a replay: camera poses from the bag, one scene update per frame, the JSON.

Poses come from ``/tf`` + ``/tf_static`` (every ``tf2_msgs/TFMessage`` topic, found by type) or
from an ``--odom-topic`` (``nav_msgs/Odometry``) / ``--pose-topic`` (``geometry_msgs/PoseStamped``)
combined with the static transforms; they are read in a first pass over those topics only, so a
frame's pose is interpolated between the poses around its stamp. The camera frame is the colour
image's ``header.frame_id``. A bag with no pose at all gives a static-camera scene (said once);
a frame whose transform is missing is skipped by the scene and counted.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..poses import CameraPoseSource, TransformLookupError, camera_up
from .source import ODOMETRY_T, POSE_STAMPED_T, TF_T, BagReadError, open_bag

if TYPE_CHECKING:
    from ..scene import SceneConfig


@dataclass
class SceneOptions:
    """What a replay's scene needs: world frame, JSON path, an explicit pose topic (else ``/tf``)."""

    world_frame: str = "odom"
    scene_out: str | Path | None = None
    #: a saved map (scene JSON in ``world_frame``) to continue instead of starting empty
    scene_in: str | Path | None = None
    odom_topic: str | None = None
    pose_topic: str | None = None
    #: the map's own settings (the node's grid_resolution, inflation_radius,
    #: scene_confirm_observations, scene_delete_misses, scene_publish_score, scene_track_classifier);
    #: None = the SceneConfig defaults
    config: SceneConfig | None = None


@dataclass
class SceneStats:
    """What the scene did in a replay (a part of the replay summary)."""

    world_frame: str
    pose_source: str = ""
    frames: int = 0
    skipped: Counter = field(default_factory=Counter)
    first_problem: str = ""
    objects: int = 0
    json_path: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able values."""
        return {"world_frame": self.world_frame, "pose_source": self.pose_source, "frames": self.frames,
                "skipped": dict(self.skipped), "objects": self.objects, "json": self.json_path}

    def format(self) -> str:
        """One summary line."""
        text = f"world {self.world_frame}, pose {self.pose_source}, {self.frames} frame(s) mapped"
        if self.skipped:
            text += " (skipped: " + ", ".join(f"{k} {v}" for k, v in self.skipped.most_common()) + ")"
            if self.first_problem:
                text += f"; first: {self.first_problem}"
        text += f", {self.objects} object(s)"
        return text + (f" -> {self.json_path}" if self.json_path else "")


def _check_topic(topics: dict[str, str], topic: str, want: str, flag: str) -> None:
    if topic not in topics:
        raise ValueError(f"{flag} {topic!r}: no such topic in the bag; topics: {', '.join(sorted(topics))}")
    if topics[topic] != want:
        raise ValueError(f"{flag} {topic!r} has type {topics[topic]}, expected {want}")


def load_poses(in_path: str | Path, opts: SceneOptions) -> tuple[CameraPoseSource | None, str]:
    """The bag's camera poses and a description of their source; ``(None, why)`` when the bag has
    none (static camera). ``ValueError`` for a pose topic that is missing or of the wrong type."""
    with open_bag(in_path) as src:
        topics = dict(src.topics)
        kinds = {t: ("tf_static" if t.rstrip("/").endswith("tf_static") else "tf") for t, ty in topics.items()
                 if ty == TF_T}
        kind, what = "tf", " + ".join(sorted(kinds)) or "/tf"
        if opts.odom_topic:
            _check_topic(topics, opts.odom_topic, ODOMETRY_T, "--odom-topic")
            kinds[opts.odom_topic], kind, what = "odometry", "odometry", opts.odom_topic
        elif opts.pose_topic:
            _check_topic(topics, opts.pose_topic, POSE_STAMPED_T, "--pose-topic")
            kinds[opts.pose_topic], kind, what = "pose", "pose", opts.pose_topic
        if not kinds:
            return None, "none (no /tf, --odom-topic or --pose-topic): static camera"
        poses = CameraPoseSource(world_frame=opts.world_frame, kind=kind, max_history_ns=None)
        bad = 0
        try:
            for m in src.messages(list(kinds)):
                try:
                    poses.add_message(src.deserialize(m.raw, m.msgtype), kinds[m.topic])
                except (ValueError, TypeError, AttributeError):
                    bad += 1
        except BagReadError:
            pass  # poses read before the damage are used; the replay reports the damage
    if poses.messages == 0:
        return None, f"none ({what} has no usable message): static camera"
    return poses, what + (f" ({bad} malformed message(s) ignored)" if bad else "")


def check_scene_out(in_path: str | Path, scene_out: str | Path | None) -> None:
    """``ValueError`` for a JSON path that is a directory or lies inside the input bag."""
    if scene_out is None:
        return
    from .output_safety import check_output_path

    path = Path(scene_out)
    if path.is_dir():
        raise ValueError(f"--scene-out {str(path)!r} is a directory; give a file name such as scene.json")
    check_output_path(in_path, path)


def continued_map(path: str | Path, config: SceneConfig) -> Any:
    """The map saved at ``path`` to continue, with ``config``; ``ValueError`` when it cannot
    be read or lies in another frame than ``config.world_frame``."""
    from ..scene import SceneMap

    try:
        m = SceneMap.from_json(path, config)
    except (OSError, ValueError) as e:
        raise ValueError(f"--scene-in {str(path)!r}: {e}") from None
    if m.frame_id != config.world_frame:
        raise ValueError(f"--scene-in {str(path)!r} is a map in frame {m.frame_id!r}, not the world frame "
                         f"{config.world_frame!r} (--world-frame)")
    return m


class SceneRecorder:
    """Feeds a :class:`~shape_detector.scene.SceneMap` per replayed frame and writes its messages."""

    def __init__(self, in_path: str | Path, opts: SceneOptions, log: Any = None) -> None:
        from ..scene import SceneConfig, SceneMap

        check_scene_out(in_path, opts.scene_out)
        self.opts = opts
        self.poses, source = load_poses(in_path, opts)
        self.stats = SceneStats(world_frame=opts.world_frame, pose_source=source)
        base = replace(opts.config or SceneConfig(), world_frame=opts.world_frame)
        self.map = SceneMap(base) if not opts.scene_in else continued_map(opts.scene_in, base)
        if self.poses is None and log is not None:
            log(f"scene: no camera pose in the bag, {source}")

    def up_at(self, frame: Any) -> np.ndarray | None:
        """Gravity up (unit vector, camera optical frame) from the world frame's z axis at the
        frame's camera pose; None without poses or when the pose is not known at its stamp."""
        if self.poses is None:
            return None
        try:
            T = self.poses.T_world_camera(frame.frame_id, frame.stamp_ns)
        except TransformLookupError:
            return None
        return camera_up(T)

    def update(self, frame: Any, prepared: Any, objects: list, up: np.ndarray | None) -> bool:
        """Add one frame (``prepared``: its decoded arrays, None when unusable); False when skipped."""
        if prepared is None:
            self.stats.skipped["frame unusable"] += 1
            return False
        T = None
        if self.poses is not None:
            try:
                T = self.poses.T_world_camera(frame.frame_id, frame.stamp_ns)
            except TransformLookupError as e:
                return self._skip("no transform", str(e))
        try:
            self.map.update(objects, T, prepared.depth, prepared.K, int(frame.stamp_ns),
                            up_camera=up if T is None else None)
        except Exception as e:  # noqa: BLE001 - a scene failure must not end the replay
            return self._skip("scene error", f"{type(e).__name__}: {e}")
        self.stats.frames += 1
        return True

    def _skip(self, kind: str, problem: str) -> bool:
        self.stats.skipped[kind] += 1
        if not self.stats.first_problem:
            self.stats.first_problem = problem
        return False

    def write(self, out: Any, stamp_ns: int) -> None:
        """The current scene (MarkerArray) and grid (OccupancyGrid) into the output bag at ``stamp_ns``."""
        out.write_scene(self.map.objects(), self.map.grid(), int(stamp_ns), self.map.frame_id)

    def finish(self) -> None:
        """Count the final objects and write the JSON (``scene_out``)."""
        self.stats.objects = len(self.map.objects())
        if self.opts.scene_out:
            path = Path(self.opts.scene_out)
            if path.parent and not path.parent.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
            self.map.save_json(path)
            self.stats.json_path = str(path)
