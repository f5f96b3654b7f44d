"""Free-space carving: boxes shrink out of space the depth map sees through, and only there."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from shape_detector.postprocess.free_space import FLAT_TOPPED, CarveParams, carve_free_space
from shape_detector.frustum import pixel_points
from toy_scenes import chair_parts, placed_box_scene, toy_scene
from shape_detector.types import Cuboid, Object3D

SIZE = np.array([0.53, 1.00, 1.17])


def _dresser(yaw: float = 0.35):
    frame, centre, rotation = placed_box_scene("dresser", SIZE, 0.25, 2.6, yaw, 12.0, 1.3)
    return frame, centre, rotation


def _object(frame, centre, rotation, lo, hi, iid: int = 1) -> Object3D:
    """An Object3D spanning [lo, hi] in the box frame of (centre, rotation), its points the
    instance's pixels, with one primitive filling the box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = centre + rotation @ (0.5 * (lo + hi))
    pix = np.flatnonzero(frame.instance_mask.ravel() == iid)
    return Object3D("dresser", 1.0, c, hi - lo, rotation, primitives=[Cuboid(c, hi - lo, rotation)],
                    pixel_index=pix, seg_labels=np.ones(pix.size, dtype=bool))


def _carve(frame, obj, depth=None):
    depth = frame.depth if depth is None else depth
    return carve_free_space(obj, depth, frame.K, functools.partial(pixel_points, depth, frame.K))


#: the camera sees the box's -x and -y faces and its top; +x and +y face away
HIDDEN_GROWTH = (np.zeros(3), np.array([0.10, 0.0, 0.08]))


def test_a_box_grown_on_its_hidden_sides_and_top_is_carved_back():
    frame, centre, R = _dresser()
    half = SIZE / 2
    assert np.all(((-centre) @ R)[:2] < -half[:2])  # the camera is on the -x / -y side
    # 10 cm too deep at +x (hidden but for a sliver past the -y edge), 8 cm too tall (seen
    # against the background)
    obj = _object(frame, centre, R, -half - HIDDEN_GROWTH[0], half + HIDDEN_GROWTH[1])
    _carve(frame, obj)
    hi = R.T @ (obj.center - centre) + obj.size / 2
    assert abs(hi[2] - half[2]) <= 0.025, hi  # within one 2 cm layer
    assert half[0] - 0.02 <= hi[0] <= half[0] + 0.06, hi  # at least 4 of the 10 cm
    np.testing.assert_allclose(hi[1], half[1], atol=1e-9)
    # the primitive stretched with the box
    np.testing.assert_allclose(obj.primitives[0].size, obj.size, atol=1e-9)
    np.testing.assert_allclose(obj.primitives[0].center, obj.center, atol=1e-9)


def test_the_true_box_is_left_alone():
    frame, centre, R = _dresser()
    obj = _object(frame, centre, R, -SIZE / 2, SIZE / 2)
    _carve(frame, obj)
    assert np.all(obj.size >= SIZE - 0.02 - 1e-9), obj.size
    assert np.linalg.norm(obj.center - centre) <= 0.015


def test_the_top_is_carved_only_for_flat_topped_classes():
    frame, centre, R = _dresser()
    half = SIZE / 2
    grown = (-half, half + [0.0, 0.0, 0.10])
    tops = {}
    for name in ("dresser", "sofa"):
        obj = _object(frame, centre, R, *grown)
        obj.class_name = name
        _carve(frame, obj)
        tops[name] = (R.T @ (obj.center - centre) + obj.size / 2)[2]
    assert "dresser" in FLAT_TOPPED and "sofa" not in FLAT_TOPPED
    assert tops["dresser"] <= half[2] + 0.025
    assert tops["sofa"] == pytest.approx(half[2] + 0.10)


