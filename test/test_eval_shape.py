"""Hand-computed shape metrics on unions of cuboids."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shape_detector.evaluation.shape_metrics import (
    box_relative_iou,
    gt_scale,
    sample_union_surface,
    shape_iou,
    shape_metrics,
    surface_distance,
    to_box_frame,
)
from shape_detector.geometry import rot_z
from shape_detector.types import Cuboid

I3 = np.eye(3)


def cube(x=0.0, y=0.0, z=0.0, size=(1, 1, 1), R=I3):
    return Cuboid([x, y, z], size, R)


def test_identical_sets():
    parts = [cube(), cube(0.7, 0.2, 0.1, (0.5, 2, 0.3), rot_z(0.4))]
    assert shape_iou(parts, parts) == 1.0
    assert surface_distance(parts, parts, n=2000, rng=0) == 0.0


def test_half_shifted_cube_iou_is_one_third():
    a, b = [cube(0.5, 0.5, 0.5)], [cube(1.0, 0.5, 0.5)]
    # x-range [0, 1.5] in 30 cells of 0.05: 20 centres in each cube, 10 shared -> 10/30
    assert shape_iou(a, b, resolution=30) == pytest.approx(1 / 3, abs=1e-12)
    assert shape_iou(a, b, resolution=32) == pytest.approx(1 / 3, abs=0.03)
    # explicit bounds: a larger grid does not change the answer much
    assert shape_iou(a, b, resolution=64, bounds=np.array([[-1, -1, -1], [3, 2, 2]])) == pytest.approx(1 / 3, abs=0.03)


def test_two_overlapping_cubes_equal_their_union_box():
    pred = [cube(0.5, 0.5, 0.5), cube(1.0, 0.5, 0.5)]  # union = [0, 1.5] x [0, 1] x [0, 1]
    gt = [cube(0.75, 0.5, 0.5, (1.5, 1, 1))]
    assert shape_iou(pred, gt) == 1.0
    pts = sample_union_surface(pred, 3000, rng=1)
    assert len(pts) == 3000
    lo, hi = np.array([0, 0, 0]), np.array([1.5, 1, 1])
    inside = np.all((pts > lo + 1e-9) & (pts < hi - 1e-9), axis=1)
    assert not inside.any()  # the inner faces (x = 0.5 and x = 1) were discarded
    assert np.all((pts >= lo - 1e-9) & (pts <= hi + 1e-9))
    d = surface_distance(pred, gt, n=3000, rng=2)
    assert 0.0 < d < 0.02  # only the sampling density separates the two samples


def test_area_weighted_sampling():
    pts = sample_union_surface([cube(size=(2, 1, 1))], 20000, rng=3)
    on_x_faces = np.isclose(np.abs(pts[:, 0]), 1.0)
    # x faces: 2 of total area 2 * (2 + 2 + 1) = 10
    assert on_x_faces.mean() == pytest.approx(0.2, abs=0.015)


def test_offset_parallel_plates_known_distance():
    # flat 1x1 plates 0.3 apart: common random numbers put every sample exactly above
    # its partner, so both directed distances are exactly 0.3
    a = [cube(size=(1, 1, 0))]
    b = [cube(z=0.3, size=(1, 1, 0))]
    assert surface_distance(a, b, n=1000, rng=0, normalise="none") == pytest.approx(0.3, abs=1e-12)
    assert surface_distance(a, b, n=1000, rng=0) == pytest.approx(0.3 / math.sqrt(2), abs=1e-12)
    assert gt_scale(b, "bbox_diagonal") == pytest.approx(math.sqrt(2))


def test_rotation_invariance_and_scale():
    pred = [cube(0.1, 0, 0, (1, 0.5, 0.8)), cube(0.2, 0.6, 0, (0.3, 0.3, 0.3))]
    gt = [cube(0, 0, 0, (1, 0.6, 0.8))]
    R = rot_z(0.9)
    rp = [c.transformed(R, np.array([1.0, 2.0, 3.0])) for c in pred]
    rg = [c.transformed(R, np.array([1.0, 2.0, 3.0])) for c in gt]
    d0 = surface_distance(pred, gt, n=1500, rng=5)
    d1 = surface_distance(rp, rg, n=1500, rng=5)
    assert d1 == pytest.approx(d0, rel=1e-9)
    assert gt_scale(gt) == pytest.approx(math.sqrt(1 + 0.36 + 0.64))
    assert gt_scale(rg) == pytest.approx(gt_scale(gt))


def test_empty_sets():
    assert shape_iou([], [cube()]) == 0.0
    assert math.isnan(shape_iou([], []))
    assert math.isnan(surface_distance([], [cube()], n=100, rng=0))


def test_to_box_frame():
    R = rot_z(math.pi / 2)
    center = np.array([1.0, 2.0, 0.0])
    part = Cuboid(center + R @ np.array([0.5, 0.0, 0.25]), [0.2, 0.4, 0.5], R @ rot_z(0.1))
    (q,) = to_box_frame([part], center, R)
    np.testing.assert_allclose(q.center, [0.5, 0.0, 0.25], atol=1e-12)
    np.testing.assert_allclose(q.rotation, rot_z(0.1), atol=1e-12)
    np.testing.assert_allclose(q.size, [0.2, 0.4, 0.5])
    size = np.array([3.0, 4.0, 0.0])  # diagonal 5
    (n,) = to_box_frame([part], center, R, size=size, normalise=True)
    np.testing.assert_allclose(n.center, [0.1, 0.0, 0.05], atol=1e-12)
    np.testing.assert_allclose(n.size, [0.04, 0.08, 0.1])
    with pytest.raises(ValueError):
        to_box_frame([part], center, R, normalise=True)
    m = shape_metrics([part], [part], n=200, rng=0)
    assert m == {"iou": 1.0, "surface_distance": 0.0}


def _in_box(parts_unit, centre, R, size):
    """Axis-aligned cuboids given in a box's unit cube -> the box's frame (camera frame)."""
    size = np.asarray(size, dtype=np.float64)
    return [Cuboid(centre + R @ (np.asarray(c) * size), np.asarray(s) * size, R) for c, s in parts_unit]


TABLE_UNIT = [((0, 0, 0.475), (1, 1, 0.05)), ((-0.45, -0.45, -0.025), (0.1, 0.1, 0.95))]  # top + one leg


def test_box_relative_iou_ignores_the_box_error():
    gt_box = (np.array([0.0, 0.0, 2.0]), I3, np.array([1.2, 0.8, 0.75]))
    pred_box = (np.array([0.3, -0.1, 2.2]), rot_z(0.4), np.array([1.0, 0.9, 0.85]))  # off in all 7 dof
    gt = _in_box(TABLE_UNIT, *gt_box)
    pred = _in_box(TABLE_UNIT, *pred_box)
    assert box_relative_iou(pred, pred_box, gt, gt_box) == pytest.approx(1.0)
    # the isotropic object frame still sees the box's size error: the thin top misses
    po = to_box_frame(pred, pred_box[0], pred_box[1], pred_box[2], normalise=True)
    go = to_box_frame(gt, gt_box[0], gt_box[1], gt_box[2], normalise=True)
    assert shape_iou(po, go) < 0.5


def test_box_relative_iou_hand_computed():
    box = (np.array([1.0, 2.0, 3.0]), rot_z(0.7), np.array([2.0, 1.0, 0.5]))
    full = _in_box([((0, 0, 0), (1, 1, 1))], *box)
    lower = _in_box([((0, 0, -0.25), (1, 1, 0.5))], *box)
    upper = _in_box([((0, 0, 0.25), (1, 1, 0.5))], *box)
    other = (np.zeros(3), I3, np.array([1.0, 3.0, 2.0]))
    # the grid spans the unit cube: 16 of 32 z-layers are inside the lower half
    assert box_relative_iou(lower, box, _in_box([((0, 0, 0), (1, 1, 1))], *other), other) == pytest.approx(0.5)
    assert box_relative_iou(upper, box, _in_box([((0, 0, -0.25), (1, 1, 0.5))], *other), other) == 0.0
    assert box_relative_iou(full, box, full, box) == 1.0
    assert box_relative_iou([], box, full, box) == 0.0
    assert math.isnan(box_relative_iou([], box, [], box))
    with pytest.raises(ValueError, match="positive"):
        box_relative_iou(full, (box[0], box[1], np.array([1.0, 0.0, 1.0])), full, box)


def test_nearest_distances_are_the_brute_force_ones():
    from shape_detector.evaluation.shape_metrics import nearest_distances

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(700, 3)), rng.normal(size=(500, 3))
    b[:20] = a[:20]  # coincident points: exactly 0
    brute = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min(1)
    d = nearest_distances(a, b)
    assert np.allclose(d, brute, rtol=0, atol=1e-12) and np.all(d[:20] == 0.0)
    assert np.all(np.isinf(nearest_distances(a, b[:0]))) and nearest_distances(a[:0], b).shape == (0,)
