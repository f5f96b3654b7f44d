"""``shape-detector replay`` against hostile use: output paths that hit the input,
unwritable outputs, signals mid-run, bad options, bags whose every frame is skipped."""

from __future__ import annotations

import argparse
import errno
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from child_env import child_env
from shape_detector.bags.source import MARKERS_TOPIC, read_messages
from shape_detector.bags.output import OutputError
from shape_detector.bags.output_safety import UnsafeOutputError, check_output_path
from shape_detector.replay import configure_parser, replay_bag
from shape_detector.synth.bag import write_rgbd_bag
from test_replay import FakeDetector, _cli, synthetic_frames

FAKE = ["--detector", "test_replay:FakeDetector", "--no-progress"]


class SignalDetector(FakeDetector):
    """FakeDetector that sends itself ``$SD_SIGNAL`` (INT / TERM) while detecting frame
    ``$SD_AT`` (1-based): a signal at a known point of the run."""

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        out = super().detect(rgb, depth, K, boxes2d, up)
        if len(self.calls) == int(os.environ.get("SD_AT", "3")):
            os.kill(os.getpid(), getattr(signal, "SIG" + os.environ.get("SD_SIGNAL", "TERM")))
        return out


@pytest.fixture()
def small_bag(tmp_path) -> Path:
    """6 frames of 160x120 with noise in the colour images (about 350 kB compressed)."""
    rng = np.random.default_rng(0)
    fr = [(t, rng.integers(0, 256, rgb.shape, dtype=np.uint8), d, k) for t, rgb, d, k in synthetic_frames(6, 160, 120)]
    return write_rgbd_bag(tmp_path / "in", fr)


def _snapshot(d: Path) -> dict[str, int]:
    return {str(p.relative_to(d)): p.stat().st_size for p in sorted(d.rglob("*")) if p.is_file()}


def _one_line_error(r) -> str:
    assert "Traceback" not in r.stderr, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("shape-detector replay:")]
    assert len(lines) == 1, r.stderr
    return lines[0]


# --- 2: the output must never be, contain or lie inside the input ------------------------


def test_output_overlapping_input_is_refused(small_bag, tmp_path):
    (tmp_path / "gt.json").write_text("{}")
    link = tmp_path / "link"
    link.symlink_to(small_bag)
    mcap = next(small_bag.glob("*.mcap"))
    for out in (small_bag, small_bag / "sub", tmp_path, link, link / "x", mcap, Path(os.path.relpath(small_bag))):
        with pytest.raises(UnsafeOutputError):
            check_output_path(small_bag, out)
    with pytest.raises(UnsafeOutputError):
        check_output_path(mcap, small_bag)  # a .mcap given directly: its bag directory is the input too
    check_output_path(small_bag, tmp_path / "out")  # a sibling is fine
    before = _snapshot(tmp_path)
    for out in (small_bag, link, tmp_path):
        r = _cli(str(small_bag), "-o", str(out), "--overwrite", *FAKE)
        assert r.returncode == 2, r.stderr
        assert "input" in _one_line_error(r)
    with pytest.raises(ValueError):
        replay_bag(small_bag, small_bag, FakeDetector(), progress=False, overwrite=True)
    assert _snapshot(tmp_path) == before  # nothing of the input (nor gt.json) deleted


def test_overwrite_replaces_only_bags_and_only_when_complete(small_bag, tmp_path):
    notabag = tmp_path / "notabag"
    notabag.mkdir()
    (notabag / "thesis.tex").write_text("precious")
    r = _cli(str(small_bag), "-o", str(notabag), "--overwrite", *FAKE)
    assert r.returncode == 1 and "not a bag" in _one_line_error(r)
    assert (notabag / "thesis.tex").read_text() == "precious"
    out = tmp_path / "out"
    replay_bag(small_bag, out, FakeDetector(), progress=False, copy_input=False)
    s = replay_bag(small_bag, out, FakeDetector(), progress=False, overwrite=True)
    assert s.ok and sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "out.mcap"]
    assert sum(1 for t, _, _ in read_messages(out) if t == "/camera/color/image_raw") == 6  # the new one
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "notabag", "out"]  # no .partial / .old left


# --- 3: unwritable outputs: one line naming path and cause, exit 1 ------------------------


def test_unwritable_output_is_one_line(small_bag, tmp_path):
    (tmp_path / "afile").write_text("x")
    r = _cli(str(small_bag), "-o", str(tmp_path / "afile" / "out"), *FAKE)
    assert r.returncode == 1
    line = _one_line_error(r)
    assert "afile" in line and "directory" in line.lower()



