"""The learned 2D proposer: input preparation, decoding, targets, training and export."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from shape_detector.box_iou import box2d_iou_matrix
from shape_detector.proposals.learned import (DEFAULT_MODEL, INPUT_SIZE, STRIDE, LearnedProposer, decode,
                                              model_file, prepare_input)
from shape_detector.proposals.learned_int8 import int8_path, int8_source_matches
from shape_detector.training.train_proposer import targets

OUT = (INPUT_SIZE[0] // STRIDE, INPUT_SIZE[1] // STRIDE)


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def test_prepare_input_scales_colour_and_depth_and_marks_invalid_depth():
    rgb = np.full((480, 640, 3), 255, np.uint8)
    depth = np.full((480, 640), 4.0, np.float32)
    depth[:, :320] = np.nan
    x = prepare_input(rgb, depth)
    assert x.shape == (5, INPUT_SIZE[1], INPUT_SIZE[0]) and x.dtype == np.float32
    np.testing.assert_allclose(x[:3], 0.5)
    assert np.all(x[4, :, :80] == 0) and np.all(x[4, :, 80:] == 1)
    assert np.all(x[3, :, :80] == 0) and np.allclose(x[3, :, 80:], 0.0)  # 4 m is the normalisation's zero


def test_targets_decode_back_to_their_boxes():
    boxes = [(100.0, 120.0, 260.0, 400.0), (400.0, 200.0, 520.0, 330.0), (30.0, 20.0, 90.0, 70.0)]
    hm, reg, mask = targets(boxes, 640, 480, OUT)
    assert hm.shape == (1, OUT[1], OUT[0]) and mask.sum() == 3 and hm.max() == 1.0
    got = decode(_logit(hm[0]), reg, 640, 480, k=10, min_score=0.9)
    assert len(got) == 3
    for want in boxes:
        best = min(got, key=lambda b: np.abs(np.subtract(b[:4], want)).sum())
        np.testing.assert_allclose(best[:4], want, atol=1e-3)


def test_decode_keeps_local_maxima_best_first_within_k_and_the_image():
    hm = np.full((OUT[1], OUT[0]), -10.0)
    reg = np.zeros((4, OUT[1], OUT[0]))
    reg[2:] = np.log(4.0)  # 4 x 4 cells = 64 x 64 px of a 640 x 480 image
    hm[10, 10], hm[10, 11] = 2.0, 1.0  # a neighbour of a stronger peak is no centre
    hm[20, 30] = 3.0
    hm[0, 0] = 0.5  # at the corner: clipped to the image
    hm[25, 5] = -4.0  # below min_score
    got = decode(hm, reg, 640, 480, k=10, min_score=0.05)
    assert [round(b[4], 3) for b in got] == [round(1 / (1 + np.exp(-v)), 3) for v in (3.0, 2.0, 0.5)]
    x1, y1, x2, y2, _ = got[0]
    assert (x1, y1, x2, y2) == pytest.approx((30 * 16 - 32, 20 * 16 - 32, 30 * 16 + 32, 20 * 16 + 32))
    assert got[2][:2] == (0.0, 0.0)
    assert len(decode(hm, reg, 640, 480, k=1)) == 1


def test_missing_model_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="train-proposer"):
        LearnedProposer(tmp_path / "none.onnx")


def test_the_packaged_model_proposes_on_a_generated_frame():
    from shape_detector.synth.generate import SynthConfig, generate_frame

    assert DEFAULT_MODEL.is_file() and Path(str(DEFAULT_MODEL) + ".json").is_file()
    f = generate_frame(10_003, SynthConfig(width=320, height=240))
    grav, props = LearnedProposer(max_proposals=5)(f.depth, f.K, rgb=f.rgb)
    assert 1 <= len(props) <= 5 and all(p.class_name is None and 0.75 <= p.score <= 1.0 for p in props)
    assert all(0 <= p.box2d[0] < p.box2d[2] <= 320 and 0 <= p.box2d[1] < p.box2d[3] <= 240 for p in props)
    assert np.isclose(np.linalg.norm(grav.up), 1.0)
    with pytest.raises(ValueError, match="RGB"):
        LearnedProposer()(f.depth, f.K)


def test_detector_runs_on_learned_proposals():
    from shape_detector import ShapeDetector
    from shape_detector.synth.generate import SynthConfig, generate_frame

    f = generate_frame(10_004, SynthConfig(width=320, height=240))
    det = ShapeDetector(proposal_source="learned", score_threshold=0.0)
    objs = det.detect(f.rgb, f.depth, f.K)
    assert objs and all(np.all(np.isfinite(o.center)) for o in objs)
    assert det.last_timing["num_frustums"] >= 1


@pytest.mark.slow
def test_train_proposer_writes_an_onnx_graph_that_matches_torch(tmp_path, monkeypatch):
    import torch

    from shape_detector.synth.dataset import write_shards
    from shape_detector.synth.generate import SynthConfig
    from shape_detector.training import train_proposer

    data = tmp_path / "data"
    write_shards(data, 6, seed=0, frames_per_shard=6, workers=1, config=SynthConfig(width=160, height=120),
                 quiet=True)
    out = tmp_path / "p.onnx"
    p = argparse.ArgumentParser()
    train_proposer.configure_parser(p)
    args = p.parse_args(["--data", str(data), "--out", str(out), "--epochs", "1", "--batch-size", "4",
                         "--threads", "1"])
    assert train_proposer.main(args) == 0
    prov = json.loads(Path(str(out) + ".json").read_text())
    assert prov["phase"] == "proposer2d" and prov["data"][0]["frames"] == 6 and len(prov["losses"]) == 1
    # the graph computes what the network does (rebuilt from the same seed and data)
    x, frames = train_proposer.load_frames([data], None, 0.1)
    net, _ = train_proposer.train(x, frames, 1, 4, 2e-3, 0, log=lambda s: None)
    with torch.no_grad():
        want = [t.numpy() for t in net(torch.from_numpy(x[:2]))]
    import onnxruntime as ort

    got = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).run(None, {"input": x[:2]})
    for w, g in zip(want, got):
        np.testing.assert_allclose(g, w, atol=1e-3)
    bad = p.parse_args(["--data", str(tmp_path / "missing"), "--out", str(out)])
    assert train_proposer.main(bad) == 2
    # and its int8 version, from the same calibration frames, rebuilt alone to the same bytes
    q = int8_path(out)
    meta = json.loads(Path(str(q) + ".json").read_text())
    assert meta["source_sha256"] == prov["sha256"] and meta["calibration_frames"] == 6
    assert model_file(out, "int8") == q and model_file(out) == model_file(out, "fp32") == out
    before = q.read_bytes()
    q.unlink()
    assert train_proposer.main(p.parse_args(["--data", str(data), "--out", str(out), "--int8-only"])) == 0
    assert q.read_bytes() == before
    none = p.parse_args(["--data", str(data), "--out", str(tmp_path / "none.onnx"), "--int8-only"])
    assert train_proposer.main(none) == 2


def test_the_packaged_int8_network_is_built_from_the_packaged_network_and_agrees_with_it():
    from shape_detector.synth.generate import SynthConfig, generate_frame

    assert model_file(DEFAULT_MODEL, "int8") == int8_path(DEFAULT_MODEL)
    assert int8_source_matches(int8_path(DEFAULT_MODEL), DEFAULT_MODEL)
    fp32, int8 = LearnedProposer(), LearnedProposer(precision="int8")
    assert fp32.path == DEFAULT_MODEL and int8.path == int8_path(DEFAULT_MODEL)
    twins, total = 0, 0
    for seed in (10_005, 10_006, 10_007):
        f = generate_frame(seed, SynthConfig(width=640, height=480))
        a = [p.box2d for p in fp32.detect(f.rgb, f.depth)[:5]]
        b = [p.box2d for p in int8.detect(f.rgb, f.depth)[:10]]
        assert a and b
        twins += int(np.sum(box2d_iou_matrix(a, b).max(axis=1) >= 0.8))
        total += len(a)
    assert twins >= 0.8 * total  # int8 finds (nearly) the same top boxes, not bit-equal ones


def test_without_onnxruntime_the_float32_network_runs(monkeypatch):
    import shape_detector.model.onnx_backend as backend

    monkeypatch.setattr(backend, "ort_available", lambda: False)
    assert model_file(DEFAULT_MODEL, "int8") == DEFAULT_MODEL  # OpenCV DNN runs the float32 graph


def test_a_stale_int8_network_is_not_run(tmp_path):
    import shutil

    src = tmp_path / "p.onnx"
    shutil.copyfile(DEFAULT_MODEL, src)
    shutil.copyfile(int8_path(DEFAULT_MODEL), int8_path(src))
    meta = json.loads(Path(str(int8_path(DEFAULT_MODEL)) + ".json").read_text())
    Path(str(int8_path(src)) + ".json").write_text(json.dumps({**meta, "source_sha256": "0" * 64}))
    with pytest.warns(UserWarning, match="int8-only"):
        assert model_file(src, "int8") == src
    Path(str(int8_path(src)) + ".json").write_text(json.dumps(meta))
    assert model_file(src, "int8") == int8_path(src)  # a copy of the same network: its int8 version runs
