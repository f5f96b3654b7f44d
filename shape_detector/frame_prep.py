"""Frame preparation, shared by the live node and the bag replay: a synchronised message set
(colour image, depth image, camera_info, optional Detection2DArray) -> ``rgb, depth (m, NaN
invalid), K`` with size checks, intrinsics rescaling, and a :class:`FrameError` that says what is
wrong for input that cannot be used.

Messages of either flavour (rclpy or rosbags) are read by duck typing; nothing here imports
rclpy, rosbags or other offline code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .sync import header_stamp_ns


class FrameError(ValueError):
    """A synchronised message set that cannot be turned into a frame; ``kind`` is a short
    machine-readable reason (``camera_info``, ``encoding``, ``size``, ``empty``...)."""

    def __init__(self, kind: str, message: str) -> None:
        self.kind = kind
        super().__init__(message)


@dataclass
class PreparedFrame:
    """A frame ready for ``ShapeDetector.detect``: RGB ``(H, W, 3)`` uint8, depth
    ``(H, W)`` float32 metres (NaN = invalid), intrinsics ``K`` of that resolution,
    ``boxes2d`` (external proposals, scaled to that resolution) and ``notes`` about
    non-fatal fixes (rescaled intrinsics, invalid depth...)."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    stamp_ns: int
    frame_id: str
    boxes2d: list | None = None
    notes: list[str] = field(default_factory=list)
    valid_depth_fraction: float = 1.0


def _size_str(w: int, h: int) -> str:
    return f"{w}x{h}"


def _same_aspect(w1: int, h1: int, w2: int, h2: int, tol: float = 0.02) -> bool:
    return abs((w1 / h1) / (w2 / h2) - 1.0) <= tol


def prepare_frame(
    image: Any,
    depth: Any,
    camera_info: Any,
    *,
    depth_scale: float | None = None,
    size_mismatch: str = "rescale",
    detections2d: Any = None,
) -> PreparedFrame:
    """Turn an (image, depth, camera_info) message set into a :class:`PreparedFrame`.

    * ``depth_scale``: metres per raw unit for integer depth (None/0 = by encoding:
      16UC1 millimetres, 32FC1 metres); NaN / Inf / <= 0 depth becomes NaN.
    * camera_info of another resolution than the colour image (same aspect ratio):
      intrinsics rescaled. Depth of another resolution than the colour image: with
      ``size_mismatch='rescale'`` (and the same aspect ratio) the colour image is resized
      to the depth resolution and K scaled; with ``'skip'`` (or different aspect ratios)
      a :class:`FrameError` naming both sizes.
    * ``detections2d``: a vision_msgs Detection2DArray giving external 2D proposals.

    Raises :class:`FrameError` for missing camera_info, unusable encodings, all-zero /
    non-finite K, empty images and irreconcilable sizes.
    """
    if size_mismatch not in ("rescale", "skip"):
        raise ValueError(f"size_mismatch must be 'rescale' or 'skip', got {size_mismatch!r}")
    if image is None or depth is None:
        raise FrameError("missing", "colour or depth image missing")
    stamp = header_stamp_ns(image)
    frame_id = str(getattr(getattr(image, "header", None), "frame_id", "") or "")
    if camera_info is None:
        raise FrameError("camera_info", "no camera_info received yet: cannot interpret the images without intrinsics")
    notes: list[str] = []
    rgb, dep, K = _decode(image, depth, camera_info, depth_scale, size_mismatch, notes)
    boxes2d = _external_boxes(detections2d)
    rgb, K, boxes2d = _match_depth_size(rgb, dep, K, boxes2d, size_mismatch, notes)
    valid = np.isfinite(dep)
    frac = float(valid.mean()) if dep.size else 0.0
    if frac == 0.0:
        notes.append("depth image has no valid pixels")
    return PreparedFrame(
        rgb=np.ascontiguousarray(rgb),
        depth=dep,
        K=K,
        stamp_ns=int(stamp or 0),
        frame_id=frame_id,
        boxes2d=boxes2d,
        notes=notes,
        valid_depth_fraction=frac,
    )


