"""Runner on hand-made frames with a fake detector, the report writer and the CLI wiring."""

from __future__ import annotations

import argparse
import json
import sys
import types

import cv2
import numpy as np
import pytest

import shape_detector
from shape_detector.evaluation import cli as eval_cli
from shape_detector.evaluation.report import markdown_table, to_jsonable, write_report
from shape_detector.evaluation.runner import evaluate
from shape_detector.geometry import heading_to_rotation
from shape_detector.types import Cuboid, Frame, GTObject, Object3D

UP = np.array([0.0, -1.0, 0.0])
H, W = 24, 32


def make_frame(seed: int) -> Frame:
    R = heading_to_rotation(0.2 * seed, UP)
    c1 = np.array([-0.8, 0.2, 3.0 + seed])
    c2 = np.array([0.9, 0.1, 4.0])
    parts1 = [Cuboid(c1 + R @ [0, 0, -0.2], [0.5, 0.5, 0.1], R), Cuboid(c1 + R @ [-0.2, 0, 0.1], [0.1, 0.5, 0.6], R)]
    mask = np.zeros((H, W), np.int32)
    mask[2:10, 2:10] = 1
    mask[5:20, 15:30] = 2
    objs = [
        GTObject("chair", (2, 2, 10, 10), c1, [0.5, 0.5, 0.8], R, heading=0.2 * seed, parts=parts1, instance_id=1),
        GTObject("table", (15, 5, 30, 20), c2, [1.2, 0.8, 0.7], heading_to_rotation(0.0, UP), instance_id=2),
        GTObject("bed", (0, 20, 4, 24), [0, 0.5, 6], [2, 1.6, 0.9], heading_to_rotation(0.0, UP),
                 visible_fraction=0.05, instance_id=3),
    ]
    return Frame(np.zeros((H, W, 3), np.uint8), np.ones((H, W), np.float32), np.eye(3), up=UP, objects=objs,
                 instance_mask=mask)


def fake_detect(frame: Frame, boxes2d):
    out = []
    assert boxes2d is not None
    for x1, y1, x2, y2, cls in boxes2d:
        g = next(o for o in frame.objects if tuple(o.box2d) == (x1, y1, x2, y2))
        shift = np.array([0.1, 0.0, 0.0])  # 10 cm centroid error
        d = Object3D(cls, 0.9, g.center + shift, g.size, g.rotation, box2d=(x1, y1, x2, y2),
                     primitives=[p.transformed(np.eye(3), shift) for p in g.parts])
        if cls == "table":  # per-point segmentation: 3 of 4 points right
            d.pixel_index = np.array([5 * W + 15, 6 * W + 16, 0, 1])
            d.seg_labels = np.array([1, 1, 0, 1])
        out.append(d)
    # one false positive, low score
    out.append(Object3D("chair", 0.1, [5, 0, 9], [0.5, 0.5, 0.8], heading_to_rotation(0.0, UP)))
    return out


