"""OnnxYoloProposer on tiny ONNX graphs built here: a constant YOLOv8 / YOLOv5 output."""

from __future__ import annotations

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from shape_detector.proposals import Proposal, get_proposer  # noqa: E402
from shape_detector.proposals.onnx_yolo import (  # noqa: E402
    COCO_TO_CLASS,
    OnnxYoloProposer,
    decode_yolo,
    letterbox,
)

# detections in letterboxed 640x640 input pixels: (cx, cy, w, h, coco id, score)
DETS = [
    (320.0, 320.0, 100.0, 200.0, 56, 0.90),  # chair
    (322.0, 318.0, 100.0, 204.0, 56, 0.60),  # duplicate chair -> removed by NMS
    (150.0, 400.0, 200.0, 100.0, 57, 0.80),  # couch -> sofa
    (500.0, 300.0, 120.0, 120.0, 0, 0.95),  # person -> dropped
    (480.0, 450.0, 60.0, 40.0, 61, 0.10),  # toilet below conf -> dropped
    (560.0, 200.0, 80.0, 100.0, 60, 0.70),  # dining table -> table
    (100.0, 100.0, 90.0, 60.0, 59, 0.50),  # bed, top edge inside the top letterbox padding
]


def _const_model(path, out: np.ndarray, input_size: int = 640) -> None:
    """A graph whose output is ``out`` (+ 0 * mean(input), so the input is consumed)."""
    inp = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, input_size, input_size])
    outp = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "Z"], ["mz"]),
        helper.make_node("Add", ["C", "mz"], ["output0"]),
    ]
    inits = [
        numpy_helper.from_array(out.astype(np.float32), "C"),
        numpy_helper.from_array(np.zeros(1, np.float32), "Z"),
    ]
    model = helper.make_model(helper.make_graph(nodes, "const_yolo", [inp], [outp], initializer=inits),
                              opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _v8_output(n: int = 16) -> np.ndarray:
    out = np.zeros((1, 84, n), np.float32)
    for j, (cx, cy, w, h, c, s) in enumerate(DETS):
        out[0, :4, j] = (cx, cy, w, h)
        out[0, 4 + c, j] = s
    return out


def _v5_output(n: int = 16) -> np.ndarray:
    out = np.zeros((1, n, 85), np.float32)
    for j, (cx, cy, w, h, c, s) in enumerate(DETS):
        out[0, j, :4] = (cx, cy, w, h)
        out[0, j, 4] = 1.0  # objectness
        out[0, j, 5 + c] = s
    return out


def _expected(H: int = 480, W: int = 640) -> dict[str, tuple[float, float, float, float, float]]:
    """Our classes' boxes in the original 640x480 image (letterbox: scale 1, 80 px top pad)."""
    exp = {}
    for cx, cy, w, h, c, s in DETS:
        name = COCO_TO_CLASS.get(c)
        if name is None or s < 0.25 or (name in exp):
            continue
        x1, y1, x2, y2 = cx - w / 2, cy - h / 2 - 80, cx + w / 2, cy + h / 2 - 80
        exp[name] = (max(x1, 0), max(y1, 0), min(x2, W), min(y2, H), s)
    return exp


@pytest.mark.parametrize("layout", ["v8", "v5"])
def test_decodes_boxes_and_maps_classes(tmp_path, layout):
    path = tmp_path / f"yolo_{layout}.onnx"
    _const_model(path, _v8_output() if layout == "v8" else _v5_output())
    prop = OnnxYoloProposer(path, input_size=640, conf=0.25, nms=0.45)
    rgb = np.zeros((480, 640, 3), np.uint8)
    props = prop.detect(rgb)
    assert all(isinstance(p, Proposal) and p.source == "onnx_yolo" for p in props)
    got = {p.class_name: p for p in props}
    exp = _expected()
    assert sorted(got) == sorted(exp) == ["bed", "chair", "sofa", "table"]
    assert len(props) == 4  # duplicate chair suppressed, person and low-score toilet dropped
    for name, (x1, y1, x2, y2, s) in exp.items():
        np.testing.assert_allclose(got[name].box2d, (x1, y1, x2, y2), atol=1e-3)
        assert got[name].score == pytest.approx(s, abs=1e-5)
    assert [p.score for p in props] == sorted((p.score for p in props), reverse=True)
    # the bed's top edge lay in the letterbox padding: clipped to the image
    assert got["bed"].box2d[1] == 0.0


def test_letterbox_scales_back(tmp_path):
    # a 1280x960 frame: scale 0.5, 80 px top padding -> boxes twice as large
    path = tmp_path / "yolo.onnx"
    _const_model(path, _v8_output())
    prop = get_proposer("onnx_yolo", model_path=path, conf=0.25)
    rgb = np.zeros((960, 1280, 3), np.uint8)
    got = {p.class_name: p.box2d for p in prop.detect(rgb)}
    np.testing.assert_allclose(got["chair"], (540.0, 280.0, 740.0, 680.0), atol=1e-2)
    img, scale, left, top = letterbox(rgb, 640)
    assert img.shape == (640, 640, 3) and scale == 0.5 and (left, top) == (0.0, 80.0)


def test_interface_returns_gravity_and_needs_rgb(tmp_path):
    path = tmp_path / "yolo.onnx"
    _const_model(path, _v8_output())
    prop = OnnxYoloProposer(path)
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    depth = np.full((480, 640), np.nan, np.float32)
    grav, props = prop(depth, K, rgb=np.zeros((480, 640, 3), np.uint8))
    assert grav.source == "prior" and grav.confidence == 0.0 and len(props) == 4
    up = np.array([0.0, -0.9, -0.1])
    grav, _ = prop(depth, K, up=up, rgb=np.zeros((480, 640, 3), np.uint8))
    np.testing.assert_allclose(grav.up, up / np.linalg.norm(up))
    with pytest.raises(ValueError):
        prop(depth, K)


def test_decode_rejects_unknown_layout_and_missing_file(tmp_path):
    with pytest.raises(ValueError):
        decode_yolo(np.zeros((1, 7, 9), np.float32))
    with pytest.raises(FileNotFoundError):
        OnnxYoloProposer(tmp_path / "missing.onnx")
    boxes, scores, cids = decode_yolo(_v8_output(), conf=0.85)
    assert len(boxes) == 2 and set(cids.tolist()) == {0, 56}
