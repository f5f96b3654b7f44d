"""sensor_msgs/Image <-> numpy for both message flavours (rclpy classes, rosbags dataclasses)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from msg_conversion import (
    depth_to_image,
    image_to_depth,
    image_to_numpy,
    image_to_rgb,
    numpy_to_image,
    rclpy_types,
    rosbags_types,
    stamp_to_ns,
)

ENCODINGS: dict[str, tuple[Any, int]] = {  # encoding -> (numpy scalar type, channels)
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}




def _random(enc: str, h: int = 5, w: int = 7, seed: int = 0) -> np.ndarray:
    dtype, ch = ENCODINGS[enc]
    rng = np.random.default_rng(seed)
    shape = (h, w) if ch == 1 else (h, w, ch)
    if dtype == np.float32:
        return rng.uniform(-100, 100, shape).astype(np.float32)
    return rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)


def _raw_bytes(msg) -> bytes:
    return bytes(np.asarray(msg.data, dtype=np.uint8).tobytes()) if not isinstance(msg.data, (bytes, bytearray)) else bytes(msg.data)


@pytest.mark.parametrize("enc", list(ENCODINGS))
@pytest.mark.parametrize("big", [False, True])
@pytest.mark.parametrize("pad", [0, 7])
def test_round_trip_every_encoding(types, enc, big, pad):
    a = _random(enc)
    dtype, ch = ENCODINGS[enc]
    row = 7 * ch * np.dtype(dtype).itemsize
    msg = numpy_to_image(a, enc, types, stamp_ns=1_700_000_000_123_456_789, frame_id="cam", is_bigendian=big, step=row + pad)
    assert (msg.height, msg.width, msg.encoding, msg.step) == (5, 7, enc, row + pad)
    assert int(msg.is_bigendian) == int(big)
    assert len(_raw_bytes(msg)) == 5 * (row + pad)
    assert stamp_to_ns(msg.header.stamp) == 1_700_000_000_123_456_789
    assert msg.header.frame_id == "cam"
    out = image_to_numpy(msg)
    assert out.dtype == np.dtype(dtype) and out.dtype.isnative
    assert out.shape == a.shape
    np.testing.assert_array_equal(out, a)
    # padding bytes are zero and the wire byte order is the requested one
    raw = np.frombuffer(_raw_bytes(msg), np.uint8).reshape(5, row + pad)
    assert not raw[:, row:].any()
    wire = np.dtype(dtype).newbyteorder(">" if big else "<")
    assert raw[:, :row].tobytes() == np.ascontiguousarray(a, dtype=wire).tobytes()


def test_reads_hand_built_big_endian_padded_messages(types):
    # mono16, 2x2, step 6 (2 bytes padding), big-endian: 0x0102, 0x0304 / 0x0A0B, 0xFFFE
    data = bytes([1, 2, 3, 4, 99, 99, 0x0A, 0x0B, 0xFF, 0xFE, 99, 99])
    for enc in ("mono16", "16UC1"):
        msg = types.make(types.Image, height=2, width=2, encoding=enc, is_bigendian=1, step=6, data=_data(types, data))
        np.testing.assert_array_equal(image_to_numpy(msg), np.array([[0x0102, 0x0304], [0x0A0B, 0xFFFE]], np.uint16))
        np.testing.assert_allclose(image_to_depth(msg), np.array([[0x0102, 0x0304], [0x0A0B, 0xFFFE]]) * 0.001, rtol=1e-6)
    # 32FC1 big-endian, 1x2 with 4 bytes padding
    vals = np.array([1.5, -2.25], dtype=">f4")
    msg = types.make(types.Image, height=1, width=2, encoding="32FC1", is_bigendian=1, step=12, data=_data(types, vals.tobytes() + b"\0" * 4))
    np.testing.assert_array_equal(image_to_numpy(msg), [[1.5, -2.25]])
    # little-endian 16UC1: 1000 mm = 0xE8 0x03
    msg = types.make(types.Image, height=1, width=1, encoding="16UC1", is_bigendian=0, step=2, data=_data(types, bytes([0xE8, 0x03])))
    assert image_to_depth(msg)[0, 0] == pytest.approx(1.0)


def _data(types, raw: bytes):
    if types.flavour == "rclpy":
        import array

        return array.array("B", raw)
    return np.frombuffer(raw, np.uint8).copy()


def test_zero_copy_views_are_read_only_and_copy_is_writable(types):
    a = _random("rgb8")
    msg = numpy_to_image(a, "rgb8", types)
    view = image_to_numpy(msg)
    assert not view.flags.writeable
    with pytest.raises(ValueError):
        view[0, 0, 0] = 1
    own = image_to_numpy(msg, copy=True)
    own[...] = 0
    np.testing.assert_array_equal(image_to_numpy(msg), a)
    rgb = image_to_rgb(msg)
    rgb[...] = 0  # owned, writable, message untouched
    np.testing.assert_array_equal(image_to_numpy(msg), a)


def test_image_to_rgb_all_colour_encodings(types):
    rgb = _random("rgb8", seed=3)
    cases = {
        "rgb8": rgb,
        "bgr8": rgb[..., ::-1],
        "rgba8": np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 200, np.uint8)], axis=2),
        "bgra8": np.concatenate([rgb[..., ::-1], np.full(rgb.shape[:2] + (1,), 7, np.uint8)], axis=2),
    }
    for enc, pixels in cases.items():
        out = image_to_rgb(numpy_to_image(pixels, enc, types, step=pixels.shape[1] * pixels.shape[2] + 3))
        assert out.shape == rgb.shape and out.dtype == np.uint8 and out.flags.c_contiguous
        np.testing.assert_array_equal(out, rgb, err_msg=enc)
    grey = rgb[..., 0]
    out = image_to_rgb(numpy_to_image(grey, "mono8", types))
    np.testing.assert_array_equal(out, np.stack([grey] * 3, axis=2))


def test_depth_invalid_values(types):
    mm = np.array([[0, 1000, 65535, 1234]], np.uint16)
    d = image_to_depth(numpy_to_image(mm, "16UC1", types))
    assert d.dtype == np.float32
    assert np.isnan(d[0, 0])
    np.testing.assert_allclose(d[0, 1:], [1.0, 65.535, 1.234], rtol=1e-6)
    d = image_to_depth(numpy_to_image(mm, "mono16", types), depth_scale=0.0001)
    np.testing.assert_allclose(d[0, 1:], [0.1, 6.5535, 0.1234], rtol=1e-6)
    m = np.array([[0.0, np.nan, np.inf, -np.inf, -1.0, 2.5]], np.float32)
    d = image_to_depth(numpy_to_image(m, "32FC1", types))
    assert np.isnan(d[0, :5]).all() and d[0, 5] == 2.5


def test_depth_to_image_encodes_mm_and_metres(types):
    depth = np.array([[np.nan, 0.0, -1.0, np.inf, 1.2344, 1.2346, 70.0, 0.0004, 0.0006]])
    msg = depth_to_image(depth, types, "16UC1", stamp_ns=42, frame_id="depth")
    assert msg.encoding == "16UC1" and stamp_to_ns(msg.header.stamp) == 42 and msg.header.frame_id == "depth"
    np.testing.assert_array_equal(image_to_numpy(msg), [[0, 0, 0, 0, 1234, 1235, 65535, 0, 1]])
    back = image_to_depth(msg)
    assert np.isnan(back[0, :4]).all() and np.isnan(back[0, 7])
    np.testing.assert_allclose(back[0, [4, 5, 6, 8]], [1.234, 1.235, 65.535, 0.001], rtol=1e-6)
    msg = depth_to_image(depth, types, "32FC1", is_bigendian=True)
    raw = image_to_numpy(msg)
    assert raw.dtype == np.float32 and np.isnan(raw[0, :4]).all()
    np.testing.assert_allclose(image_to_depth(msg)[0, 4:], depth[0, 4:], rtol=1e-6)
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.2, 9.0, (48, 64))
    back = image_to_depth(depth_to_image(depth, types))
    assert np.abs(back - depth).max() <= 0.0005 + 1e-6


@pytest.mark.parametrize(
    "fields, match",
    [
        (dict(encoding="yuv422"), "Image.encoding"),
        (dict(step=20), "Image.step"),  # < 7 * 3
        (dict(data_len=5 * 21 - 1), "Image.data"),
        (dict(data_len=5 * 21 + 3), "Image.data"),
    ],
)
def test_bad_messages_raise_naming_the_field(types, fields, match):
    step = fields.get("step", 21)
    raw = bytes(fields.get("data_len", 5 * step))
    msg = types.make(types.Image, height=5, width=7, encoding=fields.get("encoding", "rgb8"), step=step, data=_data(types, raw))
    with pytest.raises(ValueError, match=match):
        image_to_numpy(msg)


def test_bad_conversions_raise(types):
    with pytest.raises(ValueError, match="Image.encoding"):
        numpy_to_image(np.zeros((4, 4, 3), np.uint8), "mono8", types)  # channel mismatch
    with pytest.raises(ValueError, match="Image.encoding"):
        numpy_to_image(np.zeros((4, 4), np.uint8), "rgb8", types)
    with pytest.raises(ValueError, match="Image.step"):
        numpy_to_image(np.zeros((4, 4, 3), np.uint8), "rgb8", types, step=11)
    with pytest.raises(ValueError, match="Image.encoding"):
        numpy_to_image(np.zeros((4, 4), np.uint8), "nv12", types)
    with pytest.raises(ValueError, match="do not fit"):
        numpy_to_image(np.array([[300]]), "mono8", types)
    with pytest.raises(ValueError, match="Image.encoding"):
        image_to_rgb(numpy_to_image(np.zeros((2, 2), np.float32), "32FC1", types))
    with pytest.raises(ValueError, match="Image.encoding"):
        image_to_depth(numpy_to_image(np.zeros((2, 2, 3), np.uint8), "rgb8", types))
    with pytest.raises(ValueError, match="Image.encoding"):
        depth_to_image(np.zeros((2, 2)), types, encoding="mono8")
    # lossless casts are accepted
    msg = numpy_to_image(np.array([[1, 2]], np.int64), "16UC1", types)
    np.testing.assert_array_equal(image_to_numpy(msg), [[1, 2]])


def test_rosbags_cdr_round_trip():
    types = rosbags_types()
    ts = types.typestore
    for enc, big, pad in (("bgr8", False, 3), ("16UC1", True, 2), ("32FC1", True, 0), ("mono16", False, 6)):
        a = _random(enc, seed=5)
        msg = numpy_to_image(a, enc, types, stamp_ns=3_000_000_007, frame_id="cam", is_bigendian=big, step=a.shape[1] * a.itemsize * (a.shape[2] if a.ndim == 3 else 1) + pad)
        back = ts.deserialize_cdr(ts.serialize_cdr(msg, "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
        assert (back.step, back.encoding, back.is_bigendian) == (msg.step, enc, int(big))
        assert stamp_to_ns(back.header.stamp) == 3_000_000_007
        np.testing.assert_array_equal(image_to_numpy(back), a)


def test_rclpy_serialisation_is_readable_by_rosbags():
    pytest.importorskip("sensor_msgs.msg")
    from rclpy.serialization import serialize_message

    a = _random("16UC1", seed=9)
    msg = numpy_to_image(a, "16UC1", rclpy_types(), stamp_ns=11, frame_id="d", is_bigendian=True, step=7 * 2 + 2)
    back = rosbags_types().typestore.deserialize_cdr(serialize_message(msg), "sensor_msgs/msg/Image")
    np.testing.assert_array_equal(image_to_numpy(back), a)
    assert back.header.frame_id == "d" and stamp_to_ns(back.header.stamp) == 11
