"""The GPU path: the backend a GPU device gets, and, where torch sees a CUDA device, detection
and training on it (those tests skip on CPU-only machines; `docs/experiments/gpu-check.md`
says where they last ran)."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.model import onnx_backend

torch = pytest.importorskip("torch")
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def test_auto_backend_follows_a_gpu_device_to_torch_when_onnxruntime_has_no_gpu_provider(monkeypatch):
    pytest.importorskip("onnxruntime")
    monkeypatch.delenv("SHAPE_DETECTOR_BACKEND", raising=False)
    monkeypatch.setattr(onnx_backend, "_torch_sees_gpu", lambda device: True)
    monkeypatch.setattr(onnx_backend, "gpu_providers", lambda: [])
    assert onnx_backend.resolve_backend("auto", "fp32", True, "cuda") == "torch"
    assert onnx_backend.resolve_backend("auto", "fp32", True, "cpu") == "onnxruntime"
    assert onnx_backend.resolve_backend("onnxruntime", "fp32", True, "cuda") == "onnxruntime"  # asked for
    monkeypatch.setattr(onnx_backend, "gpu_providers", lambda: ["CUDAExecutionProvider"])
    assert onnx_backend.resolve_backend("auto", "fp32", True, "cuda") == "onnxruntime"
    assert onnx_backend.providers_for("cuda") == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert onnx_backend.providers_for("cpu") == ["CPUExecutionProvider"]
    # a GPU device that torch does not see: onnxruntime on the CPU, as before
    monkeypatch.setattr(onnx_backend, "gpu_providers", lambda: [])
    monkeypatch.setattr(onnx_backend, "_torch_sees_gpu", lambda device: False)
    assert onnx_backend.resolve_backend("auto", "fp32", True, "cuda") == "onnxruntime"


@needs_cuda
def test_detect_on_cuda_matches_the_cpu():
    """The same frame through ShapeDetector on CUDA and on the CPU: the same objects, boxes
    within a centimetre (float32 on both; reductions run in another order)."""
    from shape_detector import ShapeDetector
    from toy_scenes import placed_box_scene

    frame, _, _ = placed_box_scene("dresser", np.array([0.53, 1.00, 1.17]), 0.25, 2.6, 0.35, 12.0, 1.3)
    gpu = ShapeDetector(device="cuda", precision="fp32", score_threshold=0.0)
    cpu = ShapeDetector(device="cpu", backend="torch", precision="fp32", score_threshold=0.0)
    assert gpu.predictor.backend == "torch" or onnx_backend.gpu_providers()
    a = gpu.detect(frame.rgb, frame.depth, frame.K)
    b = cpu.detect(frame.rgb, frame.depth, frame.K)
    assert len(a) == len(b) >= 1
    for x, y in zip(sorted(a, key=lambda o: -o.score), sorted(b, key=lambda o: -o.score)):
        assert x.class_name == y.class_name
        assert x.score == pytest.approx(y.score, abs=0.02)
        np.testing.assert_allclose(x.center, y.center, atol=0.01)
        np.testing.assert_allclose(x.size, y.size, atol=0.01)


@needs_cuda
def test_tiny_recipe_trains_on_cuda(tmp_path, monkeypatch):
    """The tiny recipe's phases run with ``--device cuda``: every phase writes weights whose
    tensors are finite, and the network's validation metrics were recorded."""
    import json
    from pathlib import Path

    from shape_detector.model.io import read_blob
    from shape_detector.training import recipe as rcp
    from shape_detector.training.runner import run_recipe

    monkeypatch.setenv("SHAPE_DETECTOR_CACHE", str(tmp_path / "graph_cache"))
    r = rcp.load_recipe(Path(__file__).resolve().parent / "data" / "tiny_recipe.json")
    run_recipe(r, tmp_path / "run", tmp_path / "data", device="cuda", say=lambda s: None)
    for ph in r["phases"]:
        res = json.loads((tmp_path / "run" / ph["name"] / "result.json").read_text())
        blob = read_blob(tmp_path / "run" / ph["name"] / res["file"])
        assert blob["provenance"]["metrics"], ph["name"]
        for k, t in blob["state_dict"].items():
            assert torch.isfinite(t.float()).all(), f"{ph['name']}: {k}"
