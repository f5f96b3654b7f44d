"""Fuzz-style robustness: malformed messages never stop the node; damaged bags make replay
fail clearly (and keep what came before the damage), never with a traceback."""

from __future__ import annotations

import array
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from child_env import child_env
from shape_detector.bags.source import BagReadError
from shape_detector.synth.bag import write_rgbd_bag
from shape_detector.node_params import PARAMETERS
from shape_detector.node_stats import stats_line
from shape_detector.replay import replay_bag
from shape_detector.types import Object3D

ROOT = Path(__file__).resolve().parents[1]
MS = 1_000_000
PARAMETERS_DEFAULT_WARN = PARAMETERS["warn_image_bytes"].default
K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])


class MoodyDetector:
    """Returns a good object, raises, or returns garbage, on request."""

    def __init__(self, **kwargs):
        self.mode = "ok"
        self.calls = 0

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        self.calls += 1
        if self.mode == "raise":
            raise RuntimeError("boom")
        if self.mode == "nan":
            return [Object3D("bed", float("nan"), [np.nan, 0, np.inf], [np.nan, 1, 1], np.full((3, 3), np.nan))]
        if self.mode == "junk":
            return [object()]
        return [Object3D("desk", 0.6, [0, 0, float(np.nanmedian(depth))], [1.2, 0.6, 0.75], np.eye(3))]


# =====================================================================================
# the node
# =====================================================================================


@pytest.fixture(scope="module")
def fuzz_node(ros_context):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from ros_spin import spinning

    from msg_conversion import rclpy_types
    from shape_detector.node import DetectorNode

    T = rclpy_types()
    det = MoodyDetector()
    node = DetectorNode("sd_fuzz", context=ros_context, detector=det,
                        cli_args=["--ros-args", "-r", "image:=/fz/image", "-r", "depth:=/fz/depth",
                                  "-r", "camera_info:=/fz/info"])
    tester = rclpy.create_node("sd_fuzz_tester", context=ros_context)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {
        "image": tester.create_publisher(T.Image, "/fz/image", qos),
        "depth": tester.create_publisher(T.Image, "/fz/depth", qos),
        "info": tester.create_publisher(T.CameraInfo, "/fz/info", qos),
    }
    markers: list = []
    tester.create_subscription(T.MarkerArray, "/sd_fuzz/markers", markers.append, qos)
    with spinning(ros_context, (node, tester), [*pubs.values(), node.markers_pub]):
        time.sleep(0.2)
        yield node, det, pubs, markers, T


def _image(T, w, h, enc, data, step=None, stamp=0, frame="cam"):
    from msg_conversion import make_header

    m = T.Image()
    m.header = make_header(T, stamp, frame)
    m.width, m.height, m.encoding = w, h, enc
    m.step = step if step is not None else 0
    m.data = array.array("B", bytes(data))
    return m


def _send(fuzz, image, depth, info=None, wait=True):
    node, det, pubs, markers, T = fuzz
    n = len(markers)
    if info is not None:
        got = node.counters["received_camera_info"]
        pubs["info"].publish(info)
        # the frame must meet this camera_info, not the previous one: wait until the node has
        # it (else the executor may hand over image and depth first)
        deadline = time.monotonic() + 5
        while node.counters["received_camera_info"] == got and time.monotonic() < deadline:
            time.sleep(0.005)
    pubs["image"].publish(image)
    pubs["depth"].publish(depth)
    if wait:
        deadline = time.monotonic() + 10
        while len(markers) < n + 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(markers) == n + 1, "the node stopped answering"
        return markers[-1]
    return None


