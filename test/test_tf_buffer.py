"""TransformBuffer: chains, static links, interpolation by stamp, bounded history, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.poses import (
    ExtrapolationError,
    FrameNotFoundError,
    TransformBuffer,
    TransformLookupError,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
    slerp,
)
from shape_detector.geometry import rot_z

S = 1_000_000_000
OPTICAL_Q = matrix_to_quaternion(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))


def _q_z(theta: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(theta / 2), np.cos(theta / 2)])


def _chain_buffer() -> TransformBuffer:
    buf = TransformBuffer()
    buf.add("odom", "base_link", 0, (0, 0, 0), _q_z(0.0))
    buf.add("odom", "base_link", 2 * S, (2.0, 0, 0), _q_z(np.pi / 2))
    buf.add("base_link", "camera_link", 0, (0.1, 0, 1.0), (0, 0, 0, 1), static=True)
    buf.add("camera_link", "camera_color_optical_frame", 0, (0, 0.02, 0), OPTICAL_Q, static=True)
    return buf


def test_quaternion_round_trip_and_slerp_midpoint() -> None:
    for theta in (0.0, 0.3, 2.5, -3.0):
        R = rot_z(theta)
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-9)
    mid = slerp(_q_z(0.0), _q_z(np.pi / 2), 0.5)
    np.testing.assert_allclose(quaternion_to_matrix(mid), rot_z(np.pi / 4), atol=1e-9)


def test_chain_with_static_links_at_a_stored_stamp() -> None:
    buf = _chain_buffer()
    T = buf.lookup("odom", "camera_color_optical_frame", 0)
    # optical z (forward) is base x; the optical origin is 0.1 m ahead, 0.02 m left, 1 m up
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.02, 1.0], atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(T[:3, 1], [0.0, 0.0, -1.0], atol=1e-9)


def test_interpolation_linear_translation_and_slerp_rotation() -> None:
    buf = _chain_buffer()
    T = buf.lookup("odom", "base_link", 1 * S)
    np.testing.assert_allclose(T[:3, 3], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(T[:3, :3], rot_z(np.pi / 4), atol=1e-9)
    T_cam = buf.lookup("odom", "camera_link", S // 2)
    expected = make_transform((0.5, 0, 0), _q_z(np.pi / 8)) @ make_transform((0.1, 0, 1.0), (0, 0, 0, 1))
    np.testing.assert_allclose(T_cam, expected, atol=1e-9)


def test_inverse_direction_and_sibling_frames() -> None:
    buf = _chain_buffer()
    buf.add("base_link", "lidar", 0, (0, 0, 0.5), (0, 0, 0, 1), static=True)
    T_cb = buf.lookup("camera_link", "lidar", S)
    np.testing.assert_allclose(T_cb[:3, 3], [-0.1, 0.0, -0.5], atol=1e-9)
    T_a = buf.lookup("odom", "camera_color_optical_frame", S)
    T_b = buf.lookup("camera_color_optical_frame", "odom", S)
    np.testing.assert_allclose(T_a @ T_b, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(buf.lookup("odom", "odom", 5), np.eye(4))


def test_latest_when_stamp_is_none() -> None:
    buf = _chain_buffer()
    np.testing.assert_allclose(buf.lookup("odom", "base_link", None)[:3, 3], [2.0, 0, 0], atol=1e-9)


def test_stamp_outside_history_is_a_clear_error() -> None:
    buf = _chain_buffer()
    with pytest.raises(ExtrapolationError, match="odom -> base_link.*outside"):
        buf.lookup("odom", "camera_link", 3 * S)
    assert not buf.can_transform("odom", "camera_link", -1)
    assert buf.can_transform("odom", "camera_link", 2 * S)


def test_missing_link_names_the_frames() -> None:
    buf = _chain_buffer()
    buf.add("map", "other", 0, (0, 0, 0), (0, 0, 0, 1), static=True)
    with pytest.raises(FrameNotFoundError, match="'map'.*'odom'|'odom'.*'map'"):
        buf.lookup("map", "camera_link", 0)
    with pytest.raises(TransformLookupError, match="'nowhere' is not in the transform buffer"):
        buf.lookup("odom", "nowhere", 0)
    assert issubclass(TransformLookupError, LookupError)


def test_bounded_history_drops_old_entries() -> None:
    buf = TransformBuffer(max_history_ns=2 * S)
    for k in range(10):
        buf.add("odom", "base_link", k * S, (float(k), 0, 0), (0, 0, 0, 1))
    with pytest.raises(ExtrapolationError):
        buf.lookup("odom", "base_link", 5 * S)
    np.testing.assert_allclose(buf.lookup("odom", "base_link", int(8.5 * S))[:3, 3], [8.5, 0, 0], atol=1e-9)


def test_out_of_order_and_repeated_stamps() -> None:
    buf = TransformBuffer()
    buf.add("odom", "base_link", 2 * S, (2.0, 0, 0), (0, 0, 0, 1))
    buf.add("odom", "base_link", 0, (0.0, 0, 0), (0, 0, 0, 1))
    buf.add("odom", "base_link", 2 * S, (4.0, 0, 0), (0, 0, 0, 1))  # newest wins
    np.testing.assert_allclose(buf.lookup("odom", "base_link", S)[:3, 3], [2.0, 0, 0], atol=1e-9)


def test_bad_input_refused() -> None:
    buf = TransformBuffer()
    with pytest.raises(ValueError):
        buf.add("a", "a", 0, (0, 0, 0), (0, 0, 0, 1))
    with pytest.raises(ValueError):
        buf.add("a", "", 0, (0, 0, 0), (0, 0, 0, 1))
    with pytest.raises(ValueError):
        buf.add("a", "b", 0, (np.nan, 0, 0), (0, 0, 0, 1))
    with pytest.raises(ValueError):
        buf.add("a", "b", 0, (0, 0, 0), (0, 0, 0, 0))
    with pytest.raises(ValueError):
        TransformBuffer(max_history_ns=0)


def test_leading_slash_frames_are_the_same_frame() -> None:
    buf = TransformBuffer()
    buf.add("/odom", "/base_link", 0, (1.0, 0, 0), (0, 0, 0, 1), static=True)
    np.testing.assert_allclose(buf.lookup("odom", "base_link", 0)[:3, 3], [1.0, 0, 0])


def test_camera_up_is_world_z_in_the_camera_frame() -> None:
    from shape_detector.poses import camera_up

    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # optical axes, looking along world +x
    np.testing.assert_allclose(camera_up(T), [0.0, -1.0, 0.0])
    T[:3, :3] *= 2.0  # a scaled rotation still gives a unit vector
    np.testing.assert_allclose(camera_up(T), [0.0, -1.0, 0.0])
    T[:3, :3] = 0.0
    assert camera_up(T) is None
