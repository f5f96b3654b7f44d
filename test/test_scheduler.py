"""The node's frame scheduling without ROS (rosbags message classes, a fake host): output in
input order under overload, drops counted, shutdown bounded even with a stuck detector."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image, rosbags_types
from shape_detector.node_params import PARAMETERS
from shape_detector.node_stats import NodeStats
from shape_detector.scheduler import FrameScheduler, FrameSet

pytestmark = pytest.mark.timeout(60)
T = rosbags_types()
K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])


class SlowDetector:
    """prepare / finish with a delay; ``gate``: finish waits for it (a stuck network)."""

    def __init__(self, delay: float = 0.02) -> None:
        self.delay = delay
        self.gate: threading.Event | None = None

    def prepare(self, rgb, depth, K, boxes2d=None, up=None):
        time.sleep(self.delay)
        return float(np.nanmedian(depth))

    def finish(self, prepared):
        if self.gate is not None:
            self.gate.wait()
        time.sleep(self.delay)
        return []

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        return self.finish(self.prepare(rgb, depth, K))


class Host:
    def __init__(self, detector) -> None:
        self.p = {k: v.default for k, v in PARAMETERS.items()}
        self.p["pipeline_split"] = "prepare"
        self.detector = detector
        self.stats = NodeStats()
        self.info_event = threading.Event()
        self.info_event.set()
        self.info = K_to_camera_info(K, 80, 60, T, 0, "cam")
        self.published: list[int] = []
        self.warnings: list[str] = []

    def warn(self, kind, text, period=5.0, level="warning", key=None):
        self.warnings.append(text)

    def publish(self, objects, stamp, frame_id, frame=None, up=None):
        self.published.append(stamp)

    def frame_up(self, fs, stamp_ns, frame_id):
        return fs.up

    def now_ns(self):
        return time.time_ns()

    def camera_info(self):
        return self.info

    def build_detector(self):
        raise RuntimeError("no weights here")

    def topic(self, name):
        return "/" + name

    def maybe_report(self, force=False):
        pass


def _set(stamp: int, host: Host) -> FrameSet:
    rgb = numpy_to_image(np.full((60, 80, 3), 90, np.uint8), "rgb8", T, stamp, "cam")
    depth = depth_to_image(np.full((60, 80), 2.0), T, "16UC1", stamp, "cam")
    return FrameSet(rgb, depth, host.info, None, None, time.monotonic())


@pytest.mark.parametrize("pipeline", [True, False])
def test_overload_keeps_order_and_counts_every_frame(pipeline):
    host = Host(SlowDetector())
    sched = FrameScheduler(host, pipeline)
    try:
        n = 60
        for k in range(n):
            sched.offer(_set(1_000_000_000 + k, host))
            time.sleep(0.004)  # offered far faster than processed
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and host.stats.counters["processed"] + sched.mailbox.dropped < n:
            time.sleep(0.01)
    finally:
        assert sched.stop()
    assert host.stats.counters["synced"] == n
    assert host.stats.counters["processed"] + sched.mailbox.dropped == n
    assert sched.mailbox.dropped > 0 and host.published
    assert all(b > a for a, b in zip(host.published, host.published[1:]))
    assert host.published[-1] == 1_000_000_000 + n - 1  # the newest frame is never lost


def test_stop_is_bounded_with_a_stuck_detector():
    det = SlowDetector(0.0)
    det.gate = threading.Event()
    host = Host(det)
    sched = FrameScheduler(host, True)
    try:
        sched.offer(_set(5, host))
        deadline = time.monotonic() + 5
        while sched.handoff.taken < 1 and time.monotonic() < deadline:  # the finisher holds the frame
            time.sleep(0.01)
        t0 = time.monotonic()
        assert not sched.stop(timeout=0.5)  # the finisher is stuck in the network
        assert time.monotonic() - t0 < 2.0
        assert sched.finisher is not None and sched.finisher.daemon
    finally:
        det.gate.set()
    sched.finisher.join(timeout=5)
    assert not sched.finisher.is_alive() and not sched.worker.is_alive()
    assert host.published == []  # nothing published after stop


def test_failed_rebuild_keeps_the_detector_and_says_why():
    det = SlowDetector(0.0)
    host = Host(det)
    sched = FrameScheduler(host, False)
    try:
        sched.rebuild = True
        sched.offer(_set(7, host))
        deadline = time.monotonic() + 10
        while not host.published and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        sched.stop()
    assert host.detector is det and host.published == [7]
    assert any("cannot rebuild" in w for w in host.warnings)


@pytest.mark.parametrize("pipeline", [True, False])
def test_the_detector_gets_the_hosts_gravity_for_the_frame_and_publish_the_same(pipeline):
    class Recording(SlowDetector):
        def __init__(self):
            super().__init__(0.0)
            self.ups = []

        def prepare(self, rgb, depth, K, boxes2d=None, up=None):
            self.ups.append(up)
            return super().prepare(rgb, depth, K)

        def detect(self, rgb, depth, K, boxes2d=None, up=None):
            return self.finish(self.prepare(rgb, depth, K, up=up))

    class PosedHost(Host):
        def __init__(self, detector):
            super().__init__(detector)
            self.asked, self.published_up = [], []

        def frame_up(self, fs, stamp_ns, frame_id):
            self.asked.append((stamp_ns, frame_id))
            return np.array([0.0, -0.6, 0.8])

        def publish(self, objects, stamp, frame_id, frame=None, up=None):
            super().publish(objects, stamp, frame_id, frame, up)
            self.published_up.append(up)

    det = Recording()
    host = PosedHost(det)
    sched = FrameScheduler(host, pipeline)
    try:
        sched.offer(_set(1_000_000_007, host))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not host.published:
            time.sleep(0.01)
    finally:
        assert sched.stop()
    assert host.asked == [(1_000_000_007, "cam")]
    np.testing.assert_allclose(det.ups[0], [0.0, -0.6, 0.8])
    np.testing.assert_allclose(host.published_up[0], [0.0, -0.6, 0.8])
