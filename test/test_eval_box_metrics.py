"""Hand-computed Table-4.1 box errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shape_detector.evaluation.box_metrics import (
    aggregate_box_errors,
    centroid_error,
    corner_error,
    heading_error,
    pair_errors,
    segmentation_accuracy,
    size_error,
)
from shape_detector.geometry import box_corners, heading_to_rotation
from shape_detector.types import GTObject, Object3D

UP = np.array([0.0, -1.0, 0.0])


def test_centroid_and_size():
    np.testing.assert_allclose(centroid_error([[0, 0, 0], [1, 1, 1]], [[3, 4, 0], [1, 1, 1]]), [5, 0])
    ab, rel = size_error([[1, 2, 3]], [[2, 2, 2]])
    np.testing.assert_allclose(ab, [[1, 0, 1]])
    np.testing.assert_allclose(rel, [[0.5, 0, 0.5]])


def test_heading_wrap_and_symmetry():
    d = np.radians
    e = heading_error(d([170, 0, 100, 30]), d([-170, 180, -90, 30]))
    np.testing.assert_allclose(np.degrees(e), [20, 180, 170, 0], atol=1e-9)
    s = heading_error(d([170, 0, 100, 30]), d([-170, 180, -90, 30]), symmetric=True)
    np.testing.assert_allclose(np.degrees(s), [20, 0, 10, 0], atol=1e-9)


def test_corner_error_shift_and_flip():
    size = np.array([2.0, 1.0, 0.5])
    R = heading_to_rotation(0.3, UP)
    gt = box_corners(np.zeros(3), size, R)
    shifted = box_corners(np.array([0.3, 0.0, 0.0]), size, R)
    assert corner_error(shifted[None], gt[None])[0] == pytest.approx(0.3)
    flipped = box_corners(np.zeros(3), size, heading_to_rotation(0.3 + math.pi, UP))
    # each corner lands on the diagonally opposite corner of the footprint
    assert corner_error(flipped[None], gt[None])[0] == pytest.approx(math.hypot(2.0, 1.0))
    assert corner_error(flipped[None], gt[None], flip_invariant=True)[0] == pytest.approx(0.0, abs=1e-12)


def test_segmentation_accuracy():
    assert segmentation_accuracy([1, 0, 1, 1], [1, 1, 1, 0]) == 0.5
    assert segmentation_accuracy(np.array([0.9, 0.2, 0.6]), np.array([True, False, False])) == pytest.approx(2 / 3)
    assert math.isnan(segmentation_accuracy([], []))
    with pytest.raises(ValueError):
        segmentation_accuracy([1], [1, 0])


def test_pair_errors_camera_frame_and_aggregate():
    g = GTObject("chair", (0, 0, 1, 1), [0, 0, 3], [1, 1, 1], heading_to_rotation(0.0, UP))
    p = Object3D("chair", 0.9, [0.5, 0, 3], [1, 1, 1], heading_to_rotation(math.radians(190), UP))
    p.seg_accuracy = 0.8
    r = pair_errors(p, g, UP)
    assert r["class"] == "chair"
    assert r["centroid_error"] == pytest.approx(0.5)
    assert math.degrees(r["heading_error_rad"]) == pytest.approx(170)
    assert math.degrees(r["heading_error_sym_rad"]) == pytest.approx(10)
    # unit cubes half overlapping (the 10-degree turn of a cube changes the footprint)
    assert 0.2 < r["iou3d"] < 1 / 3 + 1e-9
    assert r["seg_accuracy"] == 0.8
    r_noup = pair_errors(p, g)  # vertical from the GT box's z column
    assert r_noup["heading_error_rad"] == pytest.approx(r["heading_error_rad"])
    # aligned pair: exact numbers
    p2 = Object3D("chair", 0.9, [0.5, 0, 3], [1, 1, 1], heading_to_rotation(0.0, UP))
    r2 = pair_errors(p2, g, UP)
    assert r2["iou3d"] == pytest.approx(1 / 3)
    assert r2["corner_error"] == pytest.approx(0.5)
    agg = aggregate_box_errors([r, r2], classes=("chair", "table"))
    c = agg["per_class"]["chair"]
    assert c["n"] == 2 and agg["per_class"]["table"] == {"n": 0}
    assert c["centroid_error"]["mean"] == pytest.approx(0.5)
    assert c["heading_error_deg"]["mean"] == pytest.approx(85)
    assert c["heading_error_sym_deg"]["mean"] == pytest.approx(5)
    assert c["iou3d"]["mean"] == pytest.approx((r["iou3d"] + 1 / 3) / 2)
    assert c["seg_accuracy"]["mean"] == 0.8 and c["seg_accuracy"]["n"] == 1
    assert agg["all"]["n"] == 2
