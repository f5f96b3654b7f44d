"""Hand-computed cases for the exact oriented 3D IoU and its helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shape_detector.box_iou import (
    box2d_iou,
    box2d_iou_matrix,
    box3d_iou,
    box3d_iou_grid,
    clip_convex,
    iou_matrix,
    polygon_area,
)
from shape_detector.geometry import heading_to_rotation, rot_z
from shape_detector.types import Cuboid

I3 = np.eye(3)
UP_CAM = np.array([0.0, -1.0, 0.0])


def iou(ca, sa, ra, cb, sb, rb, up=None, **kw):
    return box3d_iou(np.array(ca, float), np.array(sa, float), ra, np.array(cb, float), np.array(sb, float), rb, up, **kw)


def test_identical_boxes():
    R = rot_z(0.7)
    assert iou([1, 2, 3], [2, 1, 0.5], R, [1, 2, 3], [2, 1, 0.5], R) == pytest.approx(1.0, abs=1e-12)


def test_disjoint_boxes():
    assert iou([0, 0, 0], [1, 1, 1], I3, [3, 0, 0], [1, 1, 1], I3) == 0.0
    # footprints overlap but heights do not
    assert iou([0, 0, 0], [1, 1, 1], I3, [0, 0, 1.5], [1, 1, 1], I3) == 0.0
    # touching faces: zero volume
    assert iou([0, 0, 0], [1, 1, 1], I3, [1, 0, 0], [1, 1, 1], I3) == 0.0


def test_half_overlap():
    # 2x2x2 cubes shifted by 1: intersection 1*2*2 = 4, union 8 + 8 - 4 = 12
    assert iou([0, 0, 0], [2, 2, 2], I3, [1, 0, 0], [2, 2, 2], I3) == pytest.approx(1 / 3, abs=1e-12)
    # shifted in x and y: intersection 1*1*2 = 2, union 14
    assert iou([0, 0, 0], [2, 2, 2], I3, [1, 1, 0], [2, 2, 2], I3) == pytest.approx(2 / 14, abs=1e-12)


def test_rotated_45_squares():
    # two 2x2 squares around the same centre, one turned 45 deg: a regular octagon of
    # inradius 1, area 8 tan(pi/8) = 8 (sqrt2 - 1); equal heights -> IoU = 1/sqrt(2)
    v = iou([0, 0, 0], [2, 2, 1], I3, [0, 0, 0], [2, 2, 1], rot_z(math.pi / 4))
    assert v == pytest.approx(1 / math.sqrt(2), abs=1e-12)
    # the intersection polygon itself
    sq = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], float)
    poly = clip_convex(sq, sq @ rot_z(math.pi / 4)[:2, :2].T)
    assert len(poly) == 8
    assert abs(polygon_area(poly)) == pytest.approx(8 * (math.sqrt(2) - 1), abs=1e-12)


def test_containment():
    # 1x1x1 inside 2x2x2 (rotated inside): IoU = 1/8
    assert iou([0, 0, 0], [2, 2, 2], I3, [0.2, -0.1, 0.3], [1, 1, 1], rot_z(0.3)) == pytest.approx(1 / 8, abs=1e-12)


def test_different_heights():
    # same 2x2 footprint; A spans z in [-1, 1] (vol 8), B spans [0.25, 1.25] (vol 4)
    # intersection 4 * 0.75 = 3, union 9
    assert iou([0, 0, 0], [2, 2, 2], I3, [0, 0, 0.75], [2, 2, 1], I3) == pytest.approx(1 / 3, abs=1e-12)


def test_camera_frame_with_up():
    # level camera: up = -y. Same 'different heights' case in camera coordinates.
    R = heading_to_rotation(0.4, UP_CAM)
    a = iou([0, 0, 3], [2, 2, 2], R, [0, -0.75, 3], [2, 2, 1], R, up=UP_CAM)
    b = iou([0, 0, 3], [2, 2, 2], R, [0, -0.75, 3], [2, 2, 1], R)  # vertical from rot_a
    assert a == pytest.approx(1 / 3, abs=1e-12)
    assert b == pytest.approx(1 / 3, abs=1e-12)
    # tilted camera: still exact
    up = np.array([0.0, -0.9, -0.3])
    Ra, Rb = heading_to_rotation(0.0, up), heading_to_rotation(math.pi / 4, up)
    assert iou([0, 0, 3], [2, 2, 1], Ra, [0, 0, 3], [2, 2, 1], Rb, up=up) == pytest.approx(1 / math.sqrt(2), abs=1e-9)


def test_other_axis_vertical():
    # box B's y column is the vertical: its height is size[1]
    Rb = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # columns: x, z, -y
    v = iou([0, 0, 0], [2, 2, 2], I3, [0, 0, 0.75], [2, 1, 2], Rb)
    assert v == pytest.approx(1 / 3, abs=1e-12)


def test_grid_fallback_matches_exact_and_is_used_for_tilted_boxes():
    rng = np.random.default_rng(0)
    for _ in range(5):
        ca, cb = rng.normal(0, 0.3, 3), rng.normal(0, 0.3, 3)
        sa, sb = rng.uniform(0.5, 1.5, 3), rng.uniform(0.5, 1.5, 3)
        Ra, Rb = rot_z(rng.uniform(-3, 3)), rot_z(rng.uniform(-3, 3))
        exact = box3d_iou(ca, sa, Ra, cb, sb, Rb)
        approx = box3d_iou_grid(ca, sa, Ra, cb, sb, Rb, resolution=48)
        assert approx == pytest.approx(exact, abs=0.02)
    c = math.cos(0.5)
    tilt = np.array([[1, 0, 0], [0, c, -math.sin(0.5)], [0, math.sin(0.5), c]])
    with pytest.raises(ValueError):
        iou([0, 0, 0], [1, 1, 1], I3, [0, 0, 0], [1, 1, 1], tilt, fallback=False)
    v = iou([0, 0, 0], [1, 1, 1], I3, [0, 0, 0], [1, 1, 1], tilt)
    assert 0.5 < v < 1.0


def test_iou_matrix_and_2d():
    boxes = [Cuboid([0, 0, 0], [2, 2, 2], I3), Cuboid([1, 0, 0], [2, 2, 2], I3), Cuboid([9, 0, 0], [1, 1, 1], I3)]
    m = iou_matrix(boxes, boxes[:2])
    assert m.shape == (3, 2)
    np.testing.assert_allclose(m, [[1, 1 / 3], [1 / 3, 1], [0, 0]], atol=1e-12)
    assert box2d_iou((0, 0, 2, 2), (1, 1, 3, 3)) == pytest.approx(1 / 7)
    assert box2d_iou((0, 0, 2, 2, "chair"), (0, 0, 2, 2)) == 1.0
    assert box2d_iou((0, 0, 1, 1), (1, 0, 2, 1)) == 0.0


def test_box2d_iou_matrix_equals_the_pairwise_iou():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 100, (12, 4))
    b = rng.uniform(0, 100, (9, 5))  # a fifth item (a class, a score) is ignored
    a[:, 2:] = a[:, :2] + rng.uniform(-5, 50, (12, 2))  # some degenerate, inverted boxes
    b[:, 2:4] = b[:, :2] + rng.uniform(-5, 50, (9, 2))
    m = box2d_iou_matrix(list(a), list(b))
    assert m == pytest.approx(np.array([[box2d_iou(x, y) for y in b] for x in a]), abs=1e-12)
    assert box2d_iou_matrix([(0, 0, 2, 2)], [(1, 1, 3, 3)])[0, 0] == pytest.approx(1 / 7)
    assert box2d_iou_matrix([], [(0, 0, 1, 1)]).shape == (0, 1)
