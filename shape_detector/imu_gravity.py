"""Gravity-up from an accelerometer: a stamp-aware first-order low-pass filter.

A resting accelerometer measures the specific force, which points *up* (away from the
ground) with magnitude g; low-passing it removes hand shake and vibration. The result is
rotated into the camera optical frame with a fixed ``imu_to_camera`` rotation (identity
when the IMU already reports in the camera optical frame) and normalised.

Pure numpy, no ROS: the node feeds it ``sensor_msgs/Imu.linear_acceleration`` samples.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

G = 9.80665


def quaternion_to_matrix(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion given as ``(x, y, z, w)`` (ROS order); normalised
    first. Raises ValueError for a zero-length or non-finite quaternion."""
    qa = np.asarray(q, dtype=np.float64).reshape(-1)
    if qa.shape != (4,):
        raise ValueError(f"quaternion must have 4 values (x, y, z, w), got {qa.size}")
    n = float(np.linalg.norm(qa))
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"quaternion must be finite and non-zero, got {qa.tolist()}")
    x, y, z, w = qa / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


class ImuGravityFilter:
    """Low-passed gravity-up vector in the camera optical frame.

    ``time_constant`` (s): the filter's time constant; a sample ``dt`` after the previous
    one is blended with weight ``1 - exp(-dt / time_constant)`` (a sample without a
    usable stamp difference uses ``default_dt``). Samples whose magnitude differs from
    g by more than ``max_deviation * g`` (strong motion) or that are not finite are
    rejected (counted in :attr:`rejected`). ``imu_to_camera``: rotation (3x3 matrix or
    ``(x, y, z, w)`` quaternion) mapping IMU-frame vectors into the camera optical frame.
    """

    def __init__(
        self,
        time_constant: float = 0.5,
        imu_to_camera: Sequence[float] | np.ndarray | None = None,
        max_deviation: float = 0.5,
        default_dt: float = 0.01,
        min_samples: int = 1,
    ) -> None:
        self.time_constant = float(time_constant)
        if not self.time_constant >= 0.0:
            raise ValueError(f"time_constant must be >= 0, got {time_constant}")
        self.max_deviation = float(max_deviation)
        self.default_dt = float(default_dt)
        self.min_samples = max(1, int(min_samples))
        self.set_imu_to_camera(imu_to_camera)
        self._acc: np.ndarray | None = None
        self._last_stamp: int | None = None
        self.samples = 0
        self.rejected = 0

    def set_imu_to_camera(self, rotation: Sequence[float] | np.ndarray | None) -> None:
        """Set the IMU -> camera rotation (None or empty = identity)."""
        if rotation is None or len(np.asarray(rotation).reshape(-1)) == 0:
            self.R = np.eye(3)
            return
        arr = np.asarray(rotation, dtype=np.float64)
        if arr.shape == (3, 3):
            if not np.allclose(arr @ arr.T, np.eye(3), atol=1e-3):
                raise ValueError("imu_to_camera matrix is not a rotation")
            self.R = arr
        else:
            self.R = quaternion_to_matrix(arr)

    def reset(self) -> None:
        """Forget the filtered vector, the last stamp and the sample count (e.g. after a time jump)."""
        self._acc = None
        self._last_stamp = None
        self.samples = 0

    def update(self, accel: Sequence[float], stamp_ns: int | None = None) -> bool:
        """Feed one accelerometer sample (m/s^2, IMU frame); returns whether it was used."""
        a = np.asarray(accel, dtype=np.float64).reshape(-1)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            self.rejected += 1
            return False
        mag = float(np.linalg.norm(a))
        if mag < 1e-6 or abs(mag - G) > self.max_deviation * G:
            self.rejected += 1
            return False
        if self._acc is None:
            self._acc = a.copy()
        else:
            dt = self.default_dt
            if stamp_ns is not None and self._last_stamp is not None:
                d = (int(stamp_ns) - self._last_stamp) * 1e-9
                if d > 0:
                    dt = d
                elif d < 0:  # out of order: treat as a default-spaced sample
                    dt = self.default_dt
            alpha = 1.0 if self.time_constant == 0.0 else 1.0 - math.exp(-dt / self.time_constant)
            self._acc += alpha * (a - self._acc)
        if stamp_ns is not None:
            self._last_stamp = int(stamp_ns) if self._last_stamp is None else max(self._last_stamp, int(stamp_ns))
        self.samples += 1
        return True

    @property
    def ready(self) -> bool:
        """Whether at least ``min_samples`` accepted samples have been filtered."""
        return self._acc is not None and self.samples >= self.min_samples

    @property
    def up(self) -> np.ndarray | None:
        """Unit gravity-up vector in the camera optical frame, or None before any sample."""
        if not self.ready:
            return None
        v = self.R @ self._acc
        n = float(np.linalg.norm(v))
        if n < 1e-9:
            return None
        return v / n

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp (int ns) of the last accepted sample, or None."""
        return self._last_stamp
