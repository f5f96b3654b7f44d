"""sensor_msgs/CameraInfo <-> K for both message flavours."""

from __future__ import annotations

import numpy as np
import pytest

from msg_conversion import (
    K_to_camera_info,
    camera_info_distortion,
    camera_info_size,
    camera_info_to_K,
    rosbags_types,
    scale_K,
    stamp_to_ns,
)

K0 = np.array([[525.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])


def test_round_trip_and_fields(types):
    msg = K_to_camera_info(K0, 640, 480, types, stamp_ns=5_000_000_001, frame_id="cam_optical")
    assert camera_info_size(msg) == (640, 480)
    assert stamp_to_ns(msg.header.stamp) == 5_000_000_001 and msg.header.frame_id == "cam_optical"
    np.testing.assert_array_equal(np.asarray(msg.k).reshape(3, 3), K0)
    np.testing.assert_array_equal(np.asarray(msg.r).reshape(3, 3), np.eye(3))
    P = np.asarray(msg.p).reshape(3, 4)
    np.testing.assert_array_equal(P[:, :3], K0)
    np.testing.assert_array_equal(P[:, 3], 0)
    model, D = camera_info_distortion(msg)
    assert model == "plumb_bob" and D.shape == (5,) and not D.any()
    for rectified in (True, False):
        K = camera_info_to_K(msg, rectified=rectified)
        assert K.shape == (3, 3)
        np.testing.assert_array_equal(K, K0)
    msg = K_to_camera_info(K0, 64, 48, types, distortion_model="rational_polynomial", D=np.arange(8) * 0.1)
    model, D = camera_info_distortion(msg)
    assert model == "rational_polynomial"
    np.testing.assert_allclose(D, np.arange(8) * 0.1)


def test_P_versus_K(types):
    msg = K_to_camera_info(K0, 640, 480, types)
    Kp = np.array([[500.0, 0.0, 300.0], [0.0, 501.0, 200.0], [0.0, 0.0, 1.0]])
    P = np.zeros((3, 4))
    P[:, :3] = Kp
    P[0, 3] = -0.05 * 500.0  # a stereo baseline term must not leak into K
    msg.p = P.reshape(-1)
    np.testing.assert_array_equal(camera_info_to_K(msg), Kp)
    np.testing.assert_array_equal(camera_info_to_K(msg, rectified=True), Kp)
    np.testing.assert_array_equal(camera_info_to_K(msg, rectified=False), K0)
    msg.p = np.zeros(12)  # uncalibrated P -> K
    np.testing.assert_array_equal(camera_info_to_K(msg), K0)


def test_rejects_uncalibrated_and_invalid(types):
    msg = types.make(types.CameraInfo, width=640, height=480)  # all-zero K and P
    with pytest.raises(ValueError, match=r"CameraInfo\.k.*all zero"):
        camera_info_to_K(msg)
    with pytest.raises(ValueError, match=r"CameraInfo\.k"):
        camera_info_to_K(msg, rectified=False)
    bad = K0.copy()
    bad[0, 0] = np.nan
    msg = K_to_camera_info(bad, 640, 480, types)
    with pytest.raises(ValueError, match=r"CameraInfo\.p.*NaN"):
        camera_info_to_K(msg)
    with pytest.raises(ValueError, match=r"CameraInfo\.k.*NaN"):
        camera_info_to_K(msg, rectified=False)
    bad = K0.copy()
    bad[1, 1] = -520.0
    with pytest.raises(ValueError, match=r"CameraInfo\.p.*focal"):
        camera_info_to_K(K_to_camera_info(bad, 640, 480, types))


def test_binning_and_roi(types):
    msg = K_to_camera_info(K0, 640, 480, types)
    msg.binning_x = 2
    msg.binning_y = 2
    np.testing.assert_allclose(camera_info_to_K(msg), scale_K(K0, 0.5, 0.5))
    np.testing.assert_array_equal(camera_info_to_K(msg, apply_binning_roi=False), K0)
    msg.binning_x = msg.binning_y = 0
    msg.roi.x_offset = 100
    msg.roi.y_offset = 40
    K = camera_info_to_K(msg)
    assert K[0, 2] == pytest.approx(219.5) and K[1, 2] == pytest.approx(199.5)


def test_scale_K_pixel_centre_convention():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(1, 5, 20)]
    for sx, sy in ((0.5, 0.5), (2.0, 2.0), (320 / 640, 240 / 480), (0.3, 0.7)):
        K2 = scale_K(K0, sx, sy)
        uv = pts @ K0.T
        uv = uv[:, :2] / uv[:, 2:]
        uv2 = pts @ K2.T
        uv2 = uv2[:, :2] / uv2[:, 2:]
        np.testing.assert_allclose(uv2[:, 0], sx * (uv[:, 0] + 0.5) - 0.5)
        np.testing.assert_allclose(uv2[:, 1], sy * (uv[:, 1] + 0.5) - 0.5)
    # the image's outer edges map onto the resized image's edges: -0.5 -> -0.5, W-0.5 -> W'-0.5
    K2 = scale_K(K0, 0.5, 0.5)
    assert K2[0, 2] == pytest.approx(0.5 * 320 - 0.5)  # centred principal point stays centred
    np.testing.assert_allclose(scale_K(scale_K(K0, 0.25, 0.5), 4.0, 2.0), K0)


def test_rosbags_cdr_round_trip():
    types = rosbags_types()
    ts = types.typestore
    msg = K_to_camera_info(K0, 640, 480, types, stamp_ns=77, frame_id="c", D=[0.1, -0.2, 0.001, 0.002, 0.03])
    back = ts.deserialize_cdr(ts.serialize_cdr(msg, "sensor_msgs/msg/CameraInfo"), "sensor_msgs/msg/CameraInfo")
    np.testing.assert_array_equal(camera_info_to_K(back), K0)
    assert camera_info_size(back) == (640, 480) and stamp_to_ns(back.header.stamp) == 77
    np.testing.assert_allclose(camera_info_distortion(back)[1], [0.1, -0.2, 0.001, 0.002, 0.03])
