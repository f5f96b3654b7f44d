"""Floor contact (shape_detector.postprocess.floor.snap_to_floor)."""

import numpy as np

from shape_detector.postprocess.floor import snap_to_floor
from shape_detector.geometry import heading_to_rotation
from shape_detector.types import Cuboid, Object3D

UP = np.array([0.0, -np.cos(0.2), np.sin(0.2)])  # camera pitched down by 0.2 rad
CAM_HEIGHT = 1.3  # the floor plane: UP . p = -1.3


def _obj(bottom: float, height: float) -> Object3D:
    """A box whose bottom face is ``bottom`` m above the floor."""
    R = heading_to_rotation(0.4, UP)
    c = np.array([0.3, 0.0, 3.0])
    c = c - (c @ UP) * UP + (-CAM_HEIGHT + bottom + height / 2) * UP
    top_slab = Cuboid(c + (height / 2 - 0.025) * UP, [0.6, 1.0, 0.05], R)  # flush with the box top
    leg = Cuboid(c + 0.25 * R[:, 0] - (height / 2 - 0.2) * UP, [0.05, 0.05, 0.4], R)  # on the box bottom
    return Object3D("dresser", 0.9, c, [0.6, 1.0, height], R, primitives=[top_slab, leg])


def test_bottom_near_the_floor_is_put_on_it_keeping_the_top():
    obj = _obj(-0.08, 1.1)  # bottom 8 cm below the floor
    top = obj.center @ UP + 0.55
    c0 = obj.center.copy()
    (out,) = snap_to_floor([obj], UP, CAM_HEIGHT, max_gap=0.25)
    assert abs(out.center @ UP - out.size[2] / 2 - (-CAM_HEIGHT)) < 1e-9  # bottom on the floor
    assert abs(out.center @ UP + out.size[2] / 2 - top) < 1e-9  # top unchanged
    assert abs(out.size[2] - 1.02) < 1e-9 and np.allclose(out.size[:2], [0.6, 1.0])
    shift = out.center - c0
    assert np.allclose(shift, (shift @ UP) * UP)  # moved along gravity only
    # the primitives stretch with the box: the slab stays flush with the top, the leg reaches the floor
    slab, leg = out.primitives
    assert abs(slab.center @ UP + slab.size[2] / 2 - top) < 1e-9
    assert abs(leg.center @ UP - leg.size[2] / 2 - (-CAM_HEIGHT)) < 1e-9
    assert abs(leg.size[2] - 0.4 * 1.02 / 1.1) < 1e-9 and np.allclose(leg.size[:2], 0.05)
    assert abs(((leg.center - out.center) @ obj.rotation)[0] - 0.25) < 1e-9  # footprint position kept


def test_far_from_the_floor_or_no_floor_is_left_alone():
    hanging = _obj(0.6, 0.5)  # a wall shelf 60 cm up
    c = hanging.center.copy()
    snap_to_floor([hanging], UP, CAM_HEIGHT, max_gap=0.25)
    assert np.allclose(hanging.center, c)
    low = _obj(0.1, 0.8)
    c = low.center.copy()
    snap_to_floor([low], UP, None)
    snap_to_floor([low], UP, CAM_HEIGHT, max_gap=0.0)
    assert np.allclose(low.center, c)
    assert snap_to_floor([], UP, CAM_HEIGHT) == []
