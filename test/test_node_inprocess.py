"""detector_node in this process, spun by an executor thread: topics, stamps, never falling
behind, parameters (dynamic ones, validation), up from a fixed vector or an IMU."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from msg_conversion import K_to_camera_info, depth_to_image, make_header, numpy_to_image, rclpy_types  # noqa: E402
from shape_detector.node import DetectorNode  # noqa: E402
from shape_detector.types import Object3D  # noqa: E402

# a hung ROS graph fails the test with a stack dump instead of holding the run
pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "shape_detector" / "weights" / "default.pt"
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
MS = 1_000_000


class FakeDetector:
    def __init__(self, delay: float = 0.0, **kwargs):
        self.delay = delay
        self.calls = []
        self.score_threshold = 0.3
        self.max_objects = 20
        self.nms_decay = 0.1
        self.refine = True
        self.refine_min_score = 0.1
        self.free_space = True

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        self.calls.append({"shape": rgb.shape, "up": up, "t": time.monotonic()})
        if self.delay:
            time.sleep(self.delay)
        z = float(np.nanmedian(depth))
        return [Object3D("table", 0.7, [0.1, 0.2, z], [1.0, 0.6, 0.7], np.eye(3))]


def make_detector():
    if WEIGHTS.exists():
        from shape_detector.detector import ShapeDetector

        return ShapeDetector()
    return FakeDetector()


class Harness:
    """A DetectorNode + a test node (publishers, markers subscriber) on one executor thread."""

    def __init__(self, ctx, name: str, detector, params=None, imu=False):
        self.types = rclpy_types()
        overrides = [Parameter(k, value=v) for k, v in (params or {}).items()]
        self.node = DetectorNode(name, context=ctx, detector=detector, parameter_overrides=overrides,
                                 cli_args=["--ros-args", "-r", f"image:=/{name}/in/image", "-r",
                                           f"depth:=/{name}/in/depth", "-r", f"camera_info:=/{name}/in/info",
                                           "-r", f"imu:=/{name}/in/imu"])
        self.test = rclpy.create_node(f"{name}_tester", context=ctx)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        T = self.types
        self.pub_img = self.test.create_publisher(T.Image, f"/{name}/in/image", qos)
        self.pub_depth = self.test.create_publisher(T.Image, f"/{name}/in/depth", qos)
        self.pub_info = self.test.create_publisher(T.CameraInfo, f"/{name}/in/info", qos)
        if imu:
            from sensor_msgs.msg import Imu

            self.pub_imu = self.test.create_publisher(Imu, f"/{name}/in/imu", qos)
        self.markers = []
        self.test.create_subscription(T.MarkerArray, f"/{name}/markers", self.markers.append, qos)
        self.executor = SingleThreadedExecutor(context=ctx)
        self.executor.add_node(self.node)
        self.executor.add_node(self.test)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if (self.pub_img.get_subscription_count() and self.pub_depth.get_subscription_count()
                    and self.pub_info.get_subscription_count() and self.node.markers_pub.get_subscription_count()):
                break
            time.sleep(0.05)
        time.sleep(0.2)

    def frame(self, stamp_ns: int, w=320, h=240, frame_id="cam_optical", depth_offset_ns=2 * MS, info=True):
        T = self.types
        rgb = np.full((h, w, 3), 100, np.uint8)
        depth = np.full((h, w), 2.5)
        if info:
            self.pub_info.publish(K_to_camera_info(K, w, h, T, stamp_ns, frame_id))
        self.pub_img.publish(numpy_to_image(rgb, "rgb8", T, stamp_ns, frame_id))
        self.pub_depth.publish(depth_to_image(depth, T, "16UC1", stamp_ns + depth_offset_ns, frame_id))

    def play(self, stamps: list[int], gap: float, timeout: float = 10.0) -> dict:
        """Publish a frame per stamp, ``gap`` seconds apart; wait until every one is synced and
        then processed or dropped; return the node's stats."""
        for s in stamps:
            self.frame(s)
            time.sleep(gap)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            st = self.node.get_stats()
            if st.get("synced", 0) == len(stamps) and st.get("processed", 0) + st["dropped"] == len(stamps):
                break
            time.sleep(0.05)
        return self.node.get_stats()

    def wait_markers(self, n: int, timeout: float = 20.0) -> list:
        deadline = time.monotonic() + timeout
        while len(self.markers) < n and time.monotonic() < deadline:
            time.sleep(0.02)
        return self.markers

    def wait_processed(self, n: int, timeout: float = 5.0) -> dict:
        """The node's stats once it counted ``n`` processed frames (or at ``timeout``): a frame
        is counted after its markers are published, so a subscriber can see them first."""
        deadline = time.monotonic() + timeout
        while self.node.get_stats().get("processed", 0) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.node.get_stats()

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(timeout=5)
        assert not self.thread.is_alive(), "executor thread still spinning after shutdown"
        self.node.destroy_node()
        self.test.destroy_node()


