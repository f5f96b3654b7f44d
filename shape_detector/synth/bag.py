"""Generated frames as a ROS 2 bag (rosbag2, MCAP storage) with a ground-truth sidecar.

Topics (typestore ROS 2 Jazzy, messages built by :mod:`msg_conversion`):

* ``/camera/color/image_raw``   sensor_msgs/Image ``rgb8``
* ``/camera/color/camera_info`` sensor_msgs/CameraInfo (same stamp as the colour image)
* ``/camera/depth/image_raw``   sensor_msgs/Image ``16UC1`` (mm, 0 = no reading), registered to colour;
  its stamp differs from the colour stamp by a few ms (like a real driver's separate streams)
* ``/camera/depth/camera_info`` sensor_msgs/CameraInfo (depth stamp; registered, so the same K)
* ``/camera/imu``               sensor_msgs/Imu accelerometer (gravity + noise, camera optical frame), optional

``header.frame_id`` is ``camera_color_optical_frame`` everywhere. Log (receive) times trail the stamps
by a small latency. MCAP chunks are zstd-compressed (rosbag2 "storage" compression, readable by
``ros2 bag``, rosbags' AnyReader and the ``mcap`` Python reader). ``gt.json`` next to
``metadata.yaml`` holds the ground truth keyed by colour stamp (ns, as a decimal string).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..types import Frame

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
INFO_TOPIC = "/camera/color/camera_info"
DEPTH_INFO_TOPIC = "/camera/depth/camera_info"
IMU_TOPIC = "/camera/imu"
SIDECAR = "gt.json"
G = 9.80665


def sidecar_dict(frames: Sequence[Frame], depth_stamps: Sequence[int] | None = None) -> dict:
    out: dict = {"frame_id": frames[0].frame_id if frames else "", "color_topic": COLOR_TOPIC,
                 "depth_topic": DEPTH_TOPIC, "camera_info_topic": INFO_TOPIC, "frames": {}}
    for i, f in enumerate(frames):
        out["frames"][str(int(f.stamp_ns))] = {
            "K": np.asarray(f.K).tolist(),
            "up": None if f.up is None else np.asarray(f.up).tolist(),
            "width": f.width, "height": f.height,
            "depth_stamp_ns": int(depth_stamps[i]) if depth_stamps is not None else int(f.stamp_ns),
            "objects": [o.to_dict() for o in f.objects],
            "clutter_boxes": [list(map(float, b)) for b in f.clutter_boxes],
        }
    return out


def read_sidecar(bag_dir: str | Path) -> dict[int, dict]:
    """``gt.json`` of a bag as {colour stamp ns: entry}; entries' ``objects`` as GTObject lists."""
    from ..types import GTObject

    d = json.loads((Path(bag_dir) / SIDECAR).read_text())
    out = {}
    for k, v in d["frames"].items():
        v = dict(v)
        v["objects"] = [GTObject.from_dict(o) for o in v["objects"]]
        v["K"] = np.array(v["K"])
        v["up"] = None if v["up"] is None else np.array(v["up"])
        out[int(k)] = v
    return out


