"""Acceptance: ``detector_node`` started as a subprocess through its console script
(LOCALHOST discovery, this run's domain id, shared-memory Fast DDS), the sample bag played
into it, one MarkerArray per synchronised frame with the right stamps and frame_id."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from shape_detector.bags.reader import BagFrameReader  # noqa: E402
from shape_detector.synth.bag import write_rgbd_bag  # noqa: E402
from shape_detector.node_bench import MarkerListener, OutputCollector, node_command, start_node, stop_node  # noqa: E402
from shape_detector.replay import play_bag  # noqa: E402
from shape_detector.types import Object3D  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TEST_DIR = Path(__file__).resolve().parent
WEIGHTS = ROOT / "shape_detector" / "weights" / "default.pt"
MS = 1_000_000

# a hung child or ROS graph fails the test with a stack dump instead of holding the run;
# every child is stopped and reaped (its process group killed) in a finally
pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]


class FakeDetector:
    """Loaded by the node via ``detector_factory:=test_node_subprocess:FakeDetector`` when
    there are no trained weights."""

    def __init__(self, **kwargs):
        self.kwargs = kwargs

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        z = float(np.nanmedian(depth))
        return [Object3D("sofa", 0.8, [0.0, 0.3, z], [0.9, 1.9, 0.8], np.eye(3))]


@pytest.fixture(scope="module")
def bag(sample_bag, tmp_path_factory) -> Path:
    if sample_bag.exists():
        return sample_bag
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    frames = []
    t0 = 1_700_000_000 * 10**9
    for k in range(12):  # VGA, 5 Hz, depth 3 ms after colour, like the sample bag
        rgb = np.full((480, 640, 3), 120, np.uint8)
        depth = np.full((480, 640), 3.0)
        depth[200:, 200:400] = 1.8
        frames.append((t0 + k * 200 * MS, rgb, depth, K))
    return write_rgbd_bag(tmp_path_factory.mktemp("bags") / "sample", frames, depth_offset_ns=3 * MS)


def test_console_script_node_receives_bag(bag, ros_context):
    with BagFrameReader(bag, slop=0.02, queue_size=10) as reader:
        sel = reader.selection
        expected = [(f.stamp_ns, f.frame_id) for f in reader.frames()]
    assert len(expected) >= 10
    cmd = node_command()
    if (Path(sys.executable).parent / "detector_node").exists():
        assert cmd[0].endswith("detector_node")  # the installed console script is what runs
    params = {"stats_period": 1.0}
    if not WEIGHTS.exists():
        params["detector_factory"] = "test_node_subprocess:FakeDetector"
    proc = start_node(
        {"image": sel.image, "depth": sel.depth, "camera_info": sel.camera_info},
        params,
        extra_pythonpath=[str(TEST_DIR)],
        params_file=ROOT / "config" / "detector.yaml",
    )
    out = OutputCollector(proc)
    listener = MarkerListener(ros_context)
    try:
        assert out.wait_for("ready:", 120), out.text
        # the real network may need more than the 200 ms between sample frames on 2 cores:
        # play slower then, so that the node (which drops what it cannot keep up with) sees all
        rate = 1.0 if not WEIGHTS.exists() else 0.2
        summary = play_bag(bag, rate, context=ros_context, wait_subscribers=20.0, node_name="acceptance_player")
        assert summary.error is None
        listener.wait_quiet(len(expected), timeout=60.0, quiet=3.0)
        received = list(listener.received)
        time.sleep(1.2)  # one more stats period for the log
    finally:
        # the child first: a hang in this process' ROS teardown must not leave it unreaped
        rc = stop_node(proc)
        listener.close()
    log = out.text
    assert rc == 0, log
    assert len(received) == len(expected), log
    assert [(r[1], r[2]) for r in received] == expected
    if not WEIGHTS.exists():
        assert all(r[3] == 4 for r in received)  # DELETEALL + box, wireframe, label of the sofa
    assert "frames/s" in log and "synced" in log
    assert "Traceback" not in log


@pytest.mark.parametrize("params, reason", [
    ({"up_source": "sideways"}, "up_source must be one of"),
    ({"depth_scale": -1.0}, "depth_scale"),
])
def test_node_exits_cleanly_on_bad_configuration(params, reason):
    proc = start_node({}, {**params, "detector_factory": "test_node_subprocess:FakeDetector"},
                      extra_pythonpath=[str(TEST_DIR)])
    out = OutputCollector(proc)
    try:
        proc.wait(timeout=60)
    finally:
        stop_node(proc)
    time.sleep(0.2)
    assert proc.returncode == 1, out.text
    assert reason in out.text and "Traceback" not in out.text


def test_4000x3000_best_effort_frame_reaches_the_node_and_sigterm_stops_it(ros_context):
    """Through the shipped shared-memory profile (the test environment's), a best-effort
    36 MB colour + 24 MB depth frame reaches the node, which says once (for the colour
    topic) that such images are near the transport's limit; SIGTERM then ends it cleanly."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image, rclpy_types

    T = rclpy_types()
    h, w = 3000, 4000
    stamp = time.time_ns()
    K = np.array([[2000.0, 0, 1999.5], [0, 2000.0, 1499.5], [0, 0, 1]])
    rgb = numpy_to_image(np.full((h, w, 3), 90, np.uint8), "rgb8", T, stamp, "cam4k")
    depth = depth_to_image(np.full((h, w), 2.0), T, "16UC1", stamp, "cam4k")
    info = K_to_camera_info(K, w, h, T, stamp, "cam4k")
    proc = start_node({"image": "/big/image", "depth": "/big/depth", "camera_info": "/big/info"},
                      {"detector_factory": "test_node_subprocess:FakeDetector", "qos": "sensor_data",
                       "stats_period": 1.0}, extra_pythonpath=[str(TEST_DIR)], node_name="sd_big")
    out = OutputCollector(proc)
    listener = MarkerListener(ros_context, "/sd_big/markers")
    pub_node = rclpy.create_node("big_frame_publisher", context=ros_context)
    best_effort = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    pubs = [pub_node.create_publisher(T.CameraInfo, "/big/info", best_effort),
            pub_node.create_publisher(T.Image, "/big/image", best_effort),
            pub_node.create_publisher(T.Image, "/big/depth", best_effort)]
    try:
        assert out.wait_for("ready:", 120), out.text
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in pubs):
            time.sleep(0.05)
        # best effort: a send may be lost (a reader not matched yet, a busy listener); a
        # frame larger than the segment never arrives
        sends = 0
        while time.monotonic() < deadline and not listener.received and sends < 10:
            for p, m in zip(pubs, (info, rgb, depth)):
                p.publish(m)
            sends += 1
            listener.wait_quiet(1, timeout=3.0, quiet=3.0)
        received = list(listener.received)
        time.sleep(1.5)  # a stats period for the log
        rc = stop_node(proc, timeout=20.0, sig=signal.SIGTERM)
    finally:
        stop_node(proc)
        listener.close()
        pub_node.destroy_node()
    log = out.text
    assert received and received[0][1] == stamp and received[0][2] == "cam4k", f"{sends} sends\n{log}"
    # the colour image (36 MB) is over the default warn_image_bytes (32 MiB), the depth (24 MB) not
    assert log.count("warn_image_bytes") == 1 and "/big/image: 34.3 MiB" in log, log
    assert rc == 0 and "Traceback" not in log, log


