"""ONNX Runtime backend: agreement with PyTorch, the fallback without onnxruntime, export-onnx."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
torch = pytest.importorskip("torch")

from shape_detector.frustum import Frustum, extract_frustum  # noqa: E402
from shape_detector.model import onnx_backend  # noqa: E402
from shape_detector.model.bench import random_frustums  # noqa: E402
from shape_detector.model.config import ModelConfig  # noqa: E402
from shape_detector.model.predictor import FrustumPredictor  # noqa: E402

from test_model_scene import make_frame  # noqa: E402
from small_net import save_small_weights  # noqa: E402

SMALL = dict(num_points=128, num_object_points=64, seg_widths=(16, 16, 32), seg_head_widths=(16,),
             tnet_widths=(16, 32), tnet_fc=(16,), box_widths=(16, 32), box_fc=(32,), shape_fc=(32,), cls_fc=(16,),
             box_context_widths=(16, 32), box2_widths=(16, 32), box2_fc=(16,), shape_widths=(16, 32),
             shape_context_widths=(16, 32))
#: ONNX Runtime and PyTorch run the same float32 maths in other orders: outputs of order 1
#: (metres, radians, probabilities) agree to ~1e-6; a point whose foreground logit sits on 0
#: may flip and move a box by millimetres, so boxes get a looser bound than probabilities
PROB_ATOL = 1e-4
BOX_ATOL_M = 5e-3


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return save_small_weights(tmp_path_factory.mktemp("w") / "w.pt", **SMALL)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A private graph cache (the module's exports do not touch the user's)."""
    path = tmp_path_factory.mktemp("cache")
    old = os.environ.get("SHAPE_DETECTOR_CACHE")
    os.environ["SHAPE_DETECTOR_CACHE"] = str(path)
    yield path
    if old is None:
        os.environ.pop("SHAPE_DETECTOR_CACHE", None)
    else:
        os.environ["SHAPE_DETECTOR_CACHE"] = old


def _random_frustums(n: int, num_points: int, seed: int = 0) -> list:
    return random_frustums(n, num_points, np.random.default_rng(seed))


def _real_frustums(num_points: int) -> tuple[list[Frustum], list[int]]:
    """Frustums of the GT boxes of a ray-cast test scene, with their class ids."""
    from shape_detector.classes import class_id

    frame = make_frame()
    frs, cls = [], []
    for o in frame.objects:
        frs.append(extract_frustum(frame.rgb, frame.depth, frame.K, o.box2d, num_points, up=frame.up))
        cls.append(class_id(o.class_name))
    return frs, cls


def _assert_agree(a: list, b: list) -> None:
    for p, q in zip(a, b):
        assert p.class_name == q.class_name
        np.testing.assert_allclose(p.class_probs, q.class_probs, atol=PROB_ATOL)
        np.testing.assert_allclose(p.center, q.center, atol=BOX_ATOL_M)
        np.testing.assert_allclose(p.size, q.size, atol=BOX_ATOL_M)
        assert abs(p.score - q.score) <= PROB_ATOL


@pytest.mark.parametrize("kind", ["random", "real"])
def test_onnxruntime_and_torch_agree_on_frustums(weights, cache, kind):
    ort_pred = FrustumPredictor(weights, backend="onnxruntime")
    torch_pred = FrustumPredictor(weights, backend="torch")
    assert (ort_pred.backend, torch_pred.backend) == ("onnxruntime", "torch")
    n = ort_pred.num_points
    if kind == "random":
        frs, cls = _random_frustums(5, n), [None, 1, None, 3, 0]
    else:
        frs, cls = _real_frustums(n)
        assert frs and all(f.valid > 0 for f in frs)
    first_o = ort_pred.predict(frs, [None] * len(frs), keep_features=True)
    first_t = torch_pred.predict(frs, [None] * len(frs), keep_features=True)
    _assert_agree(first_o, first_t)
    _assert_agree(ort_pred.predict(frs, cls), torch_pred.predict(frs, cls))
    # the class-given second pass reuses the first pass's features in both runtimes
    _assert_agree(ort_pred.refine(frs, first_o), torch_pred.refine(frs, first_t))


