"""Training shards round-trip exactly and can regenerate any frame from its seed."""

from __future__ import annotations

import json

import numpy as np

from shape_detector.synth.dataset import count_frames, frame_seed, iter_frames, read_frame, write_shards
from shape_detector.synth.generate import SynthConfig, generate_frame

CFG = SynthConfig(width=160, height=120)


def test_shards_round_trip(tmp_path, capsys):
    write_shards(tmp_path, 5, seed=9, frames_per_shard=2, workers=2, config=CFG)
    out = capsys.readouterr().out
    assert out.count("shard ") == 3 and "frames/s" in out
    index = json.loads((tmp_path / "index.json").read_text())
    assert index["num_frames"] == 5 and len(index["shards"]) == 3
    frames = list(iter_frames(tmp_path))
    assert len(frames) == 5 == count_frames(tmp_path)
    for k in (0, 4):
        ref = generate_frame(frame_seed(9, k), CFG)
        got = frames[k]
        assert np.array_equal(got.rgb, ref.rgb)
        ok = np.isfinite(ref.depth)
        assert np.array_equal(np.isfinite(got.depth), ok)
        assert np.max(np.abs(got.depth[ok] - ref.depth[ok])) <= 0.0005 + 1e-6
        assert np.array_equal(got.instance_mask, ref.instance_mask)
        assert np.allclose(got.K, ref.K) and np.allclose(got.up, ref.up)
        assert got.stamp_ns == ref.stamp_ns and got.frame_id == ref.frame_id
        assert [o.to_dict() for o in got.objects] == [o.to_dict() for o in ref.objects]
        assert got.clutter_boxes == [tuple(b) for b in ref.clutter_boxes]
    assert read_frame(tmp_path, 3).stamp_ns == frames[3].stamp_ns


def test_clean_depth_within_1mm(tmp_path):
    cfg = SynthConfig(width=160, height=120, noise=False)
    write_shards(tmp_path, 1, seed=2, workers=1, config=cfg, quiet=True)
    got = next(iter_frames(tmp_path))
    ref = generate_frame(frame_seed(2, 0), cfg)
    ok = np.isfinite(ref.depth) & (ref.depth < 65.0)
    assert np.nanmax(np.abs(got.depth[ok] - ref.depth[ok])) <= 0.0005 + 1e-6


def test_workers_start_in_a_process_that_ran_opencv_threads(tmp_path):
    """The training runner generates a missing data set after cutting frustums with OpenCV's
    thread pool running; forked workers hung there (in cv2.setNumThreads), spawned ones do not."""
    import subprocess
    import sys

    code = (
        "import numpy as np, cv2, sys\n"
        "from shape_detector.synth.dataset import write_shards\n"
        "from shape_detector.synth.generate import SynthConfig\n"
        "img = np.random.rand(1500, 1500).astype(np.float32)\n"
        "for _ in range(3):\n"
        "    cv2.GaussianBlur(img, (31, 31), 5)\n"
        "write_shards(sys.argv[1], 4, seed=3, frames_per_shard=2, workers=2, config=SynthConfig(width=64, height=48),"
        " quiet=True)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    assert count_frames(tmp_path) == 4