def test_chairs_are_not_carved():
    frame, centre, R = _dresser()
    half = SIZE / 2
    obj = _object(frame, centre, R, -half - [0.15, 0.12, 0.0], half)
    obj.class_name = "chair"
    size0 = obj.size.copy()
    _carve(frame, obj)
    np.testing.assert_allclose(obj.size, size0)


def test_a_box_grown_towards_the_camera_is_carved_back():
    frame, centre, R = _dresser()
    half = SIZE / 2
    obj = _object(frame, centre, R, -half - [0.15, 0.12, 0.0], half)
    _carve(frame, obj)
    # back to within the seen-through margin (3 cm + 1 cm per metre of depth, here ~5.7 cm)
    lo = R.T @ (obj.center - centre) - obj.size / 2
    assert np.all(lo[:2] >= -half[:2] - 0.06) and np.all(lo[:2] <= -half[:2] + 0.02), lo


def test_occluded_space_is_not_carved():
    frame, centre, R = _dresser()
    # everything but the object is a near occluder: nothing around the box is seen through
    depth = frame.depth.copy()
    depth[frame.instance_mask != 1] = 0.5
    half = SIZE / 2
    obj = _object(frame, centre, R, -half - HIDDEN_GROWTH[0], half + HIDDEN_GROWTH[1])
    size0 = obj.size.copy()
    _carve(frame, obj, depth)
    np.testing.assert_allclose(obj.size, size0)


def test_air_inside_the_object_is_not_carved_past_its_points():
    # a chair's geometry (chairs themselves are not carved, so it is labelled a sofa here): the
    # camera sees through its legs and under its seat, but its box is bounded by its own
    # points (seat, back, legs) and the layer's top rows are not seen past
    frame = toy_scene([("chair", chair_parts(0.3, 2.2))], cam_height=1.3)
    g = frame.objects[0]
    obj = Object3D("sofa", 1.0, g.center, g.size, g.rotation,
                   pixel_index=np.flatnonzero(frame.instance_mask.ravel() == g.instance_id),
                   seg_labels=None)
    obj.seg_labels = np.ones(obj.pixel_index.size, dtype=bool)
    _carve(frame, obj)
    assert np.all(obj.size >= g.size - 0.03), (obj.size, g.size)


def test_too_few_points_or_no_labels_leave_the_box_unchanged():
    frame, centre, R = _dresser()
    half = SIZE / 2
    obj = _object(frame, centre, R, -half - [0.10, 0.0, 0.0], half)
    obj.seg_labels = np.zeros_like(obj.seg_labels)
    _carve(frame, obj)
    np.testing.assert_allclose(obj.size, SIZE + [0.10, 0.0, 0.0])
    obj.seg_labels = None
    _carve(frame, obj)
    np.testing.assert_allclose(obj.size, SIZE + [0.10, 0.0, 0.0])


def test_max_frac_bounds_the_carving():
    frame, centre, R = _dresser()
    half = SIZE / 2
    obj = _object(frame, centre, R, -half - [0.40, 0.0, 0.0], half)
    p = CarveParams(max_frac=0.1)
    carve_free_space(obj, frame.depth, frame.K, functools.partial(pixel_points, frame.depth, frame.K), p)
    # at most 10% of the 0.93 m length, in whole 2 cm steps
    assert obj.size[0] >= 0.93 - 0.1 * 0.93 - 1e-9
    assert obj.size[0] < 0.93


