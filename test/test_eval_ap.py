"""Hand-computed AP cases: ranking, greedy matching, duplicates, ignored GT, mAP."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shape_detector.classes import CLASSES
from shape_detector.evaluation.ap import evaluate_detections, expand_class_hypotheses, pr_curve, voc_ap
from shape_detector.types import GTObject, Object3D

I3 = np.eye(3)


def gt(cls, x, vis=1.0, size=1.0):
    return GTObject(cls, (0, 0, 10, 10), [x, 0, 0], [size] * 3, I3, visible_fraction=vis)


def det(cls, score, x, size=1.0):
    return Object3D(cls, score, [x, 0, 0], [size] * 3, I3)


def scenario(vis1=1.0):
    # frame 0: chairs at x=0 (g0) and x=5 (g1); frame 1: chair at x=0 (g2)
    gts = [[gt("chair", 0.0), gt("chair", 5.0, vis=vis1)], [gt("chair", 0.0)]]
    dets = [
        [
            det("chair", 0.9, 0.0),   # a: g0, IoU 1 -> TP
            det("chair", 0.8, 10.0),  # b: nothing -> FP
            det("chair", 0.6, 0.1),   # d: duplicate of g0 (IoU 0.9/1.1) -> FP
            det("chair", 0.5, 5.5),   # e: g1 with IoU 0.5/1.5 = 1/3 -> TP@0.25, FP@0.5
        ],
        [det("chair", 0.7, 0.0)],     # c: g2 -> TP
    ]
    return dets, gts


def test_voc_ap_hand():
    # ranked TP FP TP FP with 3 GT: envelope 1 up to r=1/3, 2/3 up to r=2/3
    prec, rec = pr_curve(["tp", "fp", "tp", "fp"], 3)
    np.testing.assert_allclose(prec, [1, 0.5, 2 / 3, 0.5])
    np.testing.assert_allclose(rec, [1 / 3, 1 / 3, 2 / 3, 2 / 3])
    assert voc_ap(rec, prec) == pytest.approx(5 / 9)
    assert voc_ap([], []) == 0.0
    assert voc_ap([0.5, 1.0], [1.0, 1.0]) == pytest.approx(1.0)
    # precision dip later lifted by the envelope: p = 1, 0.5, 0.667 at r = .5, .5, 1
    assert voc_ap([0.5, 0.5, 1.0], [1.0, 0.5, 2 / 3]) == pytest.approx(0.5 + 0.5 * 2 / 3)


def test_three_gt_known_curve():
    dets, gts = scenario()
    r = evaluate_detections(dets, gts, (0.25, 0.5), classes=("chair", "table"))
    # @0.25 ranked a b c d e = TP FP TP FP TP: P = 1 .5 .667 .5 .6, R = 1/3 1/3 2/3 2/3 1
    assert r["ap"]["0.25"]["chair"] == pytest.approx(1 / 3 + (1 / 3) * (2 / 3) + (1 / 3) * 0.6)
    np.testing.assert_allclose(r["precision"]["0.25"]["chair"], [1, 0.5, 2 / 3, 0.5, 0.6])
    np.testing.assert_allclose(r["recall"]["0.25"]["chair"], [1 / 3, 1 / 3, 2 / 3, 2 / 3, 1])
    # @0.5 e becomes a FP: AP = 1/3 * 1 + 1/3 * 2/3
    assert r["ap"]["0.5"]["chair"] == pytest.approx(5 / 9)
    assert r["num_gt"] == {"chair": 3, "table": 0}
    assert r["num_det"]["chair"] == 5
    # table has no GT: NaN, not in the mAP
    assert math.isnan(r["ap"]["0.25"]["table"])
    assert r["mAP"]["0.5"] == pytest.approx(5 / 9)
    # matching: (frame, det) -> gt
    m = {(x["frame"], x["det"]): x["gt"] for x in r["matches"]["0.25"]}
    assert m == {(0, 0): 0, (1, 0): 0, (0, 3): 1}
    assert r["det_status"]["0.25"] == [["tp", "fp", "fp", "tp"], ["tp"]]
    assert r["det_status"]["0.5"][0][3] == "fp"
    iou_e = [x["iou"] for x in r["matches"]["0.25"] if (x["frame"], x["det"]) == (0, 3)][0]
    assert iou_e == pytest.approx(1 / 3)


def test_ignored_gt():
    dets, gts = scenario(vis1=0.1)  # g1 barely visible
    r = evaluate_detections(dets, gts, (0.25, 0.5), classes=("chair",), min_visible=0.5)
    assert r["num_gt"]["chair"] == 2 and r["num_ignored_gt"]["chair"] == 1
    # @0.25 e falls on the ignored GT: dropped. Ranked TP FP TP FP, 2 GT -> 1*.5 + 2/3*.5
    assert r["det_status"]["0.25"][0][3] == "ignored"
    assert len(r["precision"]["0.25"]["chair"]) == 4
    assert r["ap"]["0.25"]["chair"] == pytest.approx(0.5 + 0.5 * 2 / 3)
    # @0.5 e overlaps nothing enough: FP at the end, no change in AP
    assert r["det_status"]["0.5"][0][3] == "fp"
    assert r["ap"]["0.5"]["chair"] == pytest.approx(0.5 + 0.5 * 2 / 3)
    # explicit flag works as well
    g = gt("chair", 5.0)
    g.ignore = True
    r2 = evaluate_detections([[det("chair", 0.9, 5.0)]], [[g]], (0.5,), classes=("chair",))
    assert r2["num_gt"]["chair"] == 0 and r2["det_status"]["0.5"] == [["ignored"]]


def test_greedy_prefers_unmatched_gt_and_duplicates_are_fp():
    # two overlapping GT; both dets overlap gA most, the second then takes gB
    gts = [[gt("sofa", 0.0, size=2.0), gt("sofa", 0.6, size=2.0)]]
    dets = [[det("sofa", 0.9, 0.0, size=2.0), det("sofa", 0.8, 0.1, size=2.0), det("sofa", 0.7, 0.0, size=2.0)]]
    r = evaluate_detections(dets, gts, (0.5,), classes=("sofa",))
    m = {x["det"]: x["gt"] for x in r["matches"]["0.5"]}
    assert m == {0: 0, 1: 1}
    assert r["det_status"]["0.5"] == [["tp", "tp", "fp"]]
    assert r["ap"]["0.5"]["sofa"] == pytest.approx(1.0)


def test_map_over_classes_with_gt_and_missing_dets():
    dets, gts = scenario()
    gts[1].append(gt("table", 20.0))
    dets[1].append(det("table", 0.3, 20.0))
    gts[0].append(gt("bed", 30.0))  # bed: GT but no detection -> AP 0
    r = evaluate_detections(dets, gts, (0.25,), classes=("chair", "table", "bed", "desk"))
    assert r["ap"]["0.25"]["table"] == pytest.approx(1.0)
    assert r["ap"]["0.25"]["bed"] == 0.0
    assert math.isnan(r["ap"]["0.25"]["desk"])
    expected = (r["ap"]["0.25"]["chair"] + 1.0 + 0.0) / 3
    assert r["mAP"]["0.25"] == pytest.approx(expected)


def test_score_ties_keep_input_order_and_empty_input():
    gts = [[gt("chair", 0.0)]]
    dets = [[det("chair", 0.5, 10.0), det("chair", 0.5, 0.0)]]
    r = evaluate_detections(dets, gts, (0.5,), classes=("chair",))
    assert r["det_status"]["0.5"] == [["fp", "tp"]]
    assert r["ap"]["0.5"]["chair"] == pytest.approx(0.5)
    r = evaluate_detections([[]], [[]], (0.5,), classes=("chair",))
    assert math.isnan(r["mAP"]["0.5"])


def test_class_hypotheses_count_a_box_for_its_runner_up_class():
    # one box on a desk, classified table (0.6) over desk (0.3): AP(desk) 0 -> 1 with top-2
    probs = np.zeros(len(CLASSES))
    probs[CLASSES.index("table")], probs[CLASSES.index("desk")], probs[CLASSES.index("chair")] = 0.6, 0.3, 0.05
    d = Object3D("table", 0.6, [0, 0, 0], [1, 1, 1], I3, class_scores=probs)
    gts = [[gt("desk", 0.0)]]
    one = evaluate_detections([[d]], gts, (0.25,))
    assert one["ap"]["0.25"]["desk"] == 0.0
    two = expand_class_hypotheses([d], 2)
    assert [(e.class_name, e.score) for e in two] == [("table", 0.6), ("desk", 0.3)]
    assert d.class_name == "table" and d.score == 0.6  # the input is not modified
    assert evaluate_detections([two], gts, (0.25,))["ap"]["0.25"]["desk"] == pytest.approx(1.0)
    # k = 1 and detections without class scores pass through
    plain = det("chair", 0.5, 3.0)
    assert expand_class_hypotheses([d, plain], 1) == [d, plain]
    assert expand_class_hypotheses([plain], 3) == [plain]
