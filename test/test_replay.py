"""``shape-detector replay``: offline detection over bags into an output MCAP, and ``--play``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from child_env import child_env
from shape_detector.bags.reader import BagFrameReader
from shape_detector.bags.source import DETECTIONS_TOPIC, MARKERS_TOPIC, read_messages
from shape_detector.replay import replay_bag
from shape_detector.synth.bag import write_rgbd_bag
from shape_detector.types import Object3D

ROOT = Path(__file__).resolve().parents[1]
TEST_DIR = Path(__file__).resolve().parent
WEIGHTS = ROOT / "shape_detector" / "weights" / "default.pt"
MS = 1_000_000
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])


class FakeDetector:
    """Stands in for ShapeDetector (same constructor keywords): one chair per frame at the
    median depth; records its calls."""

    def __init__(self, **kwargs):
        self.kwargs = kwargs
        self.calls = []

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        self.calls.append({"shape": rgb.shape, "K": K.copy(), "boxes2d": boxes2d, "up": up})
        z = float(np.nanmedian(depth))
        return [Object3D("chair", 0.9, [0.0, 0.0, z], [0.5, 0.5, 0.8], np.eye(3))]


def detector_for_tests():
    """The trained detector when the packaged weights exist, else the fake."""
    if WEIGHTS.exists():
        from shape_detector.detector import ShapeDetector

        return ShapeDetector()
    return FakeDetector()


def synthetic_frames(n=12, w=320, h=240, hz=5.0, t0=1_700_000_000 * 10**9):
    out = []
    for k in range(n):
        rgb = np.full((h, w, 3), 90, np.uint8)
        depth = np.full((h, w), 3.0)
        depth[h // 3 :, w // 3 : 2 * w // 3] = 2.0 + 0.01 * k  # a box in front of a wall
        rgb[h // 3 :, w // 3 : 2 * w // 3] = (150, 80, 40)
        out.append((t0 + int(k * 1e9 / hz), rgb, depth, K))
    return out


@pytest.fixture(scope="module")
def bag(sample_bag, tmp_path_factory) -> Path:
    """The sample bag, or a generated stand-in (12 frames, 5 Hz, depth 3 ms late)."""
    if sample_bag.exists():
        return sample_bag
    return write_rgbd_bag(tmp_path_factory.mktemp("bags") / "sample", synthetic_frames(), depth_offset_ns=3 * MS)


def _count_input(bag: Path) -> tuple[int, Counter]:
    with BagFrameReader(bag) as r:
        n = sum(1 for _ in r.frames())
    counts = Counter(t for t, _, _ in read_messages(bag))
    return n, counts


def test_replay_bag_writes_one_marker_per_synced_frame(bag, tmp_path):
    synced, in_counts = _count_input(bag)
    assert synced >= 10
    out = tmp_path / "out"
    det = detector_for_tests()
    s = replay_bag(bag, out, det, progress=False)
    assert s.ok, s.format()
    assert s.synced == synced and s.frames_out == synced and s.frames_in == in_counts[s.topics.image]
    assert "synchronised" in s.format() and f"{synced} out" in s.format()

    # read back with rosbags: input topics copied, markers at the image stamps
    msgs: dict[str, list] = {}
    times: dict[str, list] = {}
    for topic, t, msg in read_messages(out):
        msgs.setdefault(topic, []).append(msg)
        times.setdefault(topic, []).append(t)
    for topic, n in in_counts.items():
        assert len(msgs[topic]) == n, topic
    markers = msgs[MARKERS_TOPIC]
    assert len(markers) == synced
    image_stamps = sorted(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs[s.topics.image])
    marker_stamps = [m.markers[0].header.stamp.sec * 10**9 + m.markers[0].header.stamp.nanosec for m in markers]
    assert sorted(marker_stamps) == image_stamps[: len(marker_stamps)] or set(marker_stamps) <= set(image_stamps)
    assert sorted(times[MARKERS_TOPIC]) == sorted(marker_stamps)  # log time = input stamp
    frame_ids = {m.header.frame_id for m in msgs[s.topics.image]}
    assert {m.markers[0].header.frame_id for m in markers} == frame_ids
    assert len(msgs[DETECTIONS_TOPIC]) == synced
    if isinstance(det, FakeDetector):
        assert s.objects == synced and s.objects_per_class["chair"] == synced
        assert all(len(m.markers) >= 4 for m in markers)  # DELETEALL + box + wireframe + label

    # and with the mcap library (what Foxglove reads)
    from mcap.reader import make_reader

    mcap_file = next(out.glob("*.mcap"))
    with open(mcap_file, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        per_topic = Counter(ch.topic for _, ch, _ in reader.iter_messages())
        summary = reader.get_summary()
        schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
    assert per_topic[MARKERS_TOPIC] == synced
    assert schemas[MARKERS_TOPIC].name == "visualization_msgs/msg/MarkerArray"
    assert schemas[DETECTIONS_TOPIC].name == "vision_msgs/msg/Detection3DArray"
    assert schemas[MARKERS_TOPIC].encoding == "ros2msg"


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "shape-detector"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "shape_detector"]
    env = child_env()
    return subprocess.run(cmd + ["replay", *args], capture_output=True, text=True, timeout=timeout, env=env)


def test_replay_cli(bag, tmp_path):
    synced, _ = _count_input(bag)
    out = tmp_path / "cli_out"
    det_args = [] if WEIGHTS.exists() else ["--detector", "test_replay:FakeDetector"]
    r = _cli(str(bag), "-o", str(out), "--no-progress", *det_args)
    assert r.returncode == 0, r.stderr + r.stdout
    assert f"{synced} synchronised / {synced} out" in r.stdout
    assert "ms/frame" in r.stdout
    # exists -> refused without --overwrite, clear message
    r2 = _cli(str(bag), "-o", str(out), *det_args)
    assert r2.returncode == 1 and "--overwrite" in r2.stderr
    r3 = _cli(str(bag))
    assert r3.returncode == 2 and "-o/--out" in r3.stderr


def test_replay_truncated_bag_keeps_frames_before_damage(tmp_path):
    src = write_rgbd_bag(tmp_path / "good", synthetic_frames(10, 160, 120))
    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    f = next(bad.glob("*.mcap"))
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * 0.6)])
    det = FakeDetector()
    s = replay_bag(bad, tmp_path / "out", det, progress=False)
    assert not s.ok and "damaged" in s.error and "cut off" in s.error
    assert 3 <= s.frames_out < 10 and s.frames_out == s.synced == len(det.calls)
    assert "before the damage" in s.format()
    n_markers = sum(1 for t, _, _ in read_messages(tmp_path / "out") if t == MARKERS_TOPIC)
    assert n_markers == s.frames_out
    r = _cli(str(bad), "-o", str(tmp_path / "cli_out"), "--detector", "test_replay:FakeDetector", "--no-progress")
    assert r.returncode == 1 and "damaged" in r.stderr
    assert f"{s.frames_out} out" in r.stdout


def test_replay_unreadable_inputs_error_clearly(tmp_path):
    (tmp_path / "junk.mcap").write_bytes(os.urandom(2000))
    r = _cli(str(tmp_path / "junk.mcap"), "-o", str(tmp_path / "o1"), "--detector", "test_replay:FakeDetector")
    assert r.returncode == 1 and "junk.mcap" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o1").exists()
    r = _cli(str(tmp_path / "missing"), "-o", str(tmp_path / "o2"), "--detector", "test_replay:FakeDetector")
    assert r.returncode == 1 and "no such bag" in r.stderr
    r = _cli(str(tmp_path / "junk.mcap"), "-o", str(tmp_path / "o3"), "--detector", "nope_module:X")
    assert r.returncode == 1 and "cannot create the detector" in r.stderr


def test_replay_ros1_sqlite_and_bad_frames(tmp_path):
    fr = synthetic_frames(4, 160, 120)
    ros1 = write_rgbd_bag(tmp_path / "in.bag", fr, storage="ros1", color_encoding="bgr8")
    s = replay_bag(ros1, tmp_path / "o1", FakeDetector(), progress=False)
    assert s.ok and s.frames_out == 4 and s.copied["/camera/color/image_raw"] == 4
    sql = write_rgbd_bag(tmp_path / "in_sql", fr, storage="sqlite3", depth_encoding="32FC1")
    s = replay_bag(sql, tmp_path / "o2", FakeDetector(), progress=False)
    assert s.ok and s.frames_out == 4
    # a frame whose depth is at another aspect ratio: skipped, but still one (empty) marker message
    from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image, rosbags_types
    from rosbags.rosbag2 import StoragePlugin, Writer

    T = rosbags_types()
    st = T.typestore
    p = tmp_path / "mixed"
    with Writer(p, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/c/color/image_raw", "sensor_msgs/msg/Image", typestore=st)
        cd = w.add_connection("/c/depth/image_raw", "sensor_msgs/msg/Image", typestore=st)
        ck = w.add_connection("/c/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=st)
        for k, (t, rgb, depth, KK) in enumerate(fr):
            if k == 1:
                depth = np.ones((100, 100))
            w.write(ck, t, st.serialize_cdr(K_to_camera_info(KK / 2, 160, 120, T, t, "cam"), "sensor_msgs/msg/CameraInfo"))
            w.write(ci, t, st.serialize_cdr(numpy_to_image(rgb, "rgb8", T, t, "cam"), "sensor_msgs/msg/Image"))
            w.write(cd, t, st.serialize_cdr(depth_to_image(depth, T, "16UC1", t, "cam"), "sensor_msgs/msg/Image"))
    det = FakeDetector()
    s = replay_bag(p, tmp_path / "o3", det, progress=False)
    assert s.ok and s.synced == 4 and s.frames_out == 4 and s.skipped["size"] == 1 and len(det.calls) == 3
    assert any("100x100" in n for n in s.notes)


def test_replay_up_from_imu_or_fixed_and_external_boxes(tmp_path):
    from msg_conversion import rosbags_types
    from rosbags.rosbag2 import StoragePlugin, Writer

    fr = synthetic_frames(3, 160, 120)
    T = rosbags_types()
    st = T.typestore
    base = write_rgbd_bag(tmp_path / "base", fr)
    p = tmp_path / "with_imu"
    with Writer(p, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for topic, t, msg in read_messages(base):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=st)
            w.write(conns[topic], t, st.serialize_cdr(msg, msg.__msgtype__))
        cimu = w.add_connection("/camera/imu", "sensor_msgs/msg/Imu", typestore=st)
        cdet = w.add_connection("/yolo/detections", "vision_msgs/msg/Detection2DArray", typestore=st)
        from msg_conversion import make_header

        for k in range(40):
            t = fr[0][0] - 200 * MS + k * 20 * MS
            imu = T.make_by_name("sensor_msgs/msg/Imu", header=make_header(T, t, "imu"),
                                 linear_acceleration=T.make(T.Vector3, x=0.0, y=-9.5, z=-2.0))
            w.write(cimu, t, st.serialize_cdr(imu, "sensor_msgs/msg/Imu"))
        for t, *_ in fr:
            bb = T.make(T.BoundingBox2D, size_x=40.0, size_y=20.0)
            bb.center.position.x, bb.center.position.y = 80.0, 60.0
            d = T.make(T.Detection2D, header=make_header(T, t, "cam"), bbox=bb)
            arr = T.make(T.Detection2DArray, header=make_header(T, t, "cam"), detections=[d])
            w.write(cdet, t + 1 * MS, st.serialize_cdr(arr, "vision_msgs/msg/Detection2DArray"))
    det = FakeDetector()
    s = replay_bag(p, tmp_path / "o1", det, {"imu": "/camera/imu", "detections2d": "/yolo/detections"}, progress=False)
    assert s.ok and s.frames_out == 3, s.format()
    up = det.calls[-1]["up"]
    np.testing.assert_allclose(up, np.array([0, -9.5, -2.0]) / np.linalg.norm([0, -9.5, -2.0]), atol=1e-6)
    assert det.calls[0]["boxes2d"][0][:4] == (60.0, 50.0, 100.0, 70.0)
    det = FakeDetector()
    s = replay_bag(p, tmp_path / "o2", det, progress=False, up=(0, -2, 0))
    np.testing.assert_allclose(det.calls[0]["up"], [0, -1, 0])
    assert det.calls[0]["boxes2d"] is None


def test_play_cli_publishes_live(bag, ros_context):
    """``replay --play`` publishes the bag; a subscriber here receives every image, re-stamped."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    n_img = sum(1 for t, _, _ in read_messages(bag) if t.endswith("color/image_raw"))
    with BagFrameReader(bag) as r:
        image_topic, info_topic = r.selection.image, r.selection.camera_info
    node = rclpy.create_node("play_cli_listener", context=ros_context)
    got, infos = [], []
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Image, "/played/image", lambda m: got.append((time.time_ns(), m.header.stamp)), qos)
    node.create_subscription(CameraInfo, info_topic, lambda m: infos.append(m), qos)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    exe = Path(sys.executable).parent / "shape-detector"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "shape_detector"]
    proc = subprocess.Popen(
        cmd + ["replay", str(bag), "--play", "--rate", "2", "--restamp", "--wait-subscribers", "20",
               "--topics", image_topic, info_topic, "--remap", f"{image_topic}:=/played/image"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=child_env(),
    )
    try:
        deadline = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        ex.shutdown()
        node.destroy_node()
    assert proc.returncode == 0, err
    assert f"played {2 * n_img} messages" in out
    assert len(got) == n_img and len(infos) == n_img
    # re-stamped: stamps are close to the arrival time (well under a second)
    lat = [(arr - (s.sec * 10**9 + s.nanosec)) / 1e9 for arr, s in got]
    assert all(-0.05 < x < 1.0 for x in lat), lat


def test_play_bag_ros1_in_process(tmp_path, ros_context):
    """play_bag converts ROS 1 messages to ROS 2 and publishes them (as fast as possible)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from shape_detector.replay import play_bag

    fr = synthetic_frames(4, 64, 48)
    p = write_rgbd_bag(tmp_path / "in.bag", fr, storage="ros1")
    node = rclpy.create_node("play_ros1_listener", context=ros_context)
    imgs, infos = [], []
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Image, "/r1/image", imgs.append, qos)
    node.create_subscription(CameraInfo, "/camera/color/camera_info", infos.append, qos)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    import threading

    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    try:
        s = play_bag(p, 0.0, context=ros_context, wait_subscribers=10.0, remap={"/camera/color/image_raw": "/r1/image"},
                     topics=["/camera/color/image_raw", "/camera/color/camera_info"], node_name="ros1_player")
        deadline = time.monotonic() + 10
        while (len(imgs) < 4 or len(infos) < 4) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        ex.shutdown(timeout_sec=2)
        th.join(timeout=5)  # rclpy's shutdown does not wait for a spinning thread
        assert not th.is_alive()
        node.destroy_node()
    assert s.published == 8 and not s.skipped_topics
    assert len(imgs) == 4 and len(infos) == 4
    assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in imgs] == [t for t, *_ in fr]
    assert imgs[0].width == 64 and abs(infos[0].k[0] - 300.0) < 1e-9


@pytest.mark.parametrize("flags, want", [([], None), (["--detections2d", "/boxes"], "external"),
                                         (["--proposal-source", "geometric"], "geometric")])
def test_replay_proposes_as_the_preset_unless_told_otherwise(tmp_path, flags, want):
    """Without a choice, replay runs the realtime preset's proposals (what the node runs)."""
    import argparse

    from shape_detector.bags.replay_cli import run_offline
    from shape_detector.detector_config import preset
    from shape_detector.replay import configure_parser

    p = argparse.ArgumentParser()
    configure_parser(p)
    args = p.parse_args([str(tmp_path / "in"), "-o", str(tmp_path / "out"), *flags])
    seen = {}

    def make_detector(config, _factory):
        seen["source"] = config.proposal_source
        raise RuntimeError("stop here")

    run_offline(args, make_detector, lambda *a, **k: None)
    assert seen["source"] == (want or preset("realtime").proposal_source)
