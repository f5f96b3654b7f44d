"""Walk-through sequences as a rosbag2 MCAP: RGB-D + camera_info + IMU, camera poses, world GT.

Topics: those of :func:`.bag.write_bag` plus

* ``/tf``        tf2_msgs/TFMessage, ``odom -> camera_link`` at every colour stamp;
* ``/tf_static`` tf2_msgs/TFMessage, ``camera_link -> camera_color_optical_frame`` once;
* ``/odom``      nav_msgs/Odometry, the pose of ``camera_link`` in ``odom`` at every colour stamp.

Next to ``gt.json`` (per-frame, camera frame) ``gt_world.json`` holds the room's objects in the
world frame (``odom``, z up) and every frame's ``T_world_camera`` (optical frame -> world).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .bag import write_bag

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
ODOM_TOPIC = "/odom"
WORLD_SIDECAR = "gt_world.json"
TF_T = "tf2_msgs/msg/TFMessage"
ODOMETRY_T = "nav_msgs/msg/Odometry"
#: poses are logged this long after their stamp (before the images, which trail by 15-35 ms)
POSE_LATENCY_NS = 2_000_000


def _transform_stamped(types: Any, parent: str, child: str, stamp_ns: int, T: np.ndarray) -> Any:
    from msg_conversion.markers import rotation_to_quaternion
    from msg_conversion.stamps import make_header

    M = types.make_by_name
    qx, qy, qz, qw = rotation_to_quaternion(T[:3, :3])
    t = T[:3, 3]
    return M("geometry_msgs/msg/TransformStamped", header=make_header(types, stamp_ns, parent), child_frame_id=child,
             transform=M("geometry_msgs/msg/Transform",
                         translation=M("geometry_msgs/msg/Vector3", x=float(t[0]), y=float(t[1]), z=float(t[2])),
                         rotation=M("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)))


def _odometry(types: Any, parent: str, child: str, stamp_ns: int, T: np.ndarray) -> Any:
    from msg_conversion.markers import make_pose
    from msg_conversion.stamps import make_header

    M = types.make_by_name
    pose = M("geometry_msgs/msg/PoseWithCovariance", pose=make_pose(types, T[:3, 3], T[:3, :3]))
    return M(ODOMETRY_T, header=make_header(types, stamp_ns, parent), child_frame_id=child, pose=pose)


def pose_messages(wt: Any) -> list[tuple[int, str, Any, str]]:
    """``(log time, topic, message, type)`` of the walk-through's ``/tf``, ``/tf_static`` and ``/odom``."""
    from msg_conversion.msgtypes import rosbags_types

    from .walkthrough import LINK_FRAME, OPTICAL_FRAME, T_LINK_OPTICAL, WORLD_FRAME, link_poses

    types = rosbags_types()
    links = link_poses(wt)
    first = links[0][0]
    static = _transform_stamped(types, LINK_FRAME, OPTICAL_FRAME, first, T_LINK_OPTICAL)
    out: list[tuple[int, str, Any, str]] = [
        (first - 1_000_000, TF_STATIC_TOPIC, types.make_by_name(TF_T, transforms=[static]), TF_T)
    ]
    for stamp, T in links:
        tf = types.make_by_name(TF_T, transforms=[_transform_stamped(types, WORLD_FRAME, LINK_FRAME, stamp, T)])
        out.append((stamp + POSE_LATENCY_NS, TF_TOPIC, tf, TF_T))
        out.append((stamp + POSE_LATENCY_NS + 100_000, ODOM_TOPIC, _odometry(types, WORLD_FRAME, LINK_FRAME, stamp, T),
                    ODOMETRY_T))
    return out


def world_sidecar(wt: Any) -> dict:
    """The ``gt_world.json`` content: world frame, objects (world frame, with parts), camera poses."""
    from .walkthrough import OPTICAL_FRAME, WORLD_FRAME

    return {
        "frame_id": WORLD_FRAME,
        "camera_frame": OPTICAL_FRAME,
        "objects": [o.to_dict() for o in wt.gt_world],
        "poses": [{"stamp_ns": int(f.stamp_ns), "T_world_camera": np.asarray(T).tolist()}
                  for f, T in zip(wt.frames, wt.poses)],
    }


def write_walkthrough_bag(out_path: str | Path, frames: int = 40, seed: int = 0, rate_hz: float = 5.0,
                          width: int = 320, height: int = 240, overwrite: bool = True, compress: bool = True) -> Path:
    """Render :func:`.walkthrough.walkthrough` (``seed``, ``frames`` at ``rate_hz``, ``width`` x ``height``)
    and write it as a bag directory ``out_path`` with ``gt.json`` and ``gt_world.json``."""
    from .generate import SynthConfig
    from .walkthrough import walkthrough

    wt = walkthrough(seed, frames, rate_hz, SynthConfig(width=width, height=height))
    out = write_bag(wt.frames, out_path, rate_hz=rate_hz, seed=seed, compress=compress, overwrite=overwrite,
                    extra_messages=pose_messages(wt))
    (out / WORLD_SIDECAR).write_text(json.dumps(world_sidecar(wt), separators=(",", ":")))
    return out


def read_world_sidecar(bag_dir: str | Path) -> dict:
    """``gt_world.json`` of a walk-through bag: objects as GTObject (world frame), poses as 4x4 arrays."""
    from ..types import GTObject

    d = json.loads((Path(bag_dir) / WORLD_SIDECAR).read_text())
    d["objects"] = [GTObject.from_dict(o) for o in d["objects"]]
    for p in d["poses"]:
        p["T_world_camera"] = np.asarray(p["T_world_camera"], dtype=np.float64)
    return d