def test_read_only_filesystem_is_one_line(small_bag):
    target = Path("/sys/shape_detector_out")  # sysfs: read-only or refused, even for root
    try:
        target.mkdir()
    except OSError:
        pass
    else:
        target.rmdir()
        pytest.skip("/sys is writable here")
    r = _cli(str(small_bag), "-o", str(target), *FAKE)
    assert r.returncode == 1 and str(target) in _one_line_error(r)


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores permission bits")
def test_permission_denied_is_one_line(small_bag, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        r = _cli(str(small_bag), "-o", str(ro / "out"), *FAKE)
    finally:
        ro.chmod(0o700)
    assert r.returncode == 1 and "ro/out" in _one_line_error(r) and "ermission" in r.stderr


class _FullDisk:
    """A file that accepts ``limit`` bytes, then fails with ENOSPC."""

    def __init__(self, path: Path, limit: int) -> None:
        self.f = open(path, "xb")
        self.left = limit

    def write(self, data) -> int:
        if len(data) > self.left:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.left -= len(data)
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_disk_full_keeps_old_output_and_leaves_nothing_partial(small_bag, tmp_path, monkeypatch):
    out = tmp_path / "out"
    s = replay_bag(small_bag, out, FakeDetector(), progress=False)
    assert s.ok and s.frames_out == 6
    old = _snapshot(out)
    import shape_detector.bags.mcap_writer as mw

    monkeypatch.setattr(mw, "open_exclusive", lambda p: _FullDisk(p, 20_000))
    with pytest.raises(OutputError) as ei:
        replay_bag(small_bag, out, FakeDetector(), progress=False, overwrite=True)
    assert "No space left" in str(ei.value) and str(out) in str(ei.value) and "\n" not in str(ei.value)
    assert _snapshot(out) == old  # the old output is replaced only by a complete new one
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "out"]  # no partial left behind


def test_file_size_limit_cli_is_one_line(small_bag, tmp_path):
    """A write failing half-way (here EFBIG from RLIMIT_FSIZE, like ENOSPC) in the real CLI."""
    import resource
    import subprocess
    import sys

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, 30_000))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    env = child_env()
    cmd = [sys.executable, "-m", "shape_detector", "replay", str(small_bag), "-o", str(tmp_path / "out"), *FAKE]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, preexec_fn=limit)
    assert r.returncode == 1, r.stderr
    assert str(tmp_path / "out") in _one_line_error(r)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


# --- 4: signals finalise the output ----------------------------------------------------------


