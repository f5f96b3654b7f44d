"""precision int8: which layers are quantised, agreement with float32 on real frustums, the
backend rules, and the cache of int8 graphs."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

from shape_detector.classes import class_id  # noqa: E402
from shape_detector.frustum import extract_frustum  # noqa: E402
from shape_detector.model import onnx_backend  # noqa: E402
from shape_detector.model.onnx_export import GRAPH_FILES, read_meta  # noqa: E402
from shape_detector.model.onnx_quantize import INT8_GRAPHS, MIN_CHANNELS, int8_file, int8_graphs, int8_nodes  # noqa: E402
from shape_detector.model.predictor import FrustumPredictor  # noqa: E402

#: int8 moves the packaged network's boxes by about a millimetre (median over real frustums);
#: a heading bin that flips between two near-equal ones moves a box by more, rarely
MEDIAN_CENTRE_M = 0.01
MEDIAN_LOG_SIZE = 0.02


@pytest.fixture(scope="module")
def predictors():
    """The packaged network in float32 and in int8 (onnxruntime both)."""
    return (FrustumPredictor(backend="onnxruntime", precision="fp32"),
            FrustumPredictor(backend="onnxruntime", precision="int8"))


def test_auto_runs_the_unpublished_first_pass_and_given_boxes_in_int8(predictors):
    f, q = predictors
    a = FrustumPredictor(backend="onnxruntime", precision="auto")
    assert a.int8_graphs == ("frustum_box", "frustum_head") and f.int8_graphs == ()
    frs, cls = _real_frustums(2)

    def same(ps, rs) -> None:
        for p, r in zip(ps, rs):
            np.testing.assert_allclose(p.center, r.center, atol=1e-5)
            np.testing.assert_allclose(p.size, r.size, atol=1e-5)
            assert p.primitives and len(p.primitives) == len(r.primitives)

    # given boxes with their class: the int8 head graph, as precision int8
    same(q.predict(frs, cls), a.predict(frs, cls))
    # the class-given second pass and a class-agnostic pass whose boxes are published: float32
    same(f.predict(frs, cls, second=True), a.predict(frs, cls, second=True))
    same(f.predict(frs), a.predict(frs))
    # class-agnostic without shapes (a first pass the second replaces): the int8 box graph
    first_f, first_a = f.predict(frs, shapes=False), a.predict(frs, shapes=False)
    dc = [np.linalg.norm(p.center - r.center) for p, r in zip(first_f, first_a)]
    assert np.median(dc) < MEDIAN_CENTRE_M
    assert np.mean([p.class_name == r.class_name for p, r in zip(first_f, first_a)]) >= 0.9


def _real_frustums(n_frames: int = 4) -> tuple[list, list[int]]:
    from shape_detector.synth.generate import generate_frame

    frs, cls = [], []
    for seed in range(n_frames):
        frame = generate_frame(20_000 + seed)
        for o in frame.objects:
            frs.append(extract_frustum(frame.rgb, frame.depth, frame.K, o.box2d, 512, up=frame.up))
            cls.append(class_id(o.class_name))
    return frs, cls


def test_int8_quantises_the_wide_layers_outside_the_segmentation(predictors):
    _, q = predictors
    folder = q.graph_folder
    graphs = read_meta(folder)["graphs"]
    for name in INT8_GRAPHS:
        model = onnx.load(str(folder / GRAPH_FILES[name]))
        nodes = int8_nodes(model)
        weights = {t.name: tuple(t.dims) for t in model.graph.initializer}
        by_name = {n.name: n for n in model.graph.node}
        assert len(nodes) >= 9, name  # T-Net, box, context and second-box PointNets at least
        for n in nodes:
            assert "seg_" not in n and by_name[n].op_type == "MatMul"
            dims = [weights[i] for i in by_name[n].input if i in weights][0]
            assert dims[0] >= MIN_CHANNELS
        assert graphs[name + "_int8"]["quantized_matmuls"] == len(nodes)
        quantized = onnx.load(str(folder / int8_file(name)))
        assert sum(n.op_type in ("MatMulInteger", "DynamicQuantizeMatMul") for n in quantized.graph.node) >= len(nodes)


def test_int8_predictions_agree_with_float32_on_real_frustums(predictors):
    f, q = predictors
    frs, cls = _real_frustums()
    assert len(frs) >= 10
    a, b = f.predict(frs, cls), q.predict(frs, cls)
    # the segmentation stays float32: the same points are gathered
    for p, r in zip(a, b):
        np.testing.assert_allclose(p.seg_prob, r.seg_prob, atol=1e-4)
    dc = np.array([np.linalg.norm(p.center - r.center) for p, r in zip(a, b)])
    ds = np.array([np.abs(np.log(p.size / r.size)).max() for p, r in zip(a, b)])
    assert np.median(dc) < MEDIAN_CENTRE_M and np.median(ds) < MEDIAN_LOG_SIZE, (dc, ds)
    assert max(abs(p.score - r.score) for p, r in zip(a, b)) < 0.1
    # class-agnostic: the class head reads the int8 box feature; the best class rarely changes
    a0, b0 = f.predict(frs), q.predict(frs)
    assert np.mean([p.class_name == r.class_name for p, r in zip(a0, b0)]) >= 0.9
    assert all(len(r.primitives) > 0 for r in b)


def test_int8_refuses_the_torch_backend():
    with pytest.raises(ValueError, match="int8"):
        onnx_backend.resolve_backend("torch", "int8")


def test_int8_without_onnxruntime_runs_float32_in_torch_with_a_warning(monkeypatch):
    monkeypatch.setattr(onnx_backend, "ort_available", lambda: False)
    monkeypatch.setattr(onnx_backend, "_warned_missing", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert onnx_backend.resolve_backend("auto", "int8") == "torch"
    assert len(caught) == 1 and "int8" in str(caught[0].message)


def test_int8_graphs_are_rebuilt_unless_recorded(predictors, tmp_path):
    import shutil

    src = predictors[0].graph_folder
    for name in ("frustum_seg",) + INT8_GRAPHS:
        shutil.copy(src / GRAPH_FILES[name], tmp_path / GRAPH_FILES[name])
    shutil.copy(src / "graphs.json", tmp_path / "graphs.json")
    meta = json.loads((tmp_path / "graphs.json").read_text())
    meta["graphs"] = {k: v for k, v in meta["graphs"].items() if not k.endswith("_int8")}
    (tmp_path / "graphs.json").write_text(json.dumps(meta))
    stale = tmp_path / int8_file("frustum_head")
    stale.write_bytes(b"an int8 file this module did not record")
    paths = int8_graphs(tmp_path)
    assert onnx.load(str(paths["frustum_head"])).graph.node  # rebuilt: a graph again
    recorded = read_meta(tmp_path)["graphs"]
    assert all(recorded[n + "_int8"]["int8_version"] >= 1 for n in INT8_GRAPHS)
    mtime = paths["frustum_box"].stat().st_mtime_ns
    int8_graphs(tmp_path)
    assert paths["frustum_box"].stat().st_mtime_ns == mtime  # recorded: kept


def test_detector_with_int8_finds_the_objects_float32_finds():
    from shape_detector.detector import ShapeDetector
    from shape_detector.synth.generate import generate_frame

    frame = generate_frame(20_100)
    boxes = [(*o.box2d, o.class_name) for o in frame.objects]
    a = ShapeDetector(precision="fp32").detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes)
    det = ShapeDetector(precision="int8")
    assert det.predictor.precision == "int8" and det.classifier is not None
    b = det.detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes)
    assert len(a) == len(b) > 0
    near = [min(np.linalg.norm(o.center - p.center) for p in b) < 0.05 for o in a]
    assert np.mean(near) >= 0.8
    assert det.detect(frame.rgb, frame.depth, frame.K)  # built-in proposals: classifier in float32


def test_int8_without_the_quantiser_runs_float32_graphs_with_a_warning(tmp_path, monkeypatch):
    from shape_detector.model import onnx_quantize

    from small_net import save_small_weights

    monkeypatch.setenv("SHAPE_DETECTOR_CACHE", str(tmp_path / "cache"))
    w = save_small_weights(tmp_path / "w.pt", num_points=64, num_object_points=32)

    def missing(*_a, **_k):
        raise ImportError("No module named 'onnx'")

    monkeypatch.setattr(onnx_quantize, "quantize_graph", missing)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        p = FrustumPredictor(w, backend="onnxruntime", precision="int8")
    assert p.backend == "onnxruntime" and p.precision == "fp32"
    assert [str(c.message) for c in caught if "int8" in str(c.message)]