def test_auto_falls_back_to_torch_with_one_warning_without_onnxruntime(weights, cache, monkeypatch):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import onnxruntime -> ImportError
    monkeypatch.setattr(onnx_backend, "_warned_missing", False)
    assert not onnx_backend.ort_available()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        preds = [FrustumPredictor(weights, backend="auto") for _ in range(2)]
    assert [p.backend for p in preds] == ["torch", "torch"]
    missing = [w for w in caught if "onnxruntime is not installed" in str(w.message)]
    assert len(missing) == 1
    out = preds[0].predict(_random_frustums(2, preds[0].num_points), [None, 2])
    assert len(out) == 2 and all(np.all(np.isfinite(p.center)) for p in out)
    with pytest.raises(ImportError, match="onnxruntime"):
        FrustumPredictor(weights, backend="onnxruntime")


@pytest.mark.slow
def test_export_onnx_writes_graphs_that_load_and_match_torch(weights, tmp_path):
    import onnxruntime as ort

    from shape_detector.model import export_cli
    from shape_detector.model.traced import inference_outputs

    parser = argparse.ArgumentParser()
    export_cli.configure_parser(parser)
    out = tmp_path / "graphs"
    assert export_cli.main(parser.parse_args(["--out", str(out), "--weights", str(weights),
                                              "--classifier", "none"])) == 0
    info = json.loads((out / "graphs.json").read_text())
    assert set(info["graphs"]) == {"frustum_seg", "frustum_head", "frustum_box"}
    assert info["meta"]["weights_sha256"] and ModelConfig.from_dict(info["model_config"]).num_points == 128
    sessions = {k: ort.InferenceSession(str(out / g["file"]), providers=["CPUExecutionProvider"])
                for k, g in info["graphs"].items()}
    for name, sess in sessions.items():
        assert [i.name for i in sess.get_inputs()] == list(info["graphs"][name]["inputs"])
    model = FrustumPredictor(weights, backend="torch").model
    pts = np.stack([f.points for f in _random_frustums(3, 128, seed=4)]).astype(np.float32)
    one_hot = np.eye(3, model.config.num_classes, dtype=np.float32)
    glob, local = sessions["frustum_seg"].run(None, {"points": pts})
    got = sessions["frustum_head"].run(None, {"points": pts, "one_hot": one_hot, "seg_glob": glob, "seg_local": local})
    with torch.inference_mode():
        want = inference_outputs(model, torch.as_tensor(pts), torch.as_tensor(one_hot))
    np.testing.assert_allclose(got[0], want[0].numpy(), atol=PROB_ATOL)  # probs
    np.testing.assert_allclose(got[2], want[2].numpy(), atol=BOX_ATOL_M)  # centre (m)
    np.testing.assert_allclose(got[5], want[5].numpy(), atol=BOX_ATOL_M)  # size (m)


def test_export_onnx_takes_the_classifier_of_the_proposer_it_serves(tmp_path):
    from shape_detector.model.export_cli import classifier_path

    w = tmp_path / "default.pt"
    assert classifier_path(w, None, "hybrid") is None  # none beside the weights: the frustum graphs alone
    (tmp_path / "classifier.pt").write_bytes(b"x")
    assert classifier_path(w, None, "hybrid") == tmp_path / "classifier.pt"
    (tmp_path / "classifier_hybrid.pt").write_bytes(b"x")
    assert classifier_path(w, None, "hybrid") == tmp_path / "classifier_hybrid.pt"
    assert classifier_path(w, None, "geometric") == tmp_path / "classifier.pt"
    assert classifier_path(w, "none", "hybrid") is None
    assert classifier_path(w, tmp_path / "classifier.pt", "hybrid") == tmp_path / "classifier.pt"
    with pytest.raises(FileNotFoundError, match="other.pt"):
        classifier_path(w, tmp_path / "other.pt")