@pytest.mark.parametrize("sig,code", [("TERM", 143), ("INT", 130)])
def test_signal_finalises_output(small_bag, tmp_path, monkeypatch, sig, code):
    monkeypatch.setenv("SD_SIGNAL", sig)
    monkeypatch.setenv("SD_AT", "3")
    out = tmp_path / "out"
    r = _cli(str(small_bag), "-o", str(out), "--detector", "test_replay_safety:SignalDetector", "--no-progress")
    assert r.returncode == code, r.stderr
    line = _one_line_error(r)
    assert f"SIG{sig}" in line and "3 frame(s) written" in line
    markers = [t for t, _, _ in read_messages(out) if t == MARKERS_TOPIC]
    assert len(markers) == 3  # metadata.yaml and footer written: rosbags reads it
    from mcap.reader import make_reader

    with open(next(out.glob("*.mcap")), "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary() is not None and sum(1 for _ in reader.iter_messages()) > 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "out"]


def test_should_stop_in_library(small_bag, tmp_path):
    det = FakeDetector()
    s = replay_bag(small_bag, tmp_path / "out", det, progress=False,
                   should_stop=lambda: "SIGTERM" if len(det.calls) >= 2 else None)
    assert s.interrupted == "SIGTERM" and s.frames_out == 2 and "interrupted by SIGTERM" in s.format()
    assert sum(1 for t, _, _ in read_messages(tmp_path / "out") if t == MARKERS_TOPIC) == 2


# --- 5: every option validated at parse time ---------------------------------------------------


@pytest.mark.parametrize("args,option", [
    (["--depth-scale", "-1"], "--depth-scale"), (["--depth-scale", "0"], "--depth-scale"),
    (["--depth-scale", "nan"], "--depth-scale"), (["--depth-scale", "inf"], "--depth-scale"),
    (["--max-objects", "-5"], "--max-objects"), (["--max-objects", "0"], "--max-objects"),
    (["--score-threshold", "2"], "--score-threshold"), (["--score-threshold", "-0.1"], "--score-threshold"),
    (["--workers", "-1"], "--workers"), (["--queue-size", "0"], "--queue-size"),
    (["--slop", "-1"], "--slop"), (["--slop", "nan"], "--slop"), (["--up", "0,0,0"], "--up"),
    (["--up", "1,2"], "--up"), (["--rate", "nan"], "--rate"), (["--wait-subscribers", "-1"], "--wait-subscribers"),
    (["--delay", "-2"], "--delay"), (["--remap", "nocolon"], "--remap"), (["--device", "gpu0"], "--device"),
    (["--image", ""], "--image"),
])
def test_bad_options_rejected_naming_the_option(args, option, capsys):
    p = argparse.ArgumentParser(prog="shape-detector replay")
    configure_parser(p)
    with pytest.raises(SystemExit) as ei:
        p.parse_args(["bag", "-o", "out", *args])
    assert ei.value.code == 2
    err = capsys.readouterr().err
    assert option in err and args[-1] in err


def test_good_options_parse_and_library_checks(small_bag, tmp_path):
    p = argparse.ArgumentParser()
    configure_parser(p)
    a = p.parse_args(["bag", "-o", "o", "--depth-scale", "0.001", "--up", "0,-2,0", "--remap", "/a:=/b",
                      "--score-threshold", "1", "--max-objects", "1", "--rate", "0"])
    assert a.depth_scale == 0.001 and np.allclose(a.up, [0, -1, 0]) and a.remap == [("/a", "/b")]
    for kw in ({"depth_scale": -1.0}, {"depth_scale": float("nan")}, {"queue_size": 0}, {"slop": -0.1}):
        with pytest.raises(ValueError):
            replay_bag(small_bag, tmp_path / "o", FakeDetector(), progress=False, **kw)
    assert not (tmp_path / "o").exists()
    assert "exit status" in p.format_help() and "3" in p.epilog


# --- 6: every frame skipped -> exit 3 with the reasons ---------------------------------------------


def test_all_frames_skipped_exit_3(tmp_path):
    fr = [(t, rgb, d, np.zeros((3, 3))) for t, rgb, d, _ in synthetic_frames(4, 160, 120)]
    zero_k = write_rgbd_bag(tmp_path / "zero_k", fr)
    r = _cli(str(zero_k), "-o", str(tmp_path / "o1"), *FAKE)
    assert r.returncode == 3, r.stderr
    assert "skipped: 4 (camera_info: 4)" in r.stdout
    assert "every frame was skipped" in _one_line_error(r)
    # a colour encoding that is not supported: auto-selection names it; given by flag, exit 3
    from msg_conversion import K_to_camera_info, depth_to_image, rosbags_types
    from rosbags.rosbag2 import StoragePlugin, Writer

    T = rosbags_types()
    st = T.typestore
    p = tmp_path / "yuv"
    with Writer(p, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/c/color/image_raw", "sensor_msgs/msg/Image", typestore=st)
        cd = w.add_connection("/c/depth/image_raw", "sensor_msgs/msg/Image", typestore=st)
        ck = w.add_connection("/c/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=st)
        for t, _rgb, depth, KK in synthetic_frames(3, 160, 120):
            from msg_conversion import make_header

            img = T.make_by_name("sensor_msgs/msg/Image", header=make_header(T, t, "cam"), height=120, width=160,
                                 encoding="yuv422", is_bigendian=0, step=320,
                                 data=np.zeros(120 * 320, np.uint8))
            w.write(ci, t, st.serialize_cdr(img, "sensor_msgs/msg/Image"))
            w.write(cd, t, st.serialize_cdr(depth_to_image(depth, T, "16UC1", t, "cam"), "sensor_msgs/msg/Image"))
            w.write(ck, t, st.serialize_cdr(K_to_camera_info(KK, 160, 120, T, t, "cam"), "sensor_msgs/msg/CameraInfo"))
    r = _cli(str(p), "-o", str(tmp_path / "o2"), *FAKE)
    assert r.returncode == 1 and "yuv422" in _one_line_error(r)
    r = _cli(str(p), "-o", str(tmp_path / "o3"), "--image", "/c/color/image_raw", *FAKE)
    assert r.returncode == 3 and "encoding: 3" in r.stdout and "yuv422" in r.stdout
