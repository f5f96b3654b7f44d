"""Free-space carving of a frame's boxes together (:func:`carve_all`) gives what carving each
box alone gives, and the measured points the occupancy test counts are exactly those of a
plain back-projection of the box's image rectangle."""

from __future__ import annotations

import copy
import functools

import numpy as np

from shape_detector.frustum import pixel_points
from shape_detector.geometry import box_corners, project_points, upright_rotation
from shape_detector.postprocess.free_space import _box_points, carve_all, carve_free_space
from shape_detector.types import Cuboid, Object3D
from toy_scenes import placed_box_scene

SIZE = np.array([0.53, 1.00, 1.17])


def _scene():
    """The dresser scene of test_free_space: camera on the box's -x / -y side, 12 deg pitch."""
    return placed_box_scene("dresser", SIZE, 0.25, 2.6, 0.35, 12.0, 1.3)


def _object(frame, centre, R, lo, hi, name: str = "dresser", shift=(0.0, 0.0, 0.0)) -> Object3D:
    """A box spanning [lo, hi] in the frame of (centre, R), moved by ``shift`` (camera frame,
    metres), its points the dresser's pixels, with one primitive filling it."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = centre + R @ (0.5 * (lo + hi)) + np.asarray(shift)
    pix = np.flatnonzero(frame.instance_mask.ravel() == 1)
    return Object3D(name, 1.0, c, hi - lo, R, primitives=[Cuboid(c, hi - lo, R)],
                    pixel_index=pix, seg_labels=np.ones(pix.size, dtype=bool))


def test_carving_boxes_together_equals_carving_each_alone():
    frame, centre, R = _scene()
    half = SIZE / 2
    no_labels = _object(frame, centre, R, -half, half + [0.10, 0.0, 0.0])
    no_labels.seg_labels = None
    objects = [
        _object(frame, centre, R, -half, half + [0.10, 0.0, 0.08]),  # grown on hidden sides and top
        _object(frame, centre, R, -half - [0.15, 0.12, 0.0], half),  # grown towards the camera
        _object(frame, centre, R, -half, half),  # the true box
        _object(frame, centre, R, -half, half + [0.0, 0.0, 0.10], name="sofa"),  # top not carved
        _object(frame, centre, R, -half - [0.15, 0.12, 0.0], half, name="chair"),  # not carved
        no_labels,
        # behind the camera, outside the image, and a large box reaching behind the camera
        _object(frame, centre, R, -half, half, shift=(0.0, 0.0, -2.0 * centre[2])),
        _object(frame, centre, R, -half, half, shift=(8.0, 0.0, 0.0)),
        _object(frame, centre, R, -half - [1.5, 1.5, 0.0], half + [0.2, 0.2, 0.0]),
    ]
    points = functools.partial(pixel_points, frame.depth, frame.K)
    sizes = [o.size.copy() for o in objects]
    alone = [carve_free_space(copy.deepcopy(o), frame.depth, frame.K, points, min_prob=0.5) for o in objects]
    together = carve_all(objects, frame.depth, frame.K, points, min_prob=0.5)
    assert all(t is o for t, o in zip(together, objects))  # in place
    for a, t in zip(alone, together):
        np.testing.assert_allclose(t.center, a.center, rtol=0, atol=1e-12)
        np.testing.assert_allclose(t.size, a.size, rtol=0, atol=1e-12)
        np.testing.assert_allclose(t.primitives[0].size, a.primitives[0].size, rtol=0, atol=1e-12)
        np.testing.assert_allclose(t.primitives[0].center, a.primitives[0].center, rtol=0, atol=1e-12)
    carved = [not np.allclose(o.size, s) for o, s in zip(together, sizes)]
    assert carved[0] and carved[1], carved
    assert not any(carved[4:8]), carved  # chair, no labels, behind the camera, outside the image


def test_the_same_object_twice_is_carved_twice_in_turn():
    frame, centre, R = _scene()
    half = SIZE / 2
    points = functools.partial(pixel_points, frame.depth, frame.K)
    obj = _object(frame, centre, R, -half - [0.15, 0.12, 0.0], half)
    twice = copy.deepcopy(obj)
    carve_free_space(twice, frame.depth, frame.K, points)
    carve_free_space(twice, frame.depth, frame.K, points)
    carve_all([obj, obj], frame.depth, frame.K, points)
    np.testing.assert_allclose(obj.size, twice.size, rtol=0, atol=1e-12)


def _reference_box_points(c, R, half, depth, K, max_pixels, lower, upper) -> np.ndarray:
    """Every valid pixel of the box's strided image rectangle back-projected with
    :func:`pixel_points`, in the box frame, then kept within [lower, upper]: (3, n)."""
    h, w = depth.shape
    corners = box_corners(c, 2.0 * half, R)
    if np.any(corners[:, 2] <= 0.05):
        return np.zeros((3, 0))
    uv = project_points(corners, K)
    u0, u1 = int(np.clip(np.floor(uv[:, 0].min()), 0, w)), int(np.clip(np.ceil(uv[:, 0].max()) + 1, 0, w))
    v0, v1 = int(np.clip(np.floor(uv[:, 1].min()), 0, h)), int(np.clip(np.ceil(uv[:, 1].max()) + 1, 0, h))
    if u1 <= u0 or v1 <= v0:
        return np.zeros((3, 0))
    s = max(1, int(np.ceil(np.sqrt((u1 - u0) * (v1 - v0) / max(max_pixels, 1)))))
    vv, uu = np.mgrid[v0:v1:s, u0:u1:s]
    cam = pixel_points(depth, K, (vv * w + uu).ravel())
    with np.errstate(invalid="ignore"):
        cam = cam[np.isfinite(cam[:, 2]) & (cam[:, 2] > 0)]
    q = (cam - c) @ R
    return q[np.all((q >= lower) & (q <= upper), axis=1)].T


def test_box_points_are_exactly_those_of_a_plain_back_projection():
    frame, centre, R = _scene()
    depth = frame.depth.copy()  # float32, with every kind of invalid pixel
    rng = np.random.default_rng(0)
    for bad in (np.nan, np.inf, -np.inf, 0.0, -1.0):
        depth.ravel()[rng.choice(depth.size, 2000, replace=False)] = bad
    half = SIZE / 2 + 0.1
    # a box the floor cuts through: floor points reach nearly to both ends of its depth range
    R_cu = upright_rotation(frame.up)
    on_floor = (R_cu @ np.array([-1.0, 3.0, -1.3]), R_cu, np.array([0.6, 0.6, 0.03]))
    cases = [
        (*on_floor, -on_floor[2], on_floor[2]),
        (centre, R, half, -half, half),
        (centre, R, half, -half + [0.3, 0.0, 0.2], half - [0.0, 0.4, 0.0]),  # a part of the box
        (centre, R, half, np.full(3, -50.0), np.full(3, 50.0)),  # the whole rectangle
        (centre, 1.01 * R, half, -half, half),  # not a rotation: no depth-range cut
        (centre + [0.0, 0.0, 2.0], R, half + 1.0, -half, half),
        (centre * [1.0, 1.0, -1.0], R, half, -half, half),  # behind the camera
        (np.array([0.0, 0.0, 0.5]), R, np.array([1.0, 1.0, 1.0]), -np.ones(3), np.ones(3)),  # reaching behind
    ]
    for depth_map in (depth, depth.astype(np.float64)):
        for c, rot, h, lower, upper in cases:
            for max_pixels in (6000, 500):
                got = _box_points(c, rot, h, depth_map, frame.K, max_pixels, lower, upper)
                want = _reference_box_points(c, rot, h, depth_map, frame.K, max_pixels, lower, upper)
                assert got.shape == want.shape
                np.testing.assert_array_equal(got, want)