def _good(T, stamp, w=80, h=60):
    from msg_conversion import depth_to_image, numpy_to_image

    return (numpy_to_image(np.full((h, w, 3), 50, np.uint8), "rgb8", T, stamp, "cam"),
            depth_to_image(np.full((h, w), 2.0), T, "16UC1", stamp, "cam"))


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_malformed_messages_never_stop_the_node(fuzz_node):
    from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image

    node, det, pubs, markers, T = fuzz_node
    s = [time.time_ns() + k * 10 * MS for k in range(100)]
    img, dep = _good(T, s[0])
    # 1. no camera_info yet: skipped with a warning, empty MarkerArray (DELETEALL only)
    m = _send(fuzz_node, img, dep)
    assert len(m.markers) == 1 and node.counters["skipped_camera_info"] == 1
    info = K_to_camera_info(K, 80, 60, T, s[1], "cam")
    cases = []
    # 2. wrong / unknown encodings, swapped topics
    cases.append(("encoding", _image(T, 80, 60, "yuv422", b"\0" * 80 * 60 * 2, 160, s[2]), dep))
    cases.append(("encoding", img, _image(T, 80, 60, "rgb8", b"\0" * 80 * 60 * 3, 240, s[3])))
    cases.append(("encoding", dep, img))
    # 3. data shorter than height * step, step too small, absurd sizes with little data
    cases.append(("encoding", _image(T, 80, 60, "rgb8", b"\1" * 100, 240, s[4]), dep))
    cases.append(("encoding", _image(T, 80, 60, "rgb8", b"\1" * 80 * 60 * 3, 10, s[5]), dep))
    cases.append(("encoding", _image(T, 100000, 100000, "rgb8", b"\1" * 64, 300000, s[6]), dep))
    # 4. empty images
    cases.append(("empty", _image(T, 0, 0, "rgb8", b"", 0, s[7]), dep))
    cases.append(("empty", img, _image(T, 0, 0, "16UC1", b"", 0, s[8])))
    # 5. sizes that cannot be reconciled (4:3 colour, 16:9 depth)
    cases.append(("size", numpy_to_image(np.zeros((60, 80, 3), np.uint8), "rgb8", T, s[9], "cam"),
                  depth_to_image(np.ones((45, 80)), T, "16UC1", s[9], "cam")))
    for kind, bad_img, bad_dep in cases:
        before = node.counters[f"skipped_{kind}"]
        stamp = bad_img.header.stamp
        bad_dep.header.stamp = stamp  # make them a synchronised pair
        m = _send(fuzz_node, bad_img, bad_dep, info)
        assert len(m.markers) == 1, kind  # DELETEALL only
        assert node.counters[f"skipped_{kind}"] == before + 1, (kind, dict(node.counters))
    # 6. camera_info broken: all-zero K, NaN K
    for bad_k in (np.zeros((3, 3)), np.full((3, 3), np.nan)):
        bad_info = K_to_camera_info(bad_k, 80, 60, T, s[20], "cam")
        bi, bd = _good(T, s[20] + len(markers))
        m = _send(fuzz_node, bi, bd, bad_info)
        assert len(m.markers) == 1
    assert node.counters["skipped_camera_info"] >= 3
    # 7. NaN / Inf depth everywhere: processed, nothing detected, no detector call
    calls = det.calls
    d32 = np.full((60, 80), np.inf, np.float32)
    d32[::2] = np.nan
    bi = numpy_to_image(np.zeros((60, 80, 3), np.uint8), "rgb8", T, s[30], "cam")
    m = _send(fuzz_node, bi, depth_to_image(d32, T, "32FC1", s[30], "cam"), info)
    assert len(m.markers) == 1 and det.calls == calls and node.counters["skipped_no_depth"] == 1
    # 8. half-resolution depth is rescaled and processed
    bi = numpy_to_image(np.zeros((120, 160, 3), np.uint8), "rgb8", T, s[31], "cam")
    info160 = K_to_camera_info(K * np.array([[2], [2], [1]]), 160, 120, T, s[31], "cam")
    m = _send(fuzz_node, bi, depth_to_image(np.full((60, 80), 2.0), T, "16UC1", s[31], "cam"), info160)
    assert len(m.markers) == 4
    # 9. the detector raising, returning NaN boxes or junk
    for k, mode in enumerate(("raise", "nan", "junk")):
        det.mode = mode
        bi, bd = _good(T, s[40 + k])
        m = _send(fuzz_node, bi, bd, info)
        assert m.markers[0].action == 3
    det.mode = "ok"
    assert node.counters["detector_errors"] >= 1
    # 10. headerless-looking stamps (zero) and an empty frame_id still answer
    bi, bd = _good(T, 0)
    bi.header.frame_id = bd.header.frame_id = ""
    _send(fuzz_node, bi, bd, info)
    # and a good frame afterwards is detected normally
    bi, bd = _good(T, s[60])
    m = _send(fuzz_node, bi, bd, info)
    assert len(m.markers) == 4 and m.markers[3].text.startswith("desk")
    assert node._worker.is_alive()
    # the worker counts a frame as processed just after publishing it: let the counters settle
    deadline = time.monotonic() + 5
    while node.get_stats()["processed"] < len(markers) and time.monotonic() < deadline:
        time.sleep(0.01)
    st = node.get_stats()
    assert st["processed"] == st["published"] == len(markers)


