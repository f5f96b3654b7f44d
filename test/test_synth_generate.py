"""Generator ground truth: determinism, masks vs boxes, 3D boxes vs surface points, parts."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.classes import CLASSES
from shape_detector.frustum import backproject
from shape_detector.geometry import heading_to_rotation
from shape_detector.synth.generate import SynthConfig, generate_frame, generate_sequence

SMALL = SynthConfig(width=320, height=240)
CLEAN = SynthConfig(width=320, height=240, noise=False)


def _same(a, b) -> None:
    assert np.array_equal(a.rgb, b.rgb)
    assert np.array_equal(a.depth, b.depth, equal_nan=True)
    assert np.array_equal(a.instance_mask, b.instance_mask)
    assert np.array_equal(a.K, b.K) and np.array_equal(a.up, b.up)
    assert a.stamp_ns == b.stamp_ns
    assert [o.to_dict() for o in a.objects] == [o.to_dict() for o in b.objects]
    assert a.clutter_boxes == b.clutter_boxes


def test_determinism_by_seed():
    a = generate_frame(11, SMALL)
    b = generate_frame(11, SMALL)
    _same(a, b)
    c = generate_frame(12, SMALL)
    assert not np.array_equal(a.rgb, c.rgb)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_frame_fields_and_masks(seed):
    f = generate_frame(seed, SMALL)
    H, W = 240, 320
    assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (H, W) and f.depth.dtype == np.float32
    assert f.instance_mask.shape == (H, W) and f.instance_mask.dtype == np.int32
    assert f.frame_id == "camera_color_optical_frame"
    assert abs(np.linalg.norm(f.up) - 1) < 1e-9
    valid = np.isfinite(f.depth)
    assert valid.mean() > 0.3 and np.all(f.depth[valid] > 0)
    ids = {o.instance_id for o in f.objects}
    assert set(np.unique(f.instance_mask)) - {0} == ids
    for o in f.objects:
        assert o.class_name in CLASSES
        m = f.instance_mask == o.instance_id
        ys, xs = np.nonzero(m)
        assert o.box2d == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
        assert 0 < o.visible_fraction <= 1
        # yaw-only box: z column = up; heading consistent with the rotation
        assert np.allclose(o.rotation[:, 2], f.up, atol=1e-9)
        assert np.allclose(heading_to_rotation(o.heading, f.up), o.rotation, atol=1e-9)
        assert np.allclose(o.rotation.T @ o.rotation, np.eye(3), atol=1e-9)
        assert len(o.parts) >= 2
    for b in f.clutter_boxes:
        assert 0 <= b[0] < b[2] <= W and 0 <= b[1] < b[3] <= H


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_gt_boxes_contain_surface_points_and_parts(seed):
    f = generate_frame(seed, CLEAN)
    P = backproject(f.depth, f.K)
    assert f.objects
    for o in f.objects:
        pts = P[f.instance_mask == o.instance_id].astype(np.float64)
        local = (pts - o.center) @ o.rotation
        # exact renderer: every labelled pixel's surface point lies in the amodal box
        assert np.all(np.abs(local) <= o.size / 2 + 1e-4), o.class_name
        # the parts fill the box exactly: their corners lie inside and touch every face
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for p in o.parts:
            assert np.allclose(p.rotation, o.rotation)
            c = (p.center - o.center) @ o.rotation
            lo = np.minimum(lo, c - p.size / 2)
            hi = np.maximum(hi, c + p.size / 2)
        assert np.allclose(lo, -o.size / 2, atol=1e-6) and np.allclose(hi, o.size / 2, atol=1e-6)


def _one_box_scene(y_offset: float, occluder: bool = False):
    from shape_detector.synth import textures as tx
    from shape_detector.synth.furniture import Model
    from shape_detector.synth.layout import Placed, Scene

    sc = Scene(10.0, 10.0, 3.0, "test")
    m = Model("dresser")
    m.add(-0.25, 0.25, -0.5, 0.5, 0.0, 1.0, tx.Material())
    sc.objects.append(Placed(m, np.array([3.0, y_offset, 0.0]), np.pi))
    if occluder:
        c = Model("box", labelled=False)
        c.add(-0.1, 0.1, -0.5, 0.5, 0.0, 2.0, tx.Material())
        sc.clutter.append(Placed(c, np.array([2.0, y_offset - 0.25, 0.0]), 0.0))
    return sc


def test_visible_fraction_truncation_and_occlusion():
    from shape_detector.synth.camera import Camera, rotation_from_ypr
    from shape_detector.synth.generate import render_view

    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    cam = Camera(K, 320, 240, np.array([0.0, 0.0, 0.5]), rotation_from_ypr(0.0, 0.0, 0.0))
    cfg = SynthConfig(width=320, height=240, noise=False)
    rng = np.random.default_rng(0)
    full = render_view(_one_box_scene(0.0), cam, rng, rng, cfg).objects[0]
    assert full.visible_fraction > 0.99
    # shifted so that the image's left border (u = -0.5) cuts the box's front face in half
    y = 2.75 * 160.0 / 300.0
    fr = render_view(_one_box_scene(y), cam, rng, rng, cfg)
    half = fr.objects[0]
    assert half.box2d[0] == 0 and 0.45 < half.visible_fraction < 0.65
    # the same view in a wider image (extended to the left) sees the whole object
    K2 = K.copy()
    K2[0, 2] += 320
    cam2 = Camera(K2, 640, 240, cam.C, cam.R_wc)
    wide = render_view(_one_box_scene(y), cam2, rng, rng, SynthConfig(width=640, height=240, noise=False))
    assert wide.objects[0].visible_fraction > 0.99
    n_small = (fr.instance_mask == 1).sum()
    n_wide = (wide.instance_mask == 1).sum()
    assert abs(half.visible_fraction - n_small / n_wide) < 0.01
    occ = render_view(_one_box_scene(0.0, occluder=True), cam, rng, rng, cfg)
    assert 0.05 < occ.objects[0].visible_fraction < 0.8 and len(occ.clutter_boxes) == 1


def test_sequence_is_one_room():
    fr = generate_sequence(3, 3, 5.0, SynthConfig(width=160, height=120))
    assert [f.stamp_ns - fr[0].stamp_ns for f in fr] == [0, 200_000_000, 400_000_000]
    assert all(np.array_equal(f.K, fr[0].K) for f in fr)