def test_node_with_detector_processes_stops_on_ctrl_c_without_leftovers():
    """Ctrl-C reaches the node's whole process group, its detector processes included: the
    node stops them itself and exits cleanly, and none is left behind."""
    proc = start_node({}, {"detector_factory": "test_node_subprocess:FakeDetector", "detector_processes": 2},
                      extra_pythonpath=[str(TEST_DIR)], node_name="sd_procs")
    out = OutputCollector(proc)
    try:
        assert out.wait_for("ready:", 120), out.text
        children = [int(c) for t in Path(f"/proc/{proc.pid}/task").iterdir()
                    for c in (t / "children").read_text().split()]
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C
        rc = proc.wait(timeout=30)
        # the workers have been joined; the resource tracker follows its parent within moments
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and [c for c in children if _alive(c)]:
            time.sleep(0.1)
        left = [(c, Path(f"/proc/{c}/cmdline").read_text()) for c in children if _alive(c)]
    finally:
        stop_node(proc)
    log = out.text
    assert rc == 0, log
    assert "2 worker process(es)" in log
    assert len(children) >= 2, log  # the workers (and the shared-memory resource tracker)
    assert not left
    assert "Traceback" not in log and "KeyboardInterrupt" not in log


def _alive(pid: int) -> bool:
    try:
        return "zombie" not in Path(f"/proc/{pid}/status").read_text().lower()
    except OSError:
        return False
