"""Offline replay with the detector in worker processes: the output MCAP holds the same
messages in the same order as a replay in this process; a stop or a failing frame loses
nothing that was handed over."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from child_env import child_env
from shape_detector.bags.source import MARKERS_TOPIC, read_messages
from shape_detector.detector_config import preset
from shape_detector.process_detector import ProcessDetector
from shape_detector.replay import replay_bag
from shape_detector.synth.bag import write_rgbd_bag
from test_process_detector import EchoDetector
from test_replay import synthetic_frames

pytestmark = pytest.mark.timeout(180)
ROOT = Path(__file__).resolve().parents[1]
TEST_DIR = Path(__file__).resolve().parent
FACTORY = "test_process_detector:EchoDetector"
MS = 1_000_000


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    frames = synthetic_frames(n=14)
    frames[5][1][0, 0] = 255  # EchoDetector refuses this frame
    return write_rgbd_bag(tmp_path_factory.mktemp("bags") / "b", frames, depth_offset_ns=3 * MS)


@pytest.fixture(scope="module")
def workers():
    det = ProcessDetector(preset("realtime"), 2, FACTORY)
    det.warm_up()
    yield det
    det.close()


def _file_order(out: Path) -> list[tuple[str, int]]:
    from mcap.reader import make_reader

    with open(next(out.glob("*.mcap")), "rb") as f:
        return [(ch.topic, m.log_time) for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]


def test_same_messages_in_the_same_order_as_in_process(bag, workers, tmp_path):
    serial = replay_bag(bag, tmp_path / "serial", EchoDetector(), progress=False)
    piped = replay_bag(bag, tmp_path / "piped", workers, progress=False)
    for s in (serial, piped):
        assert s.synced == 14 and s.frames_out == 14 and s.detected == 13
        assert s.skipped["detector error"] == 1
    assert _file_order(tmp_path / "piped") == _file_order(tmp_path / "serial")
    z = [[m.pose.position.z for m in msg.markers if m.action == 0][:1]
         for _, _, msg in read_messages(tmp_path / "piped", [MARKERS_TOPIC])]
    z_serial = [[m.pose.position.z for m in msg.markers if m.action == 0][:1]
                for _, _, msg in read_messages(tmp_path / "serial", [MARKERS_TOPIC])]
    assert z == z_serial and sum(1 for v in z if v) == 13


def test_a_stop_finishes_and_writes_the_frames_in_flight(bag, workers, tmp_path):
    calls = {"n": 0}

    def stop_after_some_messages():
        calls["n"] += 1
        return "test stop" if calls["n"] > 30 else None

    s = replay_bag(bag, tmp_path / "stopped", workers, progress=False, should_stop=stop_after_some_messages)
    assert s.interrupted == "test stop"
    assert 0 < s.frames_out == s.synced < 14
    n_markers = sum(1 for _ in read_messages(tmp_path / "stopped", [MARKERS_TOPIC]))
    assert n_markers == s.frames_out


def test_replay_cli_with_processes(bag, tmp_path):
    exe = Path(sys.executable).parent / "shape-detector"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "shape_detector"]
    env = child_env()
    r = subprocess.run(cmd + ["replay", str(bag), "-o", str(tmp_path / "cli"), "--no-progress", "--processes", "2",
                              "--detector", FACTORY], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode in (0, 3), r.stderr + r.stdout  # 3: a frame was skipped (the refused one)
    assert "14 synchronised / 14 out" in r.stdout
    assert "Traceback" not in r.stderr
    assert np.isfinite(float(r.stdout.split("detector:")[1].split("ms/frame")[0]))