def test_export_onnx_reports_a_missing_weights_file(tmp_path, capsys):
    from shape_detector.model import export_cli

    parser = argparse.ArgumentParser()
    export_cli.configure_parser(parser)
    args = parser.parse_args(["--out", str(tmp_path / "o"), "--weights", str(tmp_path / "missing.pt")])
    assert export_cli.main(args) == 2
    assert "missing.pt" in capsys.readouterr().err


@pytest.mark.slow
def test_detector_under_onnxruntime_detects_without_importing_torch_once_graphs_are_cached(tmp_path):
    # warm_up detects with given boxes and with built-in proposals (classifier, second pass)
    code = ("import sys; import shape_detector.detector as d; d.ShapeDetector(max_objects=2).warm_up(); "
            "print('torch' in sys.modules)")
    env = {**os.environ, "SHAPE_DETECTOR_CACHE": str(tmp_path), "SHAPE_DETECTOR_BACKEND": ""}
    root = Path(__file__).resolve().parents[1]
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=root,
                           timeout=120) for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr
    assert runs[1].stdout.strip().splitlines()[-1] == "False"  # the first run exported (with torch)


def test_first_pass_without_shapes_keeps_every_other_output(weights, cache):
    pred = FrustumPredictor(weights, backend="onnxruntime")
    frs = _random_frustums(4, pred.num_points, seed=2)
    full = pred.predict(frs, [None] * 4, keep_features=True)
    lite = pred.predict(frs, [None] * 4, keep_features=True, shapes=False)
    assert all(p.primitives == [] and p.primitives_canonical == [] for p in lite)
    assert any(p.primitives for p in full)
    for p, q in zip(full, lite):  # same graphs up to the shape branch: same numbers
        np.testing.assert_allclose(p.class_probs, q.class_probs, atol=1e-6)
        np.testing.assert_allclose(p.center, q.center, atol=1e-6)
        np.testing.assert_allclose(p.size, q.size, atol=1e-6)
        np.testing.assert_allclose(p.seg_prob, q.seg_prob, atol=1e-6)
    # the second pass does not care which first pass it follows
    a, b = pred.refine(frs, full), pred.refine(frs, lite)
    for p, q in zip(a, b):
        np.testing.assert_allclose(p.center, q.center, atol=1e-6)
        assert len(p.primitives) == len(q.primitives)


@pytest.mark.slow
def test_processes_starting_together_share_one_export_of_the_graphs(tmp_path):
    """Three processes start at once on a cold graph cache (two detector nodes launched
    together, detector_processes): one exports and quantises, the others wait for it; every
    one runs in onnxruntime, none falls back to torch, and graphs.json records every graph.
    The shipped architecture (random weights): with a small network the export and the
    quantiser's scratch file live too briefly for the processes to collide."""
    w = save_small_weights(tmp_path / "w.pt")
    code = ("import warnings, sys; warnings.simplefilter('error'); "
            "from shape_detector.model.predictor import FrustumPredictor; "
            f"p = FrustumPredictor({str(w)!r}, backend='onnxruntime', precision='auto'); "
            "print(p.backend, p.int8_graphs)")
    env = {**os.environ, "SHAPE_DETECTOR_CACHE": str(tmp_path / "cache"), "SHAPE_DETECTOR_BACKEND": ""}
    root = Path(__file__).resolve().parents[1]
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env=env, cwd=root) for _ in range(3)]
    outs = [p.communicate(timeout=240) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-2000:]
        assert out.split()[0] == "onnxruntime", (out, err[-2000:])
    (folder,) = (tmp_path / "cache").iterdir()
    graphs = json.loads((folder / "graphs.json").read_text())["graphs"]
    assert {"frustum_seg", "frustum_head", "frustum_box", "frustum_head_int8", "frustum_box_int8"} <= set(graphs)
    assert graphs["frustum_head_int8"]["quantized_matmuls"] > 0
    assert not [f.name for f in folder.iterdir() if f.name.endswith((".tmp", "-inferred.onnx"))]