@pytest.fixture
def harness(ros_context, request):
    made = []

    def make(name, detector=None, **kw):
        h = Harness(ros_context, name, detector if detector is not None else make_detector(), **kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


def stamp_of(ma) -> int:
    s = ma.markers[0].header.stamp
    return s.sec * 10**9 + s.nanosec


def test_one_marker_array_per_frame_with_stamp_and_frame(harness):
    h = harness("sd_basic")
    stamps = []
    for k in range(6):
        stamps.append(time.time_ns())
        h.frame(stamps[-1])
        got = len(h.wait_markers(k + 1))
        assert got == k + 1, f"frame {k}: {got} marker arrays, node stats {h.node.get_stats()}"  # lockstep: none dropped
    assert [stamp_of(m) for m in h.markers] == stamps
    assert all(m.markers[0].header.frame_id == "cam_optical" for m in h.markers)
    assert all(m.markers[0].action == 3 for m in h.markers)  # DELETEALL first
    stats = h.wait_processed(6)
    assert (stats["synced"], stats["processed"], stats["published"], stats["dropped"]) == (6, 6, 6, 0), stats
    assert stats["latency_p50_ms"] > 0, stats
    if isinstance(h.node.detector, FakeDetector):
        assert all(len(m.markers) == 4 for m in h.markers)
        assert h.markers[0].markers[3].text.startswith("table")
    assert h.node.resolve_topic_name("~/markers") == "/sd_basic/markers"


def test_never_falls_behind(harness):
    det = FakeDetector(delay=0.25)
    h = harness("sd_busy", det, params={"qos_depth": 20})
    t0 = time.time_ns()
    stamps = [t0 + k * 20 * MS for k in range(12)]
    st = h.play(stamps, gap=0.02)
    assert st["synced"] == 12
    assert st["dropped"] >= 5, st
    assert st["processed"] + st["dropped"] == 12
    h.wait_markers(st["processed"])
    assert stamp_of(h.markers[-1]) == stamps[-1]  # the newest set is never the one dropped
    got = [stamp_of(m) for m in h.markers]
    assert got == sorted(got)


def test_parameters_dynamic_and_validated(harness):
    det = FakeDetector()
    h = harness("sd_params", det, params={"up_source": "fixed", "up": [0, 0, 2]})  # integers are fine too
    n = h.node
    # descriptions and read-only flags are declared
    desc = n.describe_parameters(["score_threshold", "qos"])
    assert desc[0].description and not desc[0].read_only and desc[1].read_only
    res = n.set_parameters([Parameter("score_threshold", value=0.55), Parameter("max_objects", value=3)])
    assert all(r.successful for r in res) and det.score_threshold == 0.55 and det.max_objects == 3
    assert n.set_parameters([Parameter("nms_decay", value=0.0)])[0].successful and det.nms_decay == 0.0
    assert not n.set_parameters([Parameter("nms_decay", value=1.5)])[0].successful  # out of range
    res = n.set_parameters([Parameter("refine", value=False), Parameter("refine_min_score", value=0.25)])
    assert all(r.successful for r in res) and det.refine is False and det.refine_min_score == 0.25
    assert not n.set_parameters([Parameter("refine_min_score", value=-0.1)])[0].successful  # out of range
    assert n.set_parameters([Parameter("free_space", value=False)])[0].successful and det.free_space is False
    res = n.set_parameters([Parameter("sync_slop", value=0.001), Parameter("sync_queue_size", value=4)])
    assert all(r.successful for r in res) and n.sync.slop_ns == MS and n.sync.queue_size == 4
    assert not n.set_parameters([Parameter("up_source", value="gyro")])[0].successful
    assert not n.set_parameters([Parameter("up", value=[0.0, 0.0, 0.0])])[0].successful
    assert not n.set_parameters([Parameter("imu_to_camera", value=[0.0, 0.0, 0.0, 0.0])])[0].successful
    assert not n.set_parameters([Parameter("qos", value="reliable")])[0].successful  # read-only
    assert not n.set_parameters([Parameter("score_threshold", value=2.0)])[0].successful  # out of range
    # the 1 ms slop still pairs depth 0.5 ms late; the fixed up vector reaches the detector
    h.frame(time.time_ns(), depth_offset_ns=MS // 2)
    h.wait_markers(1)
    np.testing.assert_allclose(det.calls[-1]["up"], [0, 0, 1])
    # depth 3 ms late is now outside the slop: no set
    h.frame(time.time_ns(), depth_offset_ns=3 * MS)
    time.sleep(0.5)
    assert len(h.markers) == 1


def test_up_from_imu(harness):
    det = FakeDetector()
    # IMU z axis = camera -y (up), i.e. +90 deg about x
    q = [float(np.sin(np.pi / 4)), 0.0, 0.0, float(np.cos(np.pi / 4))]
    h = harness("sd_imu", det, params={"up_source": "imu", "imu_to_camera": q, "imu_time_constant": 0.05}, imu=True)
    from sensor_msgs.msg import Imu

    deadline = time.monotonic() + 5
    while not h.pub_imu.get_subscription_count() and time.monotonic() < deadline:
        time.sleep(0.05)
    t = time.time_ns()
    for k in range(30):
        m = Imu()
        m.header = make_header(h.types, t + k * 5 * MS, "imu")
        m.linear_acceleration.z = 9.81
        h.pub_imu.publish(m)
    deadline = time.monotonic() + 5
    while h.node.imu_filter.samples < 30 and time.monotonic() < deadline:
        time.sleep(0.02)
    h.frame(t + 200 * MS)
    h.wait_markers(1)
    np.testing.assert_allclose(det.calls[-1]["up"], [0, -1, 0], atol=1e-6)


def test_external_proposals_fall_back_without_vision_msgs(harness):
    try:
        import vision_msgs.msg  # noqa: F401

        pytest.skip("vision_msgs installed: external proposals are really used")
    except ImportError:
        pass
    h = harness("sd_ext", FakeDetector(), params={"proposal_source": "external"})
    assert not h.node.external and h.node.sync.num_inputs == 2
    h.frame(time.time_ns())
    assert len(h.wait_markers(1)) == 1


class StagedDetector(FakeDetector):
    """A FakeDetector with ShapeDetector's prepare()/finish() split, recording which thread ran
    each stage and when; ``fail_on`` (a depth value) makes finish() raise for that frame."""

    def __init__(self, delay: float = 0.0, fail_on: float | None = None, **kwargs):
        super().__init__(delay, **kwargs)
        self.stages: list[tuple[str, str, float, float]] = []  # (stage, thread, start, end)
        self.fail_on = fail_on

    def prepare(self, rgb, depth, K, boxes2d=None, up=None):
        t = time.monotonic()
        time.sleep(self.delay)
        self.stages.append(("prepare", threading.current_thread().name, t, time.monotonic()))
        return float(np.nanmedian(depth))

    def finish(self, z):
        t = time.monotonic()
        time.sleep(self.delay)
        self.stages.append(("finish", threading.current_thread().name, t, time.monotonic()))
        if self.fail_on is not None and abs(z - self.fail_on) < 1e-3:
            raise RuntimeError("broken frame")
        return [Object3D("table", 0.7, [0.1, 0.2, z], [1.0, 0.6, 0.7], np.eye(3))]

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        return self.finish(self.prepare(rgb, depth, K, boxes2d, up))


def test_pipeline_overlaps_frames_and_keeps_their_order(harness):
    det = StagedDetector(delay=0.12)
    h = harness("sd_pipe", det, params={"qos_depth": 20})
    t0 = time.time_ns()
    stamps = [t0 + k * 100 * MS for k in range(8)]
    # frames arrive faster than prepare + finish (0.24 s) but slower than either
    st = h.play(stamps, gap=0.1)
    assert st["synced"] == 8 and st["processed"] + st["dropped"] == 8
    assert st["processed"] >= 5, st  # serially at most about 0.8 s / 0.24 s + 1 would be done
    h.wait_markers(st["processed"])
    got = [stamp_of(m) for m in h.markers]
    assert got == sorted(got) and got[-1] == stamps[-1]
    threads = {(stage, name) for stage, name, _, _ in det.stages}
    assert threads == {("prepare", "shape_detector_worker"), ("finish", "shape_detector_finisher")}
    prep = [(a, b) for stage, _, a, b in det.stages if stage == "prepare"]
    fin = [(a, b) for stage, _, a, b in det.stages if stage == "finish"]
    assert any(a1 < b2 and a2 < b1 for a1, b1 in prep for a2, b2 in fin), "no frame prepared while another finished"
    assert st["detect_p50_ms"] >= 200  # detector time of a frame counts both stages


class ThreeStageDetector(StagedDetector):
    """A StagedDetector with ShapeDetector's first_pass() and a lopsided last_timing."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.last_timing = {"proposals_ms": 10.0, "network_ms": 30.0, "refine_ms": 40.0}

    def first_pass(self, z, share=1.0):
        self.stages.append(("first_pass", threading.current_thread().name, time.monotonic(), time.monotonic()))
        return z


@pytest.mark.parametrize("split, early", [("auto", True), ("network", True), ("prepare", False)])
def test_pipeline_split_moves_the_first_pass_to_the_first_thread(harness, split, early):
    det = ThreeStageDetector()
    h = harness(f"sd_split_{split}", det, params={"pipeline_split": split})
    for k in range(2):
        h.frame(time.time_ns())
        h.wait_markers(k + 1)
    runs = [name for stage, name, _, _ in det.stages if stage == "first_pass"]
    assert runs == (["shape_detector_worker"] * 2 if early else [])
    assert h.node.get_stats().get("first_pass_early", 0) == (2 if early else 0)


def test_pipeline_off_runs_detect_in_one_thread(harness):
    det = StagedDetector()
    h = harness("sd_nopipe", det, params={"pipeline": False})
    assert h.node._finisher is None
    h.frame(time.time_ns())
    assert len(h.wait_markers(1)) == 1
    assert {name for _, name, _, _ in det.stages} == {"shape_detector_worker"}


def test_pipeline_detector_failure_in_second_stage_publishes_empty_and_goes_on(harness):
    det = StagedDetector(fail_on=2.5)
    h = harness("sd_pipefail", det)
    h.frame(time.time_ns())  # depth 2.5 m: finish() raises
    assert len(h.wait_markers(1)) == 1
    assert [m.action for m in h.markers[0].markers] == [3]  # DELETEALL only: no objects
    det.fail_on = None
    h.frame(time.time_ns())
    assert len(h.wait_markers(2)) == 2 and len(h.markers[1].markers) == 4
    st = h.wait_processed(2)
    assert st["detector_errors"] == 1 and st["processed"] == 2 and st.get("errors", 0) == 0


def test_classifier_and_second_pass_parameters_reach_the_detector(ros_context):
    built = []

    def factory(**kwargs):
        built.append(kwargs)
        return FakeDetector()

    for value, expect in (("", None), ("none", False), ("/some/classifier.pt", "/some/classifier.pt")):
        params = [Parameter("classifier", value=value), Parameter("refine", value=False),
                  Parameter("refine_min_score", value=0.4), Parameter("free_space", value=False)]
        node = DetectorNode("sd_factory", context=ros_context, detector_factory=factory, parameter_overrides=params)
        try:
            assert built[-1].get("classifier", None) == expect
            assert node.detector.refine is False and node.detector.refine_min_score == 0.4
            assert node.detector.free_space is False
        finally:
            node.destroy_node()


def test_detector_in_worker_processes_publishes_every_frame_in_order(ros_context, monkeypatch):
    from shape_detector.process_detector import ProcessDetector

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent))  # the workers import the factory by name
    params = {"detector_processes": 2, "detector_factory": "test_process_detector:EchoDetector"}
    h = Harness(ros_context, "sd_procs", None, params=params)
    try:
        assert isinstance(h.node.detector, ProcessDetector) and len(h.node.detector.worker_pids) == 2
        pids = list(h.node.detector.worker_pids)
        stamps = []
        for k in range(6):
            stamps.append(time.time_ns())
            h.frame(stamps[-1])
            assert len(h.wait_markers(k + 1)) == k + 1
        assert [stamp_of(m) for m in h.markers] == stamps
        assert all(len(m.markers) == 4 for m in h.markers)  # DELETEALL + the chair's box, wireframe, label
        h.node.set_parameters([Parameter("score_threshold", value=0.6)])
        h.frame(time.time_ns())
        assert len(h.wait_markers(7)) == 7 and h.node.get_stats().get("detector_errors", 0) == 0
        old = h.node.detector
        h.node.set_parameters([Parameter("backend", value="onnxruntime")])  # rebuilds the detector
        h.frame(time.time_ns())
        assert len(h.wait_markers(8)) == 8 and h.node.get_stats().get("detector_errors", 0) == 0
        assert h.node.detector is not old and isinstance(h.node.detector, ProcessDetector)
        replaced = [p for p in pids if p not in h.node.detector.worker_pids]
        assert replaced == pids  # the old workers were stopped when the new ones took over
        pids = pids + list(h.node.detector.worker_pids)
    finally:
        h.close()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in pids):
        time.sleep(0.05)
    assert not any(Path(f"/proc/{p}").exists() and "zombie" not in Path(f"/proc/{p}/status").read_text().lower()
                   for p in pids)
