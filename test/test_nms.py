"""3D NMS (shape_detector.nms)."""

import numpy as np

from shape_detector.geometry import heading_to_rotation
from shape_detector.nms import nms_3d, overlap_ratios
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
