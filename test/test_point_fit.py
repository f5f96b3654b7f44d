"""Growing boxes to their segmented points (shape_detector.postprocess.point_fit)."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.geometry import rot_z
from shape_detector.postprocess.point_fit import MIN_POINTS, grow_all_to_points, grow_to_points
from shape_detector.types import Cuboid, Object3D


def _scene(points: np.ndarray, W: int = 100):
    """Put camera-frame points into a 'back-projected depth' grid; return its lookup (flat
    pixel indices -> points, as ``pixel_points``) and the flat pixel indices of the points."""
    n = len(points)
    H = n // W + 2
    grid = np.full((H * W, 3), np.nan)
    idx = np.arange(n) + W  # first row stays invalid
    grid[idx] = points
    return (lambda flat: grid[flat]), idx


def _object(center, size, rotation, idx, fg=None, prims=()) -> Object3D:
    return Object3D(
        "dresser", 0.9, np.asarray(center, float), np.asarray(size, float), rotation,
        primitives=list(prims), pixel_index=idx, seg_labels=np.ones(len(idx), bool) if fg is None else fg,
    )


def _grid_points(lo, hi, n=2000, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, 3))


def test_box_narrower_than_its_points_grows_to_their_quantiles():
    R = rot_z(0.4)
    c_true = np.array([0.2, 0.1, 3.0])
    local = _grid_points([-0.5, -0.3, -0.4], [0.5, 0.3, 0.4])  # uniform in a 1.0 x 0.6 x 0.8 box
    grid, idx = _scene(c_true + local @ R.T)
    # predicted: right size on x and z, 0.4 m wide on y and shifted 0.1 m along x
    obj = _object(c_true + R @ np.array([0.1, 0.0, 0.0]), [1.0, 0.4, 0.8], R, idx)
    out = grow_to_points(obj, grid, quantile=0.05)
    # quantiles of U(-a, a) at 5 % / 95 %: +-0.9 a
    # x: the box's [-0.4, 0.6] (about the true centre) grows to cover the quantile at -0.45
    np.testing.assert_allclose(out.size, [1.05, 0.54, 0.8], atol=0.02)
    local_c = R.T @ (out.center - c_true)
    assert local_c[0] == pytest.approx((-0.45 + 0.6) / 2, abs=0.01)
    assert local_c[1] == pytest.approx(0.0, abs=0.02)
    np.testing.assert_allclose(out.rotation, R)  # yaw untouched


def test_box_covering_its_points_is_unchanged():
    R = rot_z(-0.3)
    c = np.array([0.0, 0.5, 2.5])
    grid, idx = _scene(c + _grid_points([-0.3] * 3, [0.3] * 3) @ R.T)
    obj = _object(c, [0.8, 0.8, 0.8], R, idx, prims=[Cuboid(c, [0.2, 0.2, 0.2], R)])
    out = grow_to_points(obj, grid, 0.15)
    np.testing.assert_allclose(out.center, c)
    np.testing.assert_allclose(out.size, [0.8, 0.8, 0.8])
    np.testing.assert_allclose(out.primitives[0].size, [0.2, 0.2, 0.2])


def test_stray_points_below_the_quantile_do_not_stretch_the_box():
    R = np.eye(3)
    c = np.array([0.0, 0.0, 3.0])
    body = _grid_points([-0.25] * 3, [0.25] * 3, n=900)
    stray = np.array([[2.0, 0.0, 0.0]] * 100)  # 10 % mis-segmented points 2 m away
    grid, idx = _scene(c + np.vstack([body, stray]))
    out = grow_to_points(_object(c, [0.5, 0.5, 0.5], R, idx), grid, 0.15)
    np.testing.assert_allclose(out.size, [0.5, 0.5, 0.5])


def test_primitives_stretch_with_the_box():
    R = np.eye(3)
    c = np.array([0.0, 0.0, 3.0])
    grid, idx = _scene(c + _grid_points([-1.0, -0.25, -0.25], [1.0, 0.25, 0.25]))
    prim = Cuboid(c + np.array([0.25, 0.0, 0.0]), np.array([0.5, 0.5, 0.5]), R)
    out = grow_to_points(_object(c, [1.0, 0.5, 0.5], R, idx, prims=[prim]), grid, 0.02)
    ratio = out.size[0] / 1.0
    assert ratio == pytest.approx(1.92, abs=0.05)  # x grows to the 2 % / 98 % quantiles
    p = out.primitives[0]
    np.testing.assert_allclose(p.size, [0.5 * ratio, 0.5, 0.5], rtol=1e-6)
    np.testing.assert_allclose(p.center - out.center, [0.25 * ratio, 0.0, 0.0], atol=1e-6)


def test_few_or_background_points_leave_the_box_alone():
    R = np.eye(3)
    c = np.array([0.0, 0.0, 3.0])
    pts = c + _grid_points([-1.0] * 3, [1.0] * 3, n=200)
    grid, idx = _scene(pts)
    fg = np.zeros(len(idx), bool)
    fg[: MIN_POINTS - 1] = True
    obj = _object(c, [0.5, 0.5, 0.5], R, idx, fg=fg)
    assert np.allclose(grow_to_points(obj, grid, 0.15).size, 0.5)
    none = Object3D("chair", 0.5, c, [0.5, 0.5, 0.5], R)  # no pixel_index / seg_labels
    assert np.allclose(grow_to_points(none, grid, 0.15).size, 0.5)
    objs = [_object(c, [0.5, 0.5, 0.5], R, idx)]
    assert np.allclose(grow_all_to_points(objs, grid, 0.0)[0].size, 0.5)  # 0 = off


def test_min_prob_leaves_out_unsure_points_that_leaked_into_the_mask():
    """A neighbour's points segmented as foreground, but less surely (0.6), stretch the box
    at the default threshold and not with ``min_prob=0.8``; without ``seg_prob`` the labels
    decide."""
    R = np.eye(3)
    c = np.array([0.0, 0.0, 3.0])
    own = _grid_points([-0.5, -0.3, -0.4], [0.5, 0.3, 0.4], n=1400, seed=1)
    leak = _grid_points([0.5, -0.3, -0.4], [1.1, 0.3, 0.4], n=600, seed=2)  # a neighbour on +x
    grid, idx = _scene(c + np.concatenate([own, leak]))
    prob = np.r_[np.full(len(own), 0.95), np.full(len(leak), 0.6)]

    def obj() -> Object3D:
        o = _object(c, [1.0, 0.6, 0.8], R, idx, fg=prob > 0.5)
        o.seg_prob = prob
        return o

    grown = grow_to_points(obj(), grid, 0.15)  # 30% of the mask lies beyond +x
    assert grown.size[0] > 1.2
    kept = grow_to_points(obj(), grid, 0.15, min_prob=0.8)
    np.testing.assert_allclose(kept.size, [1.0, 0.6, 0.8])
    np.testing.assert_allclose(kept.center, c)
    no_prob = obj()
    no_prob.seg_prob = None
    assert grow_to_points(no_prob, grid, 0.15, min_prob=0.8).size[0] == pytest.approx(grown.size[0])
    # too few sure points: unchanged
    few = obj()
    few.seg_prob = np.r_[np.full(MIN_POINTS - 1, 0.95), np.full(len(prob) - MIN_POINTS + 1, 0.6)]
    np.testing.assert_allclose(grow_to_points(few, grid, 0.15, min_prob=0.8).size, [1.0, 0.6, 0.8])
