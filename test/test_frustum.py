"""Back-projection and frustum extraction (shape_detector.frustum)."""

import numpy as np
import pytest

from shape_detector.frustum import backproject, clip_box, extract_frustum, extract_frustums
from shape_detector.geometry import normalize, rot_z, upright_rotation

K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])


def _plane_scene(z=2.0, h=480, w=640):
    depth = np.full((h, w), z, np.float32)
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = 255
    return rgb, depth


def test_backproject_inverts_projection():
    rgb, depth = _plane_scene(2.5)
    pts = backproject(depth, K)
    uv = pts.reshape(-1, 3) @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    vv, uu = np.mgrid[0:480, 0:640]
    np.testing.assert_allclose(uv[:, 0], uu.ravel(), atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], vv.ravel(), atol=1e-3)


def test_frustum_centre_ray_points_along_y_and_maps_back():
    rgb, depth = _plane_scene(3.0)
    up = normalize(np.array([0.05, -0.95, 0.25]))
    box = (450, 100, 560, 220)
    fr = extract_frustum(rgb, depth, K, box, 256, up=up, rng=np.random.default_rng(0))
    assert fr.points.shape == (256, 6) and fr.points.dtype == np.float32
    assert fr.valid == 110 * 120
    # the centre ray of the box, in frame F, has no x component
    uc, vc = (450 + 560) / 2 - 0.5, (100 + 220) / 2 - 0.5
    ray = np.linalg.solve(K, [uc, vc, 1.0])
    ray_f = fr.R_cf.T @ ray
    assert abs(ray_f[0]) < 1e-9 and ray_f[1] > 0
    # points map back onto the plane z = 3 inside the box's pixels
    p_cam = fr.to_camera(fr.points[:, :3].astype(np.float64))
    np.testing.assert_allclose(p_cam[:, 2], 3.0, atol=1e-5)
    u = p_cam[:, 0] / p_cam[:, 2] * K[0, 0] + K[0, 2]
    assert u.min() >= 450 - 1e-3 and u.max() <= 559 + 1e-3
    np.testing.assert_allclose(fr.points[:, 3:], np.tile([1.0, 0, 0], (256, 1)))
    # F's z is gravity up
    np.testing.assert_allclose(fr.R_cf[:, 2], up, atol=1e-12)
    np.testing.assert_allclose(fr.R_cf, upright_rotation(up) @ rot_z(-fr.phi), atol=1e-12)


def test_frustum_resamples_when_few_points_and_handles_none():
    rgb, depth = _plane_scene(2.0)
    depth[:] = np.nan
    depth[200, 300] = 2.0
    depth[201, 301] = 2.1
    fr = extract_frustum(rgb, depth, K, (290, 190, 310, 210), 64, rng=np.random.default_rng(1))
    assert fr.valid == 2 and fr.points.shape == (64, 6)
    assert set(np.unique(fr.pixel_index)) <= {200 * 640 + 300, 201 * 640 + 301}
    empty = extract_frustum(rgb, depth, K, (0, 0, 50, 50), 64)
    assert empty.valid == 0 and not empty.points.any()
    outside = extract_frustum(rgb, depth, K, (700, 500, 800, 600), 64)
    assert outside.valid == 0


def test_deterministic_sampling_without_rng():
    rgb, depth = _plane_scene(2.0)
    a = extract_frustum(rgb, depth, K, (100, 100, 200, 200), 128)
    b = extract_frustum(rgb, depth, K, (100, 100, 200, 200), 128)
    np.testing.assert_array_equal(a.points, b.points)
    assert len(np.unique(a.pixel_index)) == 128


def test_zero_and_far_depth_are_invalid():
    rgb, depth = _plane_scene(2.0)
    depth[:, :320] = 0.0
    depth[:, 320:330] = 50.0
    fr = extract_frustum(rgb, depth, K, (300, 0, 340, 10), 32)
    assert fr.valid == 10 * 10


def test_clip_box():
    assert clip_box((-10.2, 5.5, 700, 479.2), 640, 480) == (0, 5, 640, 480)
    assert clip_box((50, 50, 40, 60), 640, 480)[2] <= 50


def test_extract_frustums_gives_the_frustums_of_extract_frustum():
    rng = np.random.default_rng(3)
    h, w = 120, 160
    depth = rng.uniform(0.8, 4.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.1] = np.nan
    depth[:, :20] = 0.0  # an invalid band: a box inside it has no points
    rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    K = np.array([[130.0, 0.0, 79.5], [0.0, 130.0, 59.5], [0.0, 0.0, 1.0]])
    up = normalize(np.array([0.05, -1.0, -0.2]))
    boxes = [(30, 20, 90, 100), (0, 0, 15, 50), (140.5, 90.2, 170, 130), (-20, -20, -5, -5), (50, 40, 52, 41)]
    got = extract_frustums(rgb, depth, K, boxes, 64, up=up)
    assert len(got) == len(boxes)
    for box, g in zip(boxes, got):
        want = extract_frustum(rgb, depth, K, box, 64, up=up)
        assert g.valid == want.valid and g.phi == pytest.approx(want.phi, abs=1e-12)
        np.testing.assert_allclose(g.points, want.points, atol=1e-6)
        np.testing.assert_array_equal(g.pixel_index, want.pixel_index)
    assert got[1].valid == 0 and got[3].valid == 0 and not np.any(got[3].points)
