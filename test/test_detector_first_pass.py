"""The detector's first pass skips the shape branch only where no first-pass primitive is published."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.detector import ShapeDetector

from test_model_scene import make_frame


@pytest.fixture(scope="module")
def detector():
    return ShapeDetector(score_threshold=0.0, refine_min_score=0.0)


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