class _Log:
    """Stands in for the node's rclpy logger: keeps every line."""

    def __init__(self):
        self.lines: list[str] = []

    def warning(self, text):
        self.lines.append(text)

    error = info = warning


@pytest.fixture
def node_log(fuzz_node, monkeypatch):
    log = _Log()
    monkeypatch.setattr(fuzz_node[0], "get_logger", lambda: log)
    return log


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_distinct_problems_of_one_kind_are_each_reported(fuzz_node, node_log):
    from msg_conversion import K_to_camera_info

    node, det, pubs, markers, T = fuzz_node
    s = time.time_ns()
    info = K_to_camera_info(K, 80, 60, T, s, "cam")
    _, dep = _good(T, s)
    # encodings no earlier test used: their problems are new to the node
    first, second, again = (_image(T, 80, 60, enc, b"\0" * 80 * 60 * 2, 160, s + k * MS)
                            for k, enc in ((1, "fuzz_enc_a"), (2, "fuzz_enc_b"), (3, "fuzz_enc_a")))
    for img in (first, second, again):  # within one rate-limit period
        dep.header.stamp = img.header.stamp
        _send(fuzz_node, img, dep, info)
    skipped = [ln for ln in node_log.lines if ln.startswith("frame skipped")]
    # two reasons of the same kind: both told; the repeat of the first held back
    assert len(skipped) == 2, node_log.lines
    assert "fuzz_enc_a" in skipped[0] and "fuzz_enc_b" in skipped[1]


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_restamped_and_original_stamps_do_not_spoil_the_statistics(fuzz_node, node_log):
    from msg_conversion import K_to_camera_info

    node, det, pubs, markers, T = fuzz_node
    info = K_to_camera_info(K, 80, 60, T, time.time_ns(), "cam")
    before = node.get_stats().get("implausible_stamps", 0)
    for k in range(6):  # a bag's original stamps (years old) between current ones
        stamp = time.time_ns() if k % 2 else 1_600_000_000 * 10**9 + k * MS
        _send(fuzz_node, *_good(T, stamp), info)
    deadline = time.monotonic() + 5
    while node.get_stats().get("implausible_stamps", 0) < before + 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    st = node.get_stats()
    assert st["implausible_stamps"] == before + 3
    assert 0 <= st["latency_p50_ms"] <= st["latency_p95_ms"] < 60_000
    line = stats_line(st, 1.0)
    assert "stamp->publish p50" in line and "not counted" in line


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_large_images_are_reported_once_per_topic(fuzz_node, node_log):
    from rclpy.parameter import Parameter

    from msg_conversion import K_to_camera_info

    node, det, pubs, markers, T = fuzz_node
    info = K_to_camera_info(K, 80, 60, T, time.time_ns(), "cam")
    assert node.set_parameters([Parameter("warn_image_bytes", value=5000)])[0].successful
    try:
        for _ in range(3):
            _send(fuzz_node, *_good(T, time.time_ns()), info)  # 14 kB colour, 9.6 kB depth
    finally:
        node.set_parameters([Parameter("warn_image_bytes", value=PARAMETERS_DEFAULT_WARN)])
    big = [ln for ln in node_log.lines if "warn_image_bytes" in ln]
    assert len(big) == 2 and any("/fz/image" in ln for ln in big) and any("/fz/depth" in ln for ln in big)
    assert all("qos:=reliable" in ln for ln in big)


