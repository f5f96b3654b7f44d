"""``sensor_msgs/CameraInfo`` <-> 3x3 intrinsics, for rclpy messages and rosbags dataclasses.

Reading duck-types ROS 2 lower-case fields (``k, p, d, r``) and ROS 1 upper-case ones.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np

from .msgtypes import MsgTypes
from .stamps import make_header


def _field(msg: Any, name: str) -> tuple[Any, str]:
    for attr in (name, name.upper()):
        if hasattr(msg, attr):
            return getattr(msg, attr), attr
    raise ValueError(f"CameraInfo has no field {name!r}")


def _matrix(msg: Any, name: str, shape: tuple[int, int]) -> tuple[np.ndarray, str]:
    values, attr = _field(msg, name)
    m = np.asarray(values, dtype=np.float64).reshape(-1)
    n = shape[0] * shape[1]
    if m.size != n:
        raise ValueError(f"CameraInfo.{attr} has {m.size} values, expected {n}")
    return m.reshape(shape), attr


def _check_K(K: np.ndarray, attr: str) -> None:
    if not np.all(np.isfinite(K)):
        raise ValueError(f"CameraInfo.{attr} contains NaN or Inf: {K.reshape(-1).tolist()}")
    if not np.any(K):
        raise ValueError(f"CameraInfo.{attr} is all zero (camera not calibrated)")
    fx, fy = K[0, 0], K[1, 1]
    if not (fx > 0 and fy > 0):
        raise ValueError(f"CameraInfo.{attr} has non-positive focal length fx={fx}, fy={fy}")


def camera_info_to_K(msg: Any, rectified: bool = True, apply_binning_roi: bool = True) -> np.ndarray:
    """3x3 intrinsics of a CameraInfo.

    ``rectified=True`` uses ``P[:3, :3]`` (the rectified image's projection) when P is
    non-zero, else ``K``. With ``apply_binning_roi`` a non-trivial ROI offset is subtracted
    from the principal point and ``binning_x/y`` > 1 scales K down (pixel-centre
    convention, see :func:`scale_K`), giving the intrinsics of the published image.
    Raises ``ValueError`` naming the field for all-zero, NaN/Inf or non-positive-focal
    matrices.
    """
    K = None
    if rectified:
        P, p_attr = _matrix(msg, "p", (3, 4))
        if np.any(P != 0):  # NaN counts as non-zero and is rejected below
            K, attr = P[:, :3].copy(), p_attr
    if K is None:
        K, attr = _matrix(msg, "k", (3, 3))
        K = K.copy()
    _check_K(K, attr)
    if apply_binning_roi:
        roi = getattr(msg, "roi", None)
        if roi is not None:
            K[0, 2] -= float(getattr(roi, "x_offset", 0))
            K[1, 2] -= float(getattr(roi, "y_offset", 0))
        bx = int(getattr(msg, "binning_x", 0) or 1)
        by = int(getattr(msg, "binning_y", 0) or 1)
        if bx > 1 or by > 1:
            K = scale_K(K, 1.0 / bx, 1.0 / by)
    return K


def camera_info_size(msg: Any) -> tuple[int, int]:
    """``(width, height)`` of the image a CameraInfo describes."""
    return int(msg.width), int(msg.height)


def camera_info_distortion(msg: Any) -> tuple[str, np.ndarray]:
    """``(distortion_model, D)`` of a CameraInfo."""
    d, _ = _field(msg, "d")
    return str(getattr(msg, "distortion_model", "")), np.asarray(d, dtype=np.float64).reshape(-1)


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resized by ``(sx, sy)`` (new width = ``sx * width``).

    Pixel-centre convention: pixel ``u`` covers ``[u - 0.5, u + 0.5]``, so
    ``u' = sx * (u + 0.5) - 0.5``; focal lengths (and skew) scale by ``sx``/``sy``.
    """
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    out = K.copy()
    out[0, 0] = K[0, 0] * sx
    out[0, 1] = K[0, 1] * sx
    out[1, 1] = K[1, 1] * sy
    out[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
    out[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
    return out


def K_to_camera_info(
    K: np.ndarray,
    width: int,
    height: int,
    types: MsgTypes,
    stamp_ns: int = 0,
    frame_id: str = "",
    distortion_model: str = "plumb_bob",
    D: Any = None,
    header: Any = None,
) -> Any:
    """A CameraInfo of ``types`` for intrinsics ``K``: ``k = K``, ``r = I``, ``p = [K | 0]``.

    ``D`` defaults to zeros (5 for plumb_bob, 8 for rational_polynomial, 4 for equidistant,
    else none). ``header`` overrides ``stamp_ns``/``frame_id``.
    """
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if D is None:
        n = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}.get(distortion_model, 0)
        D = np.zeros(n)
    D = np.asarray(D, dtype=np.float64).reshape(-1)
    P = np.zeros((3, 4))
    P[:, :3] = K
    R = np.eye(3)
    if header is None:
        header = make_header(types, stamp_ns, frame_id)
    if types.flavour == "rclpy":
        d_field: Any = array.array("d", D.tolist())
    else:
        d_field = D.copy()
    return types.make(
        types.CameraInfo,
        header=header,
        height=int(height),
        width=int(width),
        distortion_model=str(distortion_model),
        d=d_field,
        k=K.reshape(-1).copy(),
        r=R.reshape(-1),
        p=P.reshape(-1),
    )
