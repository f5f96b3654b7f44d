"""Input validation of the detector (shape_detector.inputs)."""

import numpy as np
import pytest

from shape_detector.inputs import check_intrinsics, depth_to_metres, normalize_inputs


def test_uint16_millimetres_to_metres_with_zero_invalid():
    d = np.array([[0, 1000], [1234, 65535]], np.uint16)
    m = depth_to_metres(d)
    assert m.dtype == np.float32
    assert np.isnan(m[0, 0])
    np.testing.assert_allclose(m[~np.isnan(m)], [1.0, 1.234, 65.535], rtol=1e-6)
    np.testing.assert_allclose(depth_to_metres(d, depth_scale=0.000125)[0, 1], 0.125)


def test_float_depth_invalid_values_become_nan():
    d = np.array([[np.nan, np.inf], [-1.0, 2.5]], np.float32)
    m = depth_to_metres(d)
    assert np.isnan(m).sum() == 3 and m[1, 1] == 2.5


def test_bad_intrinsics_and_sizes_raise_clear_errors():
    with pytest.raises(ValueError, match="focal"):
        check_intrinsics(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        check_intrinsics(np.full((3, 3), np.nan))
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"640x480.*320x240"):
        normalize_inputs(np.zeros((480, 640, 3), np.uint8), np.zeros((240, 320), np.float32), K)
    with pytest.raises(ValueError, match="depth"):
        normalize_inputs(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 2), np.float32), K)
    with pytest.raises(ValueError, match="rgb"):
        normalize_inputs(np.zeros((4, 4, 5), np.uint8), np.zeros((4, 4), np.float32), K)


def test_rgba_and_grey_are_accepted():
    K = np.eye(3)
    rgb, depth, _ = normalize_inputs(np.zeros((4, 4, 4), np.uint8), np.ones((4, 4), np.float32), K)
    assert rgb.shape == (4, 4, 3)
    rgb, _, _ = normalize_inputs(np.zeros((4, 4), np.uint8), np.ones((4, 4), np.float32), K)
    assert rgb.shape == (4, 4, 3)