def write_bag(frames: Sequence[Frame], out_path: str | Path, rate_hz: float = 5.0, seed: int = 0,
              compress: bool = True, imu: bool = True, imu_rate_hz: float = 50.0, overwrite: bool = False,
              max_offset_ms: float = 12.0) -> Path:
    """Write ``frames`` (stamps taken from them, or re-stamped at ``rate_hz`` when not increasing)
    as a rosbag2 MCAP directory ``out_path`` plus ``gt.json``; returns the directory."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from msg_conversion.camera_info import K_to_camera_info
    from msg_conversion.image import depth_to_image, numpy_to_image
    from msg_conversion.msgtypes import rosbags_types
    from msg_conversion.stamps import make_header

    out = Path(out_path)
    if out.exists():
        if not overwrite:
            raise FileExistsError(f"{out} exists (pass overwrite=True / --overwrite)")
        shutil.rmtree(out)
    frames = list(frames)
    if not frames:
        raise ValueError("no frames")
    rng = np.random.default_rng(seed)
    stamps = [int(f.stamp_ns) for f in frames]
    period = int(round(1e9 / rate_hz))
    if any(b <= a for a, b in zip(stamps, stamps[1:])):
        stamps = [stamps[0] + i * period for i in range(len(frames))]
        for f, s in zip(frames, stamps):
            f.stamp_ns = s
    # small colour/depth stamp offsets (independent driver streams), monotonic
    offs = np.round(rng.uniform(-max_offset_ms, max_offset_ms, len(frames)) * 1e6).astype(np.int64)
    depth_stamps = [s + int(o) for s, o in zip(stamps, offs)]
    types = rosbags_types()
    store = types.typestore
    fid = frames[0].frame_id
    w = Writer(out, version=8, storage_plugin=StoragePlugin.MCAP)
    if compress:
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    msgs: list[tuple[int, str, object, str]] = []  # (log time, topic, msg, type)
    for f, sc, sd in zip(frames, stamps, depth_stamps):
        lat_c = int(rng.uniform(15, 35) * 1e6)
        lat_d = int(rng.uniform(15, 35) * 1e6)
        msgs.append((sc + lat_c, COLOR_TOPIC, numpy_to_image(f.rgb, "rgb8", types, stamp_ns=sc, frame_id=fid),
                     "sensor_msgs/msg/Image"))
        msgs.append((sc + lat_c + 200_000, INFO_TOPIC,
                     K_to_camera_info(f.K, f.width, f.height, types, stamp_ns=sc, frame_id=fid),
                     "sensor_msgs/msg/CameraInfo"))
        msgs.append((sd + lat_d, DEPTH_TOPIC,
                     depth_to_image(f.depth, types, encoding="16UC1", stamp_ns=sd, frame_id=fid),
                     "sensor_msgs/msg/Image"))
        msgs.append((sd + lat_d + 200_000, DEPTH_INFO_TOPIC,
                     K_to_camera_info(f.K, f.width, f.height, types, stamp_ns=sd, frame_id=fid),
                     "sensor_msgs/msg/CameraInfo"))
    if imu and frames[0].up is not None:
        Imu = store.types["sensor_msgs/msg/Imu"]
        Vector3 = store.types["geometry_msgs/msg/Vector3"]
        Quaternion = store.types["geometry_msgs/msg/Quaternion"]
        ups = np.array([f.up for f in frames])
        t0, t1 = stamps[0] - period // 2, stamps[-1] + period // 2
        n = max(2, int((t1 - t0) * imu_rate_hz / 1e9))
        ti = t0 + np.arange(n) * int(round(1e9 / imu_rate_hz))
        cov = [0.0] * 9
        for t in ti:
            # up interpolated between frames (piecewise linear), plus accelerometer noise & hand shake
            up = np.array([np.interp(t, stamps, ups[:, k]) for k in range(3)])
            up /= np.linalg.norm(up)
            a = G * up + rng.normal(0, 0.05, 3) + rng.normal(0, 0.15, 3)
            msg = Imu(
                header=make_header(types, int(t), fid),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.array([-1.0] + [0.0] * 8),
                angular_velocity=Vector3(x=float(rng.normal(0, 0.01)), y=float(rng.normal(0, 0.01)),
                                         z=float(rng.normal(0, 0.01))),
                angular_velocity_covariance=np.array(cov),
                linear_acceleration=Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=np.array([0.0025, 0, 0, 0, 0.0025, 0, 0, 0, 0.0025]),
            )
            msgs.append((int(t) + 2_000_000, IMU_TOPIC, msg, "sensor_msgs/msg/Imu"))
    msgs.sort(key=lambda m: m[0])
    with w:
        conns = {}
        for _, topic, _, ty in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, ty, typestore=store)
        for t, topic, msg, ty in msgs:
            w.write(conns[topic], int(t), store.serialize_cdr(msg, ty))
    (out / SIDECAR).write_text(json.dumps(sidecar_dict(frames, depth_stamps), separators=(",", ":")))
    return out


SAMPLE_ROOMS = ("living", "bedroom", "office", "dining")


def sample_sequence(seed: int = 7, num_frames: int = 12, rate_hz: float = 5.0, width: int = 320, height: int = 240,
                    config=None, min_visible: int = 3) -> list[Frame]:
    """A representative sequence for demos: a furnished living room / bedroom / office / dining room
    (chosen by ``seed``) in which at least ``min_visible`` objects are mostly visible at the start."""
    from .generate import SynthConfig, generate_sequence

    base = config or SynthConfig(width=width, height=height)
    small = SynthConfig(**{**base.__dict__, "width": 160, "height": 120, "noise": False})
    for k in range(40):
        s = seed * 1000 + k
        room = SAMPLE_ROOMS[(seed + k) % len(SAMPLE_ROOMS)]
        cfg = SynthConfig(**{**base.__dict__, "room_type": room, "min_objects": 4})
        probe = generate_sequence(s, 1, rate_hz, SynthConfig(**{**small.__dict__, "room_type": room, "min_objects": 4}))
        if sum(o.visible_fraction > 0.3 for o in probe[0].objects) >= min_visible:
            return generate_sequence(s, num_frames, rate_hz, cfg)
    return generate_sequence(seed, num_frames, rate_hz, base)


def write_sample_bag(out_path: str | Path, num_frames: int = 12, seed: int = 7, rate_hz: float = 5.0,
                     width: int = 320, height: int = 240, overwrite: bool = True, compress: bool = True,
                     config=None) -> Path:
    """The committed sample bag: :func:`sample_sequence` written by :func:`write_bag`."""
    frames = sample_sequence(seed, num_frames, rate_hz, width, height, config)
    return write_bag(frames, out_path, rate_hz=rate_hz, seed=seed, compress=compress, overwrite=overwrite)