def _decode(image: Any, depth: Any, camera_info: Any, depth_scale: float | None, size_mismatch: str,
            notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rgb, depth m, K of the colour size)``; camera_info of another size is rescaled (a note)."""
    from msg_conversion.camera_info import camera_info_size, camera_info_to_K, scale_K
    from msg_conversion.image import image_to_depth, image_to_rgb

    for name, msg in (("colour", image), ("depth", depth)):
        try:
            w, h = int(msg.width), int(msg.height)
        except (AttributeError, TypeError, ValueError) as e:
            raise FrameError("malformed", f"{name} image has no valid width/height: {e}") from None
        if w <= 0 or h <= 0:
            raise FrameError("empty", f"{name} image is empty ({_size_str(w, h)})")
    try:
        rgb = image_to_rgb(image)
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("encoding", f"colour image unusable: {e}") from None
    try:
        dep = image_to_depth(depth, depth_scale if depth_scale else None)
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("encoding", f"depth image unusable: {e}") from None
    try:
        K = camera_info_to_K(camera_info)
        ci_w, ci_h = camera_info_size(camera_info)
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("camera_info", f"camera_info unusable: {e}") from None
    h, w = rgb.shape[:2]
    if ci_w > 0 and ci_h > 0 and (ci_w, ci_h) != (w, h):
        if not _same_aspect(ci_w, ci_h, w, h) or size_mismatch == "skip":
            raise FrameError(
                "size",
                f"camera_info is {_size_str(ci_w, ci_h)} but the colour image is {_size_str(w, h)} "
                + ("(different aspect ratio, cannot rescale the intrinsics)" if size_mismatch == "rescale" else "(size_mismatch=skip)"),
            )
        K = scale_K(K, w / ci_w, h / ci_h)
        notes.append(f"camera_info is {_size_str(ci_w, ci_h)}, colour image {_size_str(w, h)}: intrinsics rescaled")
    return rgb, dep, K


def _external_boxes(detections2d: Any) -> list | None:
    """External 2D proposals of a Detection2DArray (None when not given)."""
    if detections2d is None:
        return None
    from msg_conversion.detections import detection2d_array_to_boxes

    try:
        return list(detection2d_array_to_boxes(detections2d))
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("detections2d", f"Detection2DArray unusable: {e}") from None


def _match_depth_size(rgb: np.ndarray, dep: np.ndarray, K: np.ndarray, boxes2d: list | None, size_mismatch: str,
                      notes: list[str]) -> tuple[np.ndarray, np.ndarray, list | None]:
    """Colour resized to the depth's size (same aspect ratio, ``size_mismatch='rescale'``), K and boxes scaled."""
    import cv2

    from msg_conversion.camera_info import scale_K

    h, w = rgb.shape[:2]
    dh, dw = dep.shape[:2]
    if (dw, dh) == (w, h):
        return rgb, K, boxes2d
    if size_mismatch == "skip" or not _same_aspect(dw, dh, w, h):
        why = "(size_mismatch=skip)" if size_mismatch == "skip" else "(different aspect ratio, cannot rescale)"
        raise FrameError("size", f"depth image is {_size_str(dw, dh)} but the colour image is {_size_str(w, h)} {why}")
    sx, sy = dw / w, dh / h
    interp = cv2.INTER_AREA if sx < 1.0 else cv2.INTER_LINEAR
    rgb = cv2.resize(rgb, (dw, dh), interpolation=interp)
    K = scale_K(K, sx, sy)
    if boxes2d is not None:
        boxes2d = [(b[0] * sx, b[1] * sy, b[2] * sx, b[3] * sy, *b[4:]) for b in boxes2d]
    notes.append(
        f"depth image is {_size_str(dw, dh)}, colour image {_size_str(w, h)}: colour resized to "
        f"{_size_str(dw, dh)} and intrinsics rescaled"
    )
    return rgb, K, boxes2d


__all__ = ["FrameError", "PreparedFrame", "prepare_frame"]
