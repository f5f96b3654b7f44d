"""Acceptance: ``detector_node`` started as a subprocess through its console script
(LOCALHOST discovery, this run's domain id, shared-memory Fast DDS), the sample bag played
into it, one MarkerArray per synchronised frame with the right stamps and frame_id."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from shape_detector.bag_io import BagFrameReader, write_rgbd_bag  # noqa: E402
from shape_detector.node_bench import MarkerListener, OutputCollector, node_command, start_node, stop_node  # noqa: E402
from shape_detector.replay import play_bag  # noqa: E402
from shape_detector.types import Object3D  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TEST_DIR = Path(__file__).resolve().parent
WEIGHTS = ROOT / "shape_detector" / "weights" / "default.pt"
MS = 1_000_000


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
        listener.close()
        rc = stop_node(proc)
    log = out.text
    assert rc == 0, log
    assert len(received) == len(expected), log
    assert [(r[1], r[2]) for r in received] == expected
    if not WEIGHTS.exists():
        assert all(r[3] == 4 for r in received)  # DELETEALL + box, wireframe, label of the sofa
    assert "frames/s" in log and "synced" in log
    assert "Traceback" not in log


def test_node_exits_cleanly_on_bad_configuration():
    proc = start_node({}, {"up_source": "sideways", "detector_factory": "test_node_subprocess:FakeDetector"},
                      extra_pythonpath=[str(TEST_DIR)])
    out = OutputCollector(proc)
    try:
        proc.wait(timeout=60)
    finally:
        stop_node(proc)
    time.sleep(0.2)
    assert proc.returncode == 1
    assert "up_source must be one of" in out.text
