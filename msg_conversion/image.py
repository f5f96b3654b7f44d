"""``sensor_msgs/Image`` <-> numpy, for rclpy messages and rosbags dataclasses alike.

Reading duck-types the fields (``height, width, encoding, is_bigendian, step, data``);
``data`` may be an ``array.array('B')`` (rclpy), a numpy uint8 array (rosbags), bytes,
bytearray, memoryview or a list of ints. Depth follows REP 118: ``32FC1`` in metres,
``16UC1``/``mono16`` in millimetres, 0 / NaN / non-positive = no reading.
"""

from __future__ import annotations

import array
import re
from typing import Any

import numpy as np

from .msgtypes import MsgTypes
from .stamps import make_header

#: named encodings -> (numpy dtype, channels); the ``<bits><U|S|F>C<n>`` forms are parsed.
_NAMED: dict[str, tuple[np.dtype, int]] = {
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),
    "mono8": (np.dtype(np.uint8), 1),
    "rgb16": (np.dtype(np.uint16), 3),
    "bgr16": (np.dtype(np.uint16), 3),
    "rgba16": (np.dtype(np.uint16), 4),
    "bgra16": (np.dtype(np.uint16), 4),
    "mono16": (np.dtype(np.uint16), 1),
}
_CV_RE = re.compile(r"^(8|16|32|64)([USF])C([1-9][0-9]*)$")
_CV_DTYPES = {
    ("8", "U"): np.uint8,
    ("8", "S"): np.int8,
    ("16", "U"): np.uint16,
    ("16", "S"): np.int16,
    ("32", "S"): np.int32,
    ("32", "F"): np.float32,
    ("64", "F"): np.float64,
}
_COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "rgb16", "bgr16", "rgba16", "bgra16", "mono16")
_DEPTH_MM_ENCODINGS = ("16UC1", "mono16")
_DEPTH_M_ENCODINGS = ("32FC1", "64FC1")


def encoding_info(encoding: str) -> tuple[np.dtype, int]:
    """``(dtype, channels)`` of an image encoding; ``ValueError`` for unsupported ones."""
    enc = str(encoding)
    if enc in _NAMED:
        return _NAMED[enc]
    m = _CV_RE.match(enc)
    if m and (m.group(1), m.group(2)) in _CV_DTYPES:
        return np.dtype(_CV_DTYPES[(m.group(1), m.group(2))]), int(m.group(3))
    raise ValueError(
        f"Image.encoding={enc!r} is not supported (expected one of {sorted(_NAMED)} or "
        "an OpenCV type such as 8UC3, 16UC1, 32FC1)"
    )


def bytes_per_pixel(encoding: str) -> int:
    """Bytes of one pixel (all channels) for ``encoding``."""
    dtype, ch = encoding_info(encoding)
    return dtype.itemsize * ch


def _data_bytes(data: Any) -> np.ndarray:
    """The message's ``data`` as a 1-D uint8 array, without copying where possible."""
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8:
            return data.reshape(-1)
        if data.flags.c_contiguous:
            return data.reshape(-1).view(np.uint8)
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)