@pytest.mark.ros
@pytest.mark.timeout(60)
@pytest.mark.parametrize("name, value", [
    ("max_objects", 0), ("depth_scale", -0.001), ("score_threshold", 1.5), ("refine_min_score", -0.1),
    ("sync_queue_size", 0), ("warn_image_bytes", -1), ("up", [0.0, 0.0, 0.0]), ("up_source", "gyro"),
    ("size_mismatch", "crop"),
])
def test_parameter_changes_are_validated_with_a_reason(fuzz_node, name, value):
    from rclpy.parameter import Parameter

    node = fuzz_node[0]
    old = node.get_parameter(name).value
    res = node.set_parameters([Parameter(name, value=value)])[0]
    assert not res.successful and name in res.reason, res.reason
    assert node.get_parameter(name).value == old and node.p[name] == old


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_invalid_parameters_at_start_are_refused(ros_context):
    from rclpy.parameter import Parameter

    from shape_detector.node import DetectorNode

    with pytest.raises(Exception) as info:
        DetectorNode("sd_bad_start", context=ros_context, detector=MoodyDetector(),
                     parameter_overrides=[Parameter("up_source", value="fixed"), Parameter("up", value=[0.0, 0.0, 0.0])])
    assert "up" in str(info.value)


# =====================================================================================
# bags
# =====================================================================================


def _frames(n=5, w=80, h=60):
    t0 = 1_700_000_000 * 10**9
    return [(t0 + k * 200 * MS, np.full((h, w, 3), k, np.uint8), np.full((h, w), 2.0), K) for k in range(n)]


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory):
    return write_rgbd_bag(tmp_path_factory.mktemp("fz") / "good", _frames(6), depth_offset_ns=2 * MS)


def _run(bag, out):
    """replay_bag on a damaged bag: a summary, or one of the documented clear errors."""
    try:
        s = replay_bag(bag, out, MoodyDetector(), progress=False)
    except (BagReadError, ValueError, FileNotFoundError) as e:
        assert str(e)
        return None
    assert s.frames_out == s.synced
    if s.error:
        assert "damaged" in s.error
    return s


def test_truncation_at_every_tenth(good_bag, tmp_path):
    data = next(good_bag.glob("*.mcap")).read_bytes()
    outs = []
    for k, frac in enumerate(np.linspace(0.05, 0.98, 12)):
        bad = tmp_path / f"t{k}"
        bad.mkdir()
        shutil.copy(good_bag / "metadata.yaml", bad / "metadata.yaml")
        (bad / next(good_bag.glob("*.mcap")).name).write_bytes(data[: int(len(data) * frac)])
        outs.append(_run(bad, tmp_path / f"o{k}"))
    done = [s.frames_out for s in outs if s is not None]
    assert done == sorted(done)  # more file, never fewer frames
    assert done and done[-1] >= 5
    assert all(s.error for s in outs if s is not None)


def test_random_corruption(good_bag, tmp_path):
    data = bytearray(next(good_bag.glob("*.mcap")).read_bytes())
    rng = np.random.default_rng(1)
    for k in range(12):
        bad = tmp_path / f"c{k}"
        bad.mkdir()
        d = bytearray(data)
        for pos in rng.integers(0, len(d), size=int(rng.integers(1, 40))):
            d[pos] = int(rng.integers(0, 256))
        (bad / "c.mcap").write_bytes(bytes(d))
        _run(bad / "c.mcap", tmp_path / f"o{k}")


def test_bad_metadata_and_empty_files(good_bag, tmp_path):
    for k, content in enumerate([b"", b"rosbag2_bagfile_information:\n  version: [", os.urandom(300)]):
        bad = tmp_path / f"m{k}"
        shutil.copytree(good_bag, bad)
        (bad / "metadata.yaml").write_bytes(content)
        _run(bad, tmp_path / f"o{k}")
    (tmp_path / "empty.mcap").write_bytes(b"")
    assert _run(tmp_path / "empty.mcap", tmp_path / "oe") is None
    (tmp_path / "empty.bag").write_bytes(b"")
    assert _run(tmp_path / "empty.bag", tmp_path / "oe2") is None


@pytest.mark.timeout(180)
def test_cli_reports_damage_without_traceback(good_bag, tmp_path):
    bad = tmp_path / "bad.mcap"
    data = next(good_bag.glob("*.mcap")).read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    exe = Path(sys.executable).parent / "shape-detector"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "shape_detector"]
    env = child_env()
    r = subprocess.run(cmd + ["replay", str(bad), "-o", str(tmp_path / "out"), "--no-progress",
                              "--detector", "test_node_fuzz:MoodyDetector"],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 1
    assert "damaged" in r.stderr and "Traceback" not in r.stderr + r.stdout
    assert (tmp_path / "out" / "metadata.yaml").exists()