def test_runner_gt_boxes():
    frames = [make_frame(s) for s in range(2)]
    res = evaluate(fake_detect, iter(frames), use_gt_boxes=True, min_visible=0.1, surface_samples=400)
    json.dumps(res, allow_nan=False)
    det = res["detection"]
    assert res["num_frames"] == 2
    assert det["ap"]["0.25"]["chair"] == pytest.approx(1.0)  # the FP ranks last
    assert det["ap"]["0.25"]["table"] == pytest.approx(1.0)
    assert det["ap"]["0.25"]["bed"] is None and det["num_ignored_gt"]["bed"] == 2
    assert det["num_det"]["bed"] == 2 and det["det_status"]["0.25"][0][2] == "ignored"
    box = res["box_errors"]
    assert box["per_class"]["chair"]["n"] == 2 and box["per_class"]["bed"]["n"] == 0
    assert box["all"]["centroid_error"]["mean"] == pytest.approx(0.1)
    assert box["all"]["heading_error_deg"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert box["per_class"]["table"]["seg_accuracy"]["mean"] == pytest.approx(0.75)
    assert all(p["pairing"] == "gt_box" for p in res["pairs"])
    sh = res["shape"]
    assert sh["per_class"]["chair"]["n"] == 2 and sh["per_class"]["table"]["n"] == 0
    assert sh["per_class"]["chair"]["iou_object"]["mean"] == pytest.approx(1.0)
    assert sh["per_class"]["chair"]["iou_box"]["mean"] == pytest.approx(1.0)
    assert sh["per_class"]["chair"]["distance_object"]["mean"] == pytest.approx(0.0, abs=1e-12)
    assert 0.0 < sh["per_class"]["chair"]["iou_camera"]["mean"] < 1.0
    assert res["timing"]["frames"] == 2 and len(res["timing"]["per_frame_s"]) == 2


def test_runner_gt_boxes_without_class_pair_by_the_box():
    frames = [make_frame(0)]

    def detect(frame, boxes2d):
        assert all(len(b) == 4 for b in boxes2d)  # the class is the detector's to name
        out = []
        for x1, y1, x2, y2 in boxes2d:
            g = next(o for o in frame.objects if tuple(o.box2d) == (x1, y1, x2, y2))
            out.append(Object3D("sofa" if g.class_name == "table" else g.class_name, 0.9, g.center, g.size,
                                g.rotation, box2d=(x1, y1, x2, y2)))
        return out

    res = evaluate(detect, frames, use_gt_boxes=True, min_visible=0.1, gt_class=False, class_hypotheses=2,
                   surface_samples=100)
    assert res["settings"]["mode"] == "gt_boxes_without_class"
    assert res["detection"]["ap"]["0.25"]["chair"] == pytest.approx(1.0)
    assert res["detection"]["ap"]["0.25"]["table"] == 0.0  # named a sofa: a miss for the AP ...
    assert sorted(p["pairing"] for p in res["pairs"]) == ["gt_box", "gt_box"]  # ... but paired by its box
    assert "detection_class_hypotheses" in res


def test_runner_detector_boxes_pairs_by_iou():
    frames = [make_frame(0)]

    def detect(frame, boxes2d):
        assert boxes2d is None
        g = frame.objects[1]
        return [Object3D("table", 0.8, g.center, g.size, g.rotation, box2d=(0, 0, 1, 1))]

    res = evaluate(detect, frames, use_gt_boxes=False)
    assert res["settings"]["mode"] == "detector_boxes"
    assert [p["pairing"] for p in res["pairs"]] == ["iou>=0.25"]
    assert res["detection"]["ap"]["0.5"]["table"] == pytest.approx(1.0)
    assert res["detection"]["ap"]["0.5"]["chair"] == 0.0
    assert "detection_class_hypotheses" not in res


def test_runner_class_hypotheses_section(tmp_path):
    frames = [make_frame(0)]
    g = frames[0].objects[1]  # a table
    probs = np.zeros(len(shape_detector.classes.CLASSES))
    probs[shape_detector.classes.CLASSES.index("desk")] = 0.7
    probs[shape_detector.classes.CLASSES.index("table")] = 0.2

    def detect(frame, boxes2d):
        return [Object3D("desk", 0.7, g.center, g.size, g.rotation, class_scores=probs)]

    res = evaluate(detect, frames, use_gt_boxes=False, class_hypotheses=2)
    assert res["detection"]["ap"]["0.5"]["table"] == 0.0
    hyp = res["detection_class_hypotheses"]
    assert hyp["k"] == 2 and hyp["ap"]["0.5"]["table"] == pytest.approx(1.0)
    md = write_report(res, tmp_path)["markdown"].read_text()
    assert "each box counted for its top 2 classes" in md


def test_markdown_table_and_jsonable():
    t = markdown_table([["chair", 3, 0.12345, None], ["a|b", float("nan"), 1.0, "x"]], ["class", "n", "AP", "note"])
    lines = t.strip().split("\n")
    assert lines[0] == "| class | n | AP | note |"
    assert lines[1] == "|---|---:|---:|---:|"
    assert lines[2] == "| chair | 3 | 0.123 | - |"
    assert lines[3] == "| a\\|b | - | 1.000 | x |"
    assert to_jsonable({1: np.float32(0.5), "b": (np.int64(2), float("inf")), "c": np.arange(2)}) == {
        "1": 0.5, "b": [2, None], "c": [0, 1]}


def test_write_report(tmp_path):
    res = evaluate(fake_detect, [make_frame(0)], use_gt_boxes=True, min_visible=0.1, surface_samples=200)
    paths = write_report(res, tmp_path / "rep", "Test report")
    md = paths["markdown"].read_text()
    assert "# Test report" in md and "AP@0.25" in md and "**mAP**" in md
    assert "| chair |" in md and "3D IoU" in md and "IoU (object)" in md
    assert json.loads(paths["json"].read_text())["num_frames"] == 1
    for key in ("pr_curves", "pr_curves_0.5", "ap_bar"):
        img = cv2.imread(str(paths[key]))
        assert img is not None and img.ndim == 3 and img.mean() < 255
    # a bare evaluate_detections result works too
    p2 = write_report(res["detection"], tmp_path / "rep2", "AP only")
    assert "AP@0.5" in p2["markdown"].read_text()


def test_cli_with_generated_frames(tmp_path, monkeypatch):
    gen = types.ModuleType("shape_detector.synth.generate")
    gen.generate_frame = make_frame

    class FakeDetector:
        def __init__(self, weights=None, device="cpu", **kw):
            self.weights = weights

        def detect(self, rgb, depth, K, boxes2d=None, up=None):
            frame = Frame(rgb, depth, K, up=up, objects=make_frame(0).objects)
            return fake_detect(frame, boxes2d)[:-1]

    monkeypatch.setitem(sys.modules, "shape_detector.synth.generate", gen)
    monkeypatch.setattr(shape_detector, "ShapeDetector", FakeDetector, raising=False)
    parser = argparse.ArgumentParser()
    eval_cli.configure_parser(parser)
    args = parser.parse_args(["--frames", "1", "--out", str(tmp_path / "o"), "--surface-samples", "100", "--quiet"])
    assert eval_cli.main(args) == 0
    assert (tmp_path / "o" / "report.md").is_file() and (tmp_path / "o" / "ap_per_class.png").is_file()
    assert json.loads((tmp_path / "o" / "report.json").read_text())["settings"]["up"] == "ground truth"
    args = parser.parse_args(["--data", str(tmp_path / "missing"), "--out", str(tmp_path / "o2")])
    assert eval_cli.main(args) == 2


def test_shape_class_mean_averages_class_means_not_pairs():
    from shape_detector.evaluation.runner import _class_mean

    recs = [{"class": "chair", "iou_camera": v, "distance_camera": 0.1, "iou_object": v, "distance_object": 0.1,
             "iou_box": v} for v in (0.1, 0.1, 0.1)]
    recs.append({"class": "bed", "iou_camera": 0.7, "distance_camera": 0.3, "iou_object": 0.7, "distance_object": 0.3,
                 "iou_box": 0.9})
    cm = _class_mean(recs, ["bed", "table", "chair"])
    assert cm["classes"] == 2 and cm["n"] == 4
    assert cm["iou_object"]["mean"] == pytest.approx(0.4)  # (0.1 + 0.7) / 2, not 1.0 / 4
    assert cm["distance_camera"]["mean"] == pytest.approx(0.2)
    assert cm["iou_box"]["mean"] == pytest.approx(0.5)