def image_to_numpy(msg: Any, copy: bool = False) -> np.ndarray:
    """Pixels of an Image: ``(H, W)`` for one channel, ``(H, W, C)`` otherwise, with the
    encoding's dtype in native byte order.

    Row padding (``step`` > ``width * bytes_per_pixel``) is dropped and ``is_bigendian`` is
    honoured. Without byte swapping the result is a zero-copy view of the message buffer;
    such views are marked read-only so writing to them raises instead of silently editing
    the message. ``copy=True`` always returns an owned, writable, C-contiguous array.
    Raises ``ValueError`` naming the offending field on inconsistent messages.
    """
    dtype, ch = encoding_info(msg.encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height < 0 or width < 0:
        raise ValueError(f"Image.height={height} / Image.width={width} must be non-negative")
    row = width * ch * dtype.itemsize
    if step < row:
        raise ValueError(
            f"Image.step={step} is smaller than width*bytes_per_pixel={width}*{ch * dtype.itemsize}={row} "
            f"for encoding {msg.encoding!r}"
        )
    buf = _data_bytes(msg.data)
    if buf.size != height * step:
        raise ValueError(
            f"Image.data has {buf.size} bytes but height*step={height}*{step}={height * step}"
        )
    shape = (height, width) if ch == 1 else (height, width, ch)
    if height == 0 or width == 0:
        return np.zeros(shape, dtype=dtype)
    big = bool(msg.is_bigendian)
    wire = dtype.newbyteorder(">" if big else "<") if dtype.itemsize > 1 else dtype
    rows = buf.reshape(height, step)[:, :row]
    pixels = rows.view(wire).reshape(shape)
    if wire.byteorder not in ("=", "|") and wire != dtype:  # non-native byte order: swap (copies)
        return pixels.astype(dtype)
    if copy:
        return np.array(pixels, dtype=dtype, order="C", copy=True)
    pixels = pixels.view(dtype)
    pixels.flags.writeable = False
    return pixels


def image_to_rgb(msg: Any) -> np.ndarray:
    """An ``(H, W, 3)`` uint8 RGB copy of a colour or grey Image.

    rgb8, bgr8, rgba8, bgra8, mono8 (grey replicated to 3 channels) and their 16-bit
    variants (scaled to 8 bit by dropping the low byte).
    """
    enc = str(msg.encoding)
    if enc not in _COLOR_ENCODINGS:
        raise ValueError(f"Image.encoding={enc!r} is not a colour encoding (expected one of {_COLOR_ENCODINGS})")
    px = image_to_numpy(msg)
    if px.dtype == np.uint16:
        px = (px >> 8).astype(np.uint8)
    if enc.startswith("mono"):
        out = np.empty(px.shape + (3,), dtype=np.uint8)
        out[...] = px[..., None]
        return out
    if enc.startswith("rgb"):
        rgb = px[..., :3]
    else:  # bgr / bgra
        rgb = px[..., 2::-1]
    out = np.ascontiguousarray(rgb)
    return out if out.flags.writeable and out.flags.owndata else out.copy()


def image_to_depth(msg: Any, depth_scale: float | None = None) -> np.ndarray:
    """An ``(H, W)`` float32 depth image in metres, NaN where there is no reading.

    ``16UC1``/``mono16``: raw units times ``depth_scale`` (default 0.001, i.e. millimetres),
    0 -> NaN. ``32FC1``/``64FC1``: metres (times ``depth_scale`` if given), NaN / Inf /
    values <= 0 -> NaN.
    """
    enc = str(msg.encoding)
    if enc in _DEPTH_MM_ENCODINGS:
        raw = image_to_numpy(msg)
        scale = np.float32(0.001 if depth_scale is None else depth_scale)
        out = raw.astype(np.float32)
        out *= scale
        out[raw == 0] = np.nan
        return out
    if enc in _DEPTH_M_ENCODINGS:
        out = image_to_numpy(msg).astype(np.float32)  # always a fresh array
        if depth_scale is not None:
            out *= np.float32(depth_scale)
        with np.errstate(invalid="ignore"):
            out[~(np.isfinite(out) & (out > 0))] = np.nan
        return out
    raise ValueError(
        f"Image.encoding={enc!r} is not a depth encoding (expected one of "
        f"{_DEPTH_MM_ENCODINGS + _DEPTH_M_ENCODINGS})"
    )


def _cast_for_encoding(a: np.ndarray, dtype: np.dtype, encoding: str) -> np.ndarray:
    if a.dtype == dtype:
        return a
    if np.can_cast(a.dtype, dtype, casting="safe"):
        return a.astype(dtype)
    if a.dtype.kind in "iub" and dtype.kind in "iu":
        info = np.iinfo(dtype)
        if a.size == 0 or (int(a.min()) >= info.min and int(a.max()) <= info.max):
            return a.astype(dtype)
        raise ValueError(
            f"array values [{a.min()}, {a.max()}] do not fit Image.encoding={encoding!r} ({dtype})"
        )
    if a.dtype.kind == "f" and dtype.kind == "f":
        return a.astype(dtype)
    raise ValueError(f"array dtype {a.dtype} does not match Image.encoding={encoding!r} ({dtype})")


def _pack_data(buf: np.ndarray, types: MsgTypes) -> Any:
    """A 1-D uint8 buffer as the flavour's ``Image.data`` (one copy)."""
    if types.flavour == "rclpy":
        out = array.array("B")
        out.frombytes(memoryview(np.ascontiguousarray(buf).reshape(-1)))
        return out
    return np.array(buf.reshape(-1), dtype=np.uint8, copy=True)


def numpy_to_image(
    array_: np.ndarray,
    encoding: str,
    types: MsgTypes,
    stamp_ns: int = 0,
    frame_id: str = "",
    header: Any = None,
    is_bigendian: bool = False,
    step: int | None = None,
) -> Any:
    """An Image of ``types`` holding ``array_`` (``(H, W)`` or ``(H, W, C)``).

    The array's channel count must match ``encoding``; its dtype is cast when lossless
    (integers in range, float -> float), otherwise ``ValueError``. ``step`` (bytes per row)
    defaults to the packed row size; a larger value zero-pads each row. ``header`` (a
    Header of the same flavour) overrides ``stamp_ns``/``frame_id``.
    """
    dtype, ch = encoding_info(encoding)
    a = np.asarray(array_)
    if a.ndim == 2:
        a_ch = 1
    elif a.ndim == 3:
        a_ch = a.shape[2]
    else:
        raise ValueError(f"array must be (H, W) or (H, W, C), got shape {a.shape}")
    if a_ch != ch:
        raise ValueError(f"array has {a_ch} channel(s) but Image.encoding={encoding!r} needs {ch}")
    a = _cast_for_encoding(a, dtype, encoding)
    height, width = int(a.shape[0]), int(a.shape[1])
    row = width * ch * dtype.itemsize
    step = row if step is None else int(step)
    if step < row:
        raise ValueError(f"Image.step={step} is smaller than width*bytes_per_pixel={row}")
    wire = dtype.newbyteorder(">" if is_bigendian else "<") if dtype.itemsize > 1 else dtype
    packed = np.ascontiguousarray(a, dtype=wire).reshape(height, width * ch).view(np.uint8)
    if step > row:
        padded = np.zeros((height, step), dtype=np.uint8)
        padded[:, :row] = packed
        packed = padded
    if header is None:
        header = make_header(types, stamp_ns, frame_id)
    return types.make(
        types.Image,
        header=header,
        height=height,
        width=width,
        encoding=str(encoding),
        is_bigendian=1 if is_bigendian else 0,
        step=step,
        data=_pack_data(packed, types),
    )


def depth_to_image(
    depth_m: np.ndarray,
    types: MsgTypes,
    encoding: str = "16UC1",
    stamp_ns: int = 0,
    frame_id: str = "",
    header: Any = None,
    is_bigendian: bool = False,
    depth_scale: float | None = None,
) -> Any:
    """An Image of a metric depth map ``(H, W)`` (NaN / Inf / <= 0 = no reading).

    ``16UC1``/``mono16``: ``round(depth / depth_scale)`` (default scale 0.001 -> mm),
    invalid -> 0, clipped to 65535. ``32FC1``/``64FC1``: metres, invalid -> NaN.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {d.shape}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    if encoding in _DEPTH_MM_ENCODINGS:
        scale = 0.001 if depth_scale is None else float(depth_scale)
        units = np.rint(np.where(valid, d, 0.0) / scale)
        out: np.ndarray = np.clip(units, 0, 65535).astype(np.uint16)
    elif encoding in _DEPTH_M_ENCODINGS:
        dt = np.float32 if encoding == "32FC1" else np.float64
        out = np.where(valid, d, np.nan).astype(dt)
    else:
        raise ValueError(
            f"Image.encoding={encoding!r} is not a depth encoding (expected one of "
            f"{_DEPTH_MM_ENCODINGS + _DEPTH_M_ENCODINGS})"
        )
    return numpy_to_image(
        out, encoding, types, stamp_ns=stamp_ns, frame_id=frame_id, header=header, is_bigendian=is_bigendian
    )
