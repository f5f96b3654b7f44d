"""3D NMS (shape_detector.postprocess.nms)."""

import numpy as np
import pytest

from shape_detector.geometry import heading_to_rotation
from shape_detector.postprocess.nms import nms_3d, overlap_ratios
from shape_detector.types import Object3D

R = heading_to_rotation(0.3, None)


def _obj(score, center, size=(1.0, 1.0, 1.0), name="chair"):
    return Object3D(name, score, np.array(center, float), np.array(size, float), R)


def test_overlap_ratios_of_nested_boxes():
    big, small = _obj(0.9, [0, 0, 3]), _obj(0.5, [0, 0, 3], (0.5, 0.5, 0.5))
    iou, contained = overlap_ratios(big, small)
    assert abs(iou - 0.125) < 1e-6 and abs(contained - 1.0) < 1e-6


def test_nms_suppresses_duplicates_and_nested_keeps_separate():
    objs = [
        _obj(0.6, [0.05, 0, 3.0]),  # duplicate of the best one
        _obj(0.9, [0, 0, 3.0]),
        _obj(0.7, [0, 0, 3.0], (0.4, 0.4, 0.4), "table"),  # nested inside it, other class
        _obj(0.8, [2.0, 0, 3.0]),  # a separate object
    ]
    kept = nms_3d(objs, 0.25)
    assert [o.score for o in kept] == [0.9, 0.8]


def test_touching_objects_survive():
    a, b = _obj(0.9, [0, 0, 3.0]), _obj(0.8, [0, 0, 3.0] + R[:, 0] * 1.0)
    assert len(nms_3d([a, b])) == 2


def test_prism_overlaps_match_the_exact_iou():
    """The per-frame prism shortcut gives box3d_iou's numbers (random yaw-only boxes)."""
    from shape_detector.postprocess.nms import _prism_overlap, _prisms

    rng = np.random.default_rng(0)
    up = np.array([0.05, -0.99, 0.1])
    up /= np.linalg.norm(up)
    objs = [Object3D("chair", 0.5, rng.normal(0, 0.4, 3) + [0, 0, 3], rng.uniform(0.3, 1.2, 3),
                     heading_to_rotation(rng.uniform(-3, 3), up)) for _ in range(12)]
    prisms = _prisms(objs)
    assert prisms is not None
    for i in range(len(objs)):
        for k in range(len(objs)):
            got = _prism_overlap(prisms[i], prisms[k])
            want = overlap_ratios(objs[i], objs[k])
            assert np.allclose(got, want, atol=1e-5), (i, k, got, want)
    # a box tilted off the shared vertical: the shortcut declines, NMS falls back to the exact path
    tilted = Object3D("chair", 0.4, np.array([0, 0, 3.0]), np.ones(3), heading_to_rotation(0.2, np.array([0, -1.0, 0.3])))
    assert _prisms(objs + [tilted]) is None
    assert len(nms_3d(objs + [tilted], 0.25)) >= 1


def test_decay_keeps_suppressed_boxes_at_a_fraction_of_their_score():
    objs = [
        _obj(0.6, [0.05, 0, 3.0]),  # duplicate of the best one
        _obj(0.9, [0, 0, 3.0]),
        _obj(0.7, [0, 0, 3.0], (0.4, 0.4, 0.4), "table"),  # nested inside it
        _obj(0.8, [2.0, 0, 3.0]),
        _obj(0.5, [2.02, 0, 3.0]),  # duplicate of the separate object
    ]
    objs[0].class_scores = np.array([0.6, 0.3])
    out = nms_3d(objs, 0.25, decay=0.1)
    np.testing.assert_allclose(out[3].class_scores, [0.06, 0.03])  # per-class confidences decay too
    np.testing.assert_allclose(objs[0].class_scores, [0.6, 0.3])
    assert [round(o.score, 6) for o in out] == [0.9, 0.8, 0.07, 0.06, 0.05]  # kept first, then by old score
    assert [o.class_name for o in out][2] == "table"
    assert sorted(o.score for o in objs) == [0.5, 0.6, 0.7, 0.8, 0.9]  # inputs untouched (copies)
    assert out[:2] == nms_3d(objs, 0.25)  # the kept set is the hard NMS result
    # a score threshold above a decayed score: that copy is never made
    assert [round(o.score, 6) for o in nms_3d(objs, 0.25, decay=0.1, min_score=0.06)] == [0.9, 0.8, 0.07, 0.06]


def test_suppressed_boxes_suppress_nothing():
    """A box suppressed by the best one must not in turn suppress a third box that only
    it overlaps: hard NMS keeps that third box, and so does the decayed variant."""
    a = _obj(0.9, [0, 0, 3.0])
    b = _obj(0.8, np.array([0, 0, 3.0]) + R[:, 0] * 0.5)  # IoU 1/3 with a -> suppressed
    c = _obj(0.7, np.array([0, 0, 3.0]) + R[:, 0] * 1.0)  # touches a, IoU 1/3 with b
    assert overlap_ratios(b, c)[0] > 0.25 and overlap_ratios(a, c)[0] == pytest.approx(0.0, abs=1e-9)
    hard = nms_3d([a, b, c], 0.25)
    soft = nms_3d([a, b, c], 0.25, decay=0.2)
    assert hard == [a, c] and soft[:2] == [a, c]
    assert len(soft) == 3 and soft[2].score == pytest.approx(0.8 * 0.2)
