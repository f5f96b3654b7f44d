"""The detector's first pass skips the shape branch only where no first-pass primitive is published."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.detector import ShapeDetector

from test_model_scene import make_frame


@pytest.fixture(scope="module")
def detector():
    # float32: under `auto` the shape-less first pass also runs in int8 (test_int8.py), which
    # moves the classifier's inputs by int8 noise; here only the skipped shape branch differs
    return ShapeDetector(score_threshold=0.0, refine_min_score=0.0, refine_nms=False, precision="fp32")


def _objects(det, frame, boxes=None):
    return det.detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes, up=frame.up)


def test_skipping_first_pass_shapes_leaves_the_detections_unchanged(detector, monkeypatch):
    frames = [make_frame(seed=s) for s in (1, 2)]
    calls = []
    orig = detector.predictor.predict

    def spy(*a, **k):
        calls.append(k.get("shapes", True))
        return orig(*a, **k)

    monkeypatch.setattr(detector.predictor, "predict", spy)
    lite = [_objects(detector, f) for f in frames]
    assert False in calls  # built-in proposals, refine_min_score <= score_threshold: skipped
    monkeypatch.setattr(type(detector), "_second_pass_replaces_shapes", lambda self, ids: False)
    full = [_objects(detector, f) for f in frames]
    assert [len(x) for x in lite] == [len(x) for x in full] and sum(len(x) for x in full) > 0
    for a, b in zip(lite, full):
        for p, q in zip(a, b):
            assert p.class_name == q.class_name and abs(p.score - q.score) < 1e-9
            np.testing.assert_allclose(p.center, q.center, atol=1e-9)
            assert len(p.primitives) == len(q.primitives) > 0


def test_first_pass_keeps_shapes_where_they_may_be_published():
    det = ShapeDetector(score_threshold=0.2, refine_min_score=0.5)
    assert not det._second_pass_replaces_shapes([None, None])  # a 0.2..0.5 first pass is published
    det = ShapeDetector(refine=False)
    assert not det._second_pass_replaces_shapes([None])
    det = ShapeDetector()
    assert det._second_pass_replaces_shapes([None, None])
    assert not det._second_pass_replaces_shapes([None, 3])  # a given class gets no second pass
    assert not det._second_pass_replaces_shapes([])
    # duplicates suppressed before the second pass keep their first pass, published when
    # their decayed score reaches the threshold
    assert not ShapeDetector(score_threshold=0.05)._second_pass_replaces_shapes([None])
    assert ShapeDetector(score_threshold=0.05, refine_nms=False, refine_min_score=0.05)._second_pass_replaces_shapes([None])


def test_duplicates_are_suppressed_before_the_second_pass(monkeypatch):
    frames = [make_frame(seed=s) for s in (1, 2, 3)]
    runs = {}
    for nms in (True, False):
        # the suppression does not depend on the proposer; with the geometric one every object of
        # these frames keeps its class either way (with hybrid, one sofa is a bed without it)
        det = ShapeDetector(refine_nms=nms, proposal_source="geometric", max_objects=10)
        sizes = []
        orig = det.predictor.refine

        def spy(frs, *a, _orig=orig, _sizes=sizes, **k):
            _sizes.append(len(frs))
            return _orig(frs, *a, **k)

        monkeypatch.setattr(det.predictor, "refine", spy)
        runs[nms] = ([_objects(det, f) for f in frames], sum(sizes))
    (with_nms, n_nms), (without, n_all) = runs[True], runs[False]
    assert n_nms < n_all  # fewer frustums run the second pass
    for a, b in zip(with_nms, without):
        assert abs(len(a) - len(b)) <= 1  # the published objects are (nearly) the same ones
        for p in a:  # each published object has a counterpart of the same class nearby
            assert any(q.class_name == p.class_name and np.linalg.norm(q.center - p.center) < 0.3 for q in b)
        assert all(len(p.primitives) > 0 for p in a)
