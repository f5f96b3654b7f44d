"""Camera poses as an odometry or VIO system would report them: drift and jitter.

The scene map is evaluated with the walk-throughs' true poses; a robot's odometry or an AR
framework's visual-inertial tracking reports poses that drift with the distance travelled and
jitter from frame to frame. :func:`noisy_poses` turns true ``T_world_camera`` poses (world
frame z up, metres) into such reports:

* **drift**: a translation error that grows linearly with the distance the camera has
  travelled (``drift`` metres per metre, along one random horizontal direction per sequence),
  and a heading error about gravity (``yaw_drift_deg`` degrees per metre, one random sign per
  sequence) about the first camera position. Gravity stays right: inertial tracking observes it.
* **jitter**: independent per-frame Gaussian noise of the position (``jitter`` m per axis)
  and orientation (``jitter_deg`` per axis, a small rotation in the camera frame), which
  also tilts the gravity the pose gives the detector.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import rot_z


@dataclass(frozen=True)
class PoseNoise:
    """Pose error model (see the module docstring); all zero: the true poses."""

    #: translation drift, metres per metre travelled
    drift: float = 0.0
    #: heading drift about gravity, degrees per metre travelled
    yaw_drift_deg: float = 0.0
    #: per-frame position noise, metres (standard deviation per axis)
    jitter: float = 0.0
    #: per-frame orientation noise, degrees (standard deviation per axis)
    jitter_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drift", "yaw_drift_deg", "jitter", "jitter_deg"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"PoseNoise.{name} must be a finite number >= 0, got {v!r}")

    @property
    def is_zero(self) -> bool:
        """True when every error is zero."""
        return not (self.drift or self.yaw_drift_deg or self.jitter or self.jitter_deg)


def travelled(poses: Sequence[np.ndarray]) -> np.ndarray:
    """(N,) distance the camera centre has travelled up to each pose, metres."""
    if not poses:
        return np.zeros(0)
    c = np.stack([np.asarray(T, dtype=np.float64)[:3, 3] for T in poses])
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])


def noisy_poses(poses: Sequence[np.ndarray], noise: PoseNoise, seed: int = 0) -> list[np.ndarray]:
    """``poses`` ((4,4) ``T_world_camera``, world z up) with ``noise`` applied; the same
    ``seed`` gives the same errors. Zero noise returns copies of the poses."""
    out = [np.array(T, dtype=np.float64) for T in poses]
    if noise.is_zero or not out:
        return out
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    direction = np.array([np.cos(phi), np.sin(phi), 0.0])
    yaw_sign = 1.0 if rng.random() < 0.5 else -1.0
    s = travelled(out)
    pivot = out[0][:3, 3].copy()
    for T, dist in zip(out, s):
        yaw = yaw_sign * np.radians(noise.yaw_drift_deg) * dist
        Rz = rot_z(yaw)
        R, t = T[:3, :3].copy(), T[:3, 3].copy()
        R, t = Rz @ R, Rz @ (t - pivot) + pivot + noise.drift * dist * direction
        if noise.jitter_deg:
            R = R @ cv2.Rodrigues(rng.normal(0.0, np.radians(noise.jitter_deg), 3))[0]
        if noise.jitter:
            t = t + rng.normal(0.0, noise.jitter, 3)
        T[:3, :3], T[:3, 3] = R, t
    return out


def parse_pose_noise(text: str) -> PoseNoise:
    """``"drift,yaw_drift_deg,jitter,jitter_deg"`` (e.g. ``"0.01,0.5,0.005,0.2"``) as a
    :class:`PoseNoise`; ValueError naming the problem."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 4:
        raise ValueError(f"pose noise needs 4 numbers drift,yaw_drift_deg,jitter,jitter_deg; got {text!r}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"pose noise must be 4 numbers, got {text!r}") from None
    return PoseNoise(*values)
