"""Detection in worker processes: same objects as in-process, order kept through the node's
scheduler, settings reach the workers, a dead worker is replaced, nothing is left behind."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from child_env import child_env
from shape_detector.detector_config import preset
from shape_detector.process_detector import ProcessDetector
from shape_detector.types import Object3D

pytestmark = pytest.mark.timeout(120)
TEST_DIR = Path(__file__).resolve().parent
FAKE = "test_process_detector:EchoDetector"
K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])


class EchoDetector:
    """Built in the workers by name: one chair per frame at the depth's median, scored by the
    ``score_threshold`` setting (to see settings arrive), tagged with the worker's pid."""

    def __init__(self, **kwargs):
        self.score_threshold = float(kwargs.get("score_threshold", 0.3))
        self.last_up = None

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        z = float(np.nanmedian(depth))
        self.last_up = np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up)
        o = Object3D("chair", self.score_threshold, [0.0, 0.0, z], [0.5, 0.5, 0.9], np.eye(3))
        o.class_scores = np.array([float(os.getpid())])  # which worker ran it
        if float(rgb[0, 0, 0]) == 255:
            raise ValueError("a frame the detector refuses")
        return [o]


def _frame(z: float) -> tuple[np.ndarray, np.ndarray]:
    return np.full((60, 80, 3), 90, np.uint8), np.full((60, 80), z, np.float32)


@pytest.fixture()
def pool(monkeypatch):
    # the spawned workers import this module by name
    monkeypatch.setenv("PYTHONPATH", child_env()["PYTHONPATH"])
    if str(TEST_DIR) not in sys.path:
        monkeypatch.syspath_prepend(str(TEST_DIR))
    det = ProcessDetector(preset("realtime"), 2, FAKE)
    det.warm_up()
    yield det
    det.close()


def _segments() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob("psm_*")} if Path("/dev/shm").is_dir() else set()


def test_frames_in_flight_come_back_in_order_from_both_workers(pool):
    before = _segments()
    jobs = [pool.prepare(*_frame(1.0 + 0.1 * k), K) for k in range(12)]
    z = [pool.finish(j)[0].center[2] for j in jobs]
    assert z == pytest.approx([1.0 + 0.1 * k for k in range(12)], abs=1e-5)
    assert len(pool.worker_pids) == 2
    assert pool.last_up == pytest.approx([0.0, -1.0, 0.0])
    assert pool.predictor.workers == 1
    assert _segments() <= before  # every frame's shared memory is gone


def test_settings_reach_every_worker(pool):
    pool.configure(score_threshold=0.55)
    scores = {round(pool.detect(*_frame(2.0), K)[0].score, 3) for _ in range(6)}
    assert scores == {0.55}
    with pytest.raises(TypeError):
        pool.configure(no_such_setting=1)


def test_a_failing_frame_raises_and_the_next_one_works(pool):
    rgb, depth = _frame(1.5)
    rgb[0, 0] = 255
    with pytest.raises(ValueError, match="refuses"):
        pool.detect(rgb, depth, K)
    assert pool.detect(*_frame(1.5), K)[0].center[2] == pytest.approx(1.5)


def test_a_dead_worker_fails_its_frame_and_is_replaced(pool):
    job = pool.prepare(*_frame(1.0), K)
    pool.finish(job)
    os.kill(pool.worker_pids[0], signal.SIGKILL)
    time.sleep(0.3)
    with pytest.raises(RuntimeError, match="died"):
        for _ in range(4):  # a frame on the dead worker, or the broken pool, tells
            pool.detect(*_frame(1.0), K)
    assert pool.detect(*_frame(1.2), K)[0].center[2] == pytest.approx(1.2)


def test_close_stops_the_workers(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", child_env()["PYTHONPATH"])
    det = ProcessDetector(preset("realtime"), 1, FAKE)
    det.warm_up()
    pids = list(det.worker_pids)
    det.close()
    det.close()  # idempotent
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in pids):
        time.sleep(0.05)
    assert not any(Path(f"/proc/{p}").exists() and "zombie" not in Path(f"/proc/{p}/status").read_text().lower()
                   for p in pids)


def test_the_shipped_detector_gives_the_same_objects_in_a_worker(tmp_path):
    from shape_detector.detector import ShapeDetector
    from shape_detector.synth.generate import SynthConfig, generate_frame

    f = generate_frame(7, SynthConfig(width=320, height=240))
    local = ShapeDetector(preset("realtime", workers=1)).detect(f.rgb, f.depth, f.K)
    with ProcessDetector(preset("realtime"), 1) as det:
        det.warm_up()
        remote = det.detect(f.rgb, f.depth, f.K)
        assert det.last_timing.get("num_frustums", 0) >= 0 and det.last_detect_ms is not None
    assert [o.class_name for o in remote] == [o.class_name for o in local]
    for a, b in zip(remote, local):
        assert a.center == pytest.approx(b.center, abs=1e-3)
        assert a.size == pytest.approx(b.size, abs=1e-3)


def test_workers_ignore_ctrl_c_and_exit_with_a_killed_parent(tmp_path):
    import subprocess

    script = tmp_path / "parent.py"
    script.write_text(
        "import sys, time\n"
        f"sys.path.insert(0, {str(TEST_DIR)!r})\n"
        "from shape_detector.detector_config import preset\n"
        "from shape_detector.process_detector import ProcessDetector\n"
        "if __name__ == '__main__':\n"
        f"    det = ProcessDetector(preset('realtime'), 2, {FAKE!r})\n"
        "    det.warm_up()\n"
        "    print(*det.worker_pids, flush=True)\n"
        "    time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, env=child_env())
    try:
        pids = [int(p) for p in proc.stdout.readline().split()]
        assert len(pids) == 2
        for p in pids:
            os.kill(p, signal.SIGINT)  # as a terminal's Ctrl-C reaches the whole group
        time.sleep(0.5)
        assert all(Path(f"/proc/{p}").exists() for p in pids)
        proc.kill()  # the parent dies without cleaning up
        proc.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in pids):
            time.sleep(0.1)
        assert not any(Path(f"/proc/{p}").exists() for p in pids)
        assert "Traceback" not in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_workers_that_cannot_start_say_so_at_warm_up():
    det = ProcessDetector(preset("realtime"), 1, "no_such_module_here:Factory")
    try:
        with pytest.raises(RuntimeError, match="could not start"):
            det.warm_up()
    finally:
        det.close()
    with pytest.raises(RuntimeError, match="could not start"):
        ProcessDetector.started(preset("realtime"), 1, "no_such_module_here:Factory")
