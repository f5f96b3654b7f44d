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
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

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
    """The ``gt.json`` content of ``frames``: per colour stamp K, up, size, depth stamp, objects."""
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


def _imu_messages(frames: Sequence[Frame], stamps: list[int], period: int, imu_rate_hz: float,
                  rng: np.random.Generator, types: Any, fid: str) -> list[tuple[int, str, object, str]]:
    """Accelerometer messages between the first and last frame: gravity up (interpolated between
    frames) plus noise and hand shake, camera optical frame."""
    from msg_conversion.stamps import make_header

    store = types.typestore
    msgs: list[tuple[int, str, object, str]] = []
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
    return msgs


def write_bag(frames: Sequence[Frame], out_path: str | Path, rate_hz: float = 5.0, seed: int = 0,
              compress: bool = True, imu: bool = True, imu_rate_hz: float = 50.0, overwrite: bool = False,
              max_offset_ms: float = 12.0,
              extra_messages: Sequence[tuple[int, str, Any, str]] = ()) -> Path:
    """Write ``frames`` (stamps taken from them, or re-stamped at ``rate_hz`` when not increasing)
    as a rosbag2 MCAP directory ``out_path`` plus ``gt.json``; returns the directory.

    ``extra_messages``: more ``(log time ns, topic, rosbags message, type name)`` to write (e.g.
    ``/tf``), merged in log-time order."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from msg_conversion.camera_info import K_to_camera_info
    from msg_conversion.image import depth_to_image, numpy_to_image
    from msg_conversion.msgtypes import rosbags_types

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
        msgs += _imu_messages(frames, stamps, period, imu_rate_hz, rng, types, fid)
    msgs.extend(extra_messages)
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


def write_rgbd_bag(
    path: str | Path,
    frames: Iterable[tuple[int, np.ndarray, np.ndarray, np.ndarray]],
    *,
    storage: str = "mcap",
    image_topic: str = "/camera/color/image_raw",
    depth_topic: str = "/camera/depth/image_raw",
    info_topic: str = "/camera/color/camera_info",
    color_encoding: str = "rgb8",
    depth_encoding: str = "16UC1",
    frame_id: str = "camera_color_optical_frame",
    depth_offset_ns: int = 0,
) -> Path:
    """Write ``(stamp_ns, rgb, depth_m, K)`` frames as a bag: colour image, depth image
    (stamp + ``depth_offset_ns``) and camera_info per frame, log time = stamp.

    ``storage``: ``'mcap'`` or ``'sqlite3'`` (rosbag2 directory ``path``) or ``'ros1'``
    (ROS 1 ``.bag`` file ``path``). For tests, tools and examples.
    """
    from msg_conversion.camera_info import K_to_camera_info

    from ..bags.ros1 import convert_message
    from ..bags.source import CAMERA_INFO_T, IMAGE_T
    from msg_conversion.image import depth_to_image, numpy_to_image
    from msg_conversion.msgtypes import rosbags_types

    path = Path(path)
    T = rosbags_types()
    store = T.typestore
    if color_encoding.startswith("bgr"):
        def colour(rgb: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(rgb[..., ::-1])
    else:
        def colour(rgb: np.ndarray) -> np.ndarray:
            return rgb

    def messages() -> Iterator[tuple[str, str, int, Any]]:
        for stamp, rgb, depth, K in frames:
            h, w = rgb.shape[:2]
            yield image_topic, IMAGE_T, stamp, numpy_to_image(colour(rgb), color_encoding, T, stamp, frame_id)
            dstamp = stamp + depth_offset_ns
            yield depth_topic, IMAGE_T, dstamp, depth_to_image(depth, T, depth_encoding, dstamp, frame_id)
            yield info_topic, CAMERA_INFO_T, stamp, K_to_camera_info(K, w, h, T, stamp, frame_id)

    if storage == "ros1":
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.typesys import Stores, get_typestore

        ros1 = get_typestore(Stores.ROS1_NOETIC)
        with Writer1(path) as w:
            conns: dict[str, Any] = {}
            for topic, typ, t, msg in messages():
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, typ, typestore=ros1)
                w.write(conns[topic], t, ros1.serialize_ros1(convert_message(msg, typ, ros1), typ))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
    if plugin is None:
        raise ValueError(f"storage must be 'mcap', 'sqlite3' or 'ros1', got {storage!r}")
    with Writer(path, version=8, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ, t, msg in messages():
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=store)
            w.write(conns[topic], t, store.serialize_cdr(msg, typ))
    return path


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
