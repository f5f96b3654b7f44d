"""Frames and yaw-only box conventions (shape_detector.geometry)."""

import numpy as np
import pytest

from shape_detector.geometry import (
    box_corners,
    heading_to_rotation,
    normalize,
    points_in_box,
    project_points,
    rot_z,
    rotation_to_heading,
    upright_rotation,
    wrap_angle,
)


def test_level_camera_upright_frame_is_sunrgbd_upright():
    # level camera: U = x right, y forward (optical z), z up (optical -y)
    R = upright_rotation(None)
    np.testing.assert_allclose(R, [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize("pitch_deg,roll_deg", [(0, 0), (-30, 0), (20, 10), (-60, -15)])
def test_upright_rotation_is_proper_and_z_is_up(pitch_deg, roll_deg):
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    # gravity-up in the optical frame of a camera pitched by p (down negative) and rolled by r
    up = normalize(np.array([np.sin(r) * np.cos(p), -np.cos(r) * np.cos(p), np.sin(p)]))
    R = upright_rotation(up)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], up, atol=1e-12)
    # y axis is the horizontal projection of the optical axis: no x component of forward
    assert (R.T @ np.array([0, 0, 1.0]))[0] == pytest.approx(0.0, abs=1e-12)


def test_upright_rotation_degenerate_looking_down():
    R = upright_rotation(np.array([0.0, 0.0, -1.0]))  # camera looks straight down
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("theta", [-3.0, -1.2, 0.0, 0.4, 2.9])
def test_heading_round_trip_and_z_column_is_up(theta):
    up = normalize(np.array([0.1, -0.9, 0.3]))
    R = heading_to_rotation(theta, up)
    np.testing.assert_allclose(R[:, 2], up, atol=1e-12)
    assert rotation_to_heading(R, up) == pytest.approx(theta, abs=1e-9)


def test_box_corners_extent_and_points_in_box():
    R = heading_to_rotation(0.5, None)
    c, s = np.array([0.3, 0.2, 3.0]), np.array([2.0, 1.0, 0.5])
    corners = box_corners(c, s, R)
    local = (corners - c) @ R
    np.testing.assert_allclose(np.abs(local), np.tile(s / 2, (8, 1)), atol=1e-12)
    np.testing.assert_allclose(corners.mean(0), c, atol=1e-12)
    inside = c + R @ np.array([0.9, -0.45, 0.2])
    outside = c + R @ np.array([1.1, 0.0, 0.0])
    assert points_in_box(np.stack([inside, outside]), c, s, R).tolist() == [True, False]


def test_rot_z_and_wrap():
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert rot_z(np.zeros(4)).shape == (4, 3, 3)
    assert wrap_angle(3 * np.pi / 2) == pytest.approx(-np.pi / 2)


def test_project_points_pixel_centre_convention():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(project_points(np.array([[0, 0, 2.0]]), K), [[319.5, 239.5]])


def test_measured_depth_reads_the_pixel_a_point_projects_to():
    from shape_detector.geometry import measured_depth

    K = np.array([[100.0, 0, 50.0], [0, 100.0, 40.0], [0, 0, 1]])
    depth = np.full((80, 100), 3.0, np.float32)
    depth[40, 60] = 0.0  # invalid pixel
    pts = np.array([[0.0, 0.0, 2.0], [0.2, 0.0, 2.0], [0.0, 0.0, 0.01], [9.0, 0.0, 1.0]])
    d = measured_depth(pts, depth, K)
    assert d[0] == 3.0 and np.isnan(d[1:]).all()  # on an invalid pixel, too near, outside
    assert measured_depth(pts.reshape(2, 2, 3), depth, K).shape == (2, 2)