def test_unsure_leaked_points_do_not_hold_a_face_out_with_min_prob():
    """Floor pixels beyond the box's far face leak into the mask (probability 0.6): at the
    mask's own threshold they count as the object's points and hold out its 10 cm too deep
    +x face; with ``min_prob=0.8`` only the sure points do, and the face is carved back."""
    frame, centre, R = _dresser()
    half = SIZE / 2
    obj = _object(frame, centre, R, -half, half + [0.10, 0.0, 0.0])
    own = obj.pixel_index
    pts = pixel_points(frame.depth, frame.K, np.arange(frame.depth.size))
    with np.errstate(invalid="ignore"):
        local = (pts - centre) @ R
        beyond = (frame.instance_mask.ravel() == 0) & (local[:, 0] > half[0] + 0.15) & (local[:, 0] < half[0] + 0.6)
    leak = np.flatnonzero(beyond)[: own.size // 10]
    assert leak.size > 0.05 * own.size
    prob = np.r_[np.full(own.size, 0.95), np.full(leak.size, 0.6)]

    def obj_() -> Object3D:
        return Object3D("dresser", 1.0, obj.center, obj.size, R, primitives=list(obj.primitives),
                        pixel_index=np.r_[own, leak], seg_labels=prob > 0.5, seg_prob=prob)

    points = functools.partial(pixel_points, frame.depth, frame.K)
    held = carve_free_space(obj_(), frame.depth, frame.K, points)
    carved = carve_free_space(obj_(), frame.depth, frame.K, points, min_prob=0.8)
    far = lambda o: (R.T @ (o.center - centre) + o.size / 2)[0]  # noqa: E731
    assert far(held) == pytest.approx(half[0] + 0.10)
    assert far(carved) <= half[0] + 0.06


BOOKSHELF = np.array([0.40, 1.00, 1.90])


def _bookshelf(distance: float = 3.4):
    """A 1.9 m bookshelf seen by a camera 1.3 m high: from below its top."""
    frame, centre, R = placed_box_scene("bookshelf", BOOKSHELF, 0.25, distance, 0.35, 12.0, 1.3)
    return frame, centre, R, tuple(float(v) for v in frame.objects[0].box2d)


def _tall_object(frame, centre, R, box2d, extra_top: float) -> Object3D:
    half = BOOKSHELF / 2
    obj = _object(frame, centre, R, -half, half + [0.0, 0.0, extra_top])
    obj.class_name = "bookshelf"
    obj.box2d = box2d
    return obj


def _top(obj, centre, R) -> float:
    return float((R.T @ (obj.center - centre) + obj.size / 2)[2])


def test_a_top_seen_from_below_is_capped_at_the_points_when_it_is_in_the_image():
    frame, centre, R, box2d = _bookshelf()
    half = BOOKSHELF / 2
    assert ((-centre) @ R)[2] < half[2]  # the camera is below the top: it cannot see past it
    assert box2d[1] > 2  # the top edge is inside the image
    obj = _carve(frame, _tall_object(frame, centre, R, box2d, 0.15))
    assert half[2] - 0.01 <= _top(obj, centre, R) <= half[2] + 0.025  # the front edge's height + 1 cm
    np.testing.assert_allclose(obj.primitives[0].size, obj.size, atol=1e-9)  # primitives stretch with it
    # the true box keeps its top
    obj = _carve(frame, _tall_object(frame, centre, R, box2d, 0.0))
    assert _top(obj, centre, R) == pytest.approx(half[2], abs=0.02)


def test_the_top_cap_needs_the_top_in_the_image_a_flat_topped_class_and_can_be_turned_off():
    frame, centre, R, box2d = _bookshelf()
    half = BOOKSHELF / 2
    cut = (box2d[0], 0.0, box2d[2], box2d[3])  # as if the image's top border cut the object
    assert _top(_carve(frame, _tall_object(frame, centre, R, cut, 0.15)), centre, R) == pytest.approx(half[2] + 0.15)
    sofa = _tall_object(frame, centre, R, box2d, 0.15)
    sofa.class_name = "sofa"
    assert _top(_carve(frame, sofa), centre, R) == pytest.approx(half[2] + 0.15)
    off = carve_free_space(_tall_object(frame, centre, R, box2d, 0.15), frame.depth, frame.K,
                           functools.partial(pixel_points, frame.depth, frame.K), CarveParams(top_cap_quantile=1.0))
    assert _top(off, centre, R) == pytest.approx(half[2] + 0.15)
