"""Snapping primitives to their box (shape_detector.postprocess.primitive_snap)."""

import numpy as np

from shape_detector.geometry import heading_to_rotation, rot_z
from shape_detector.postprocess.primitive_snap import snap_in_box, snap_primitives
from shape_detector.types import Cuboid, Object3D

BOX = np.array([1.2, 0.8, 0.75])  # a table: l, w, h (m)


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def test_a_top_sticking_out_is_clipped_to_the_box():
    # a 4 cm top whose upper face is 2 cm above the box top, and 10 cm too long
    c, s, r, keep = snap_in_box([[0.05, 0.0, 0.375]], [[1.3, 0.8, 0.04]], [np.eye(3)], BOX)
    assert keep.tolist() == [True]
    np.testing.assert_allclose(s[0], [1.2, 0.8, 0.02], atol=1e-12)
    np.testing.assert_allclose(c[0], [0.0, 0.0, 0.365], atol=1e-12)
    lo, hi = c[0] - s[0] / 2, c[0] + s[0] / 2
    assert np.all(lo >= -BOX / 2 - 1e-12) and np.all(hi <= BOX / 2 + 1e-12)


def test_a_slightly_tilted_and_axis_swapped_leg_becomes_box_aligned():
    # a leg (5 x 5 x 70 cm) described with its long axis as the cuboid's first axis,
    # tilted 10 degrees: cuboid x ~ box z
    swap = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # columns: box z, box y, box x
    r0 = _rot_x(np.radians(10)) @ swap
    c, s, r, keep = snap_in_box([[0.5, 0.3, -0.02]], [[0.7, 0.05, 0.05]], [r0], BOX)
    assert keep[0]
    np.testing.assert_allclose(r[0], np.eye(3))
    np.testing.assert_allclose(s[0], [0.05, 0.05, 0.7], atol=1e-12)
    np.testing.assert_allclose(c[0], [0.5, 0.3, -0.02], atol=1e-12)


def test_a_strongly_tilted_primitive_is_left_alone_and_one_outside_is_dropped():
    tilted = rot_z(np.radians(40))
    c, s, r, keep = snap_in_box([[0.0, 0.0, 0.0], [0.0, 0.0, 0.6]], [[0.3, 0.3, 0.3], [0.2, 0.2, 0.1]],
                                [tilted, np.eye(3)], BOX)
    assert keep.tolist() == [True, False]
    np.testing.assert_allclose(r[0], tilted)
    np.testing.assert_allclose(s[0], [0.3, 0.3, 0.3])


def test_snap_primitives_works_in_the_camera_frame_and_keeps_something():
    up = np.array([0.0, -np.cos(0.3), np.sin(0.3)])
    R = heading_to_rotation(0.7, up)
    centre = np.array([0.4, 0.2, 3.0])
    inside = Cuboid(centre + R @ np.array([0.0, 0.0, 0.365]), np.array([1.2, 0.8, 0.06]), R)  # 2 cm out at the top
    out_obj = Object3D("table", 0.9, centre, BOX.copy(), R, primitives=[inside])
    (prim,) = snap_primitives([out_obj])[0].primitives
    local_top = (prim.center - centre) @ R + prim.size / 2
    assert abs(local_top[2] - 0.375) < 1e-9 and abs(prim.size[2] - 0.04) < 1e-9
    np.testing.assert_allclose(prim.rotation, R, atol=1e-12)
    # nothing inside the box: the primitives are kept as predicted rather than emptied
    far = Cuboid(centre + R @ np.array([0.0, 0.0, 2.0]), np.array([0.1, 0.1, 0.1]), R)
    obj = Object3D("table", 0.9, centre, BOX.copy(), R, primitives=[far])
    bare = Object3D("table", 0.9, centre, BOX.copy(), R)
    assert snap_primitives([obj, bare]) == [obj, bare]
    assert len(obj.primitives) == 1 and obj.primitives[0] is far and bare.primitives == []
    assert snap_primitives([]) == []


def test_a_frame_of_objects_snaps_each_to_its_own_box():
    rng = np.random.default_rng(4)
    up = np.array([0.0, -np.cos(0.2), np.sin(0.2)])

    def make():
        objs = []
        for k in range(4):
            R = heading_to_rotation(0.5 * k, up)
            centre = np.array([k - 1.5, 0.3, 3.0 + k])
            size = np.array([0.5 + 0.2 * k, 0.6, 0.9])
            prims = [Cuboid(centre + R @ rng.normal(scale=0.15, size=3), np.abs(rng.normal(scale=0.3, size=3)) + 0.05,
                            R @ rot_z(np.radians(rng.uniform(-20, 20)))) for _ in range(1 + k)]
            objs.append(Object3D("chair", 0.8, centre, size, R, primitives=prims))
        return objs

    state = rng.bit_generator.state
    together = snap_primitives(make())
    rng.bit_generator.state = state
    one_by_one = [snap_primitives([o])[0] for o in make()]
    for a, b in zip(together, one_by_one):
        assert len(a.primitives) == len(b.primitives) >= 1
        for p, q in zip(a.primitives, b.primitives):
            np.testing.assert_allclose(p.center, q.center, atol=1e-12)
            np.testing.assert_allclose(p.size, q.size, atol=1e-12)
        local = np.stack([(p.center - a.center) @ a.rotation for p in a.primitives])
        ext = np.stack([p.size for p in a.primitives]) / 2
        assert np.all(np.abs(local) + ext <= a.size / 2 + 1e-9)  # all inside their own box
