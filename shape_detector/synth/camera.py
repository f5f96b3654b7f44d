"""Camera intrinsics and pose sampling (hand-held / robot RGB-D cameras in a room).

World frame: z up (see :mod:`shape_detector.synth.layout`). A pose is the camera centre
``C`` (world) and ``R_wc`` whose columns are the optical axes (x right, y down, z forward)
in world coordinates, so ``p_cam = R_wc.T @ (p_world - C)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .layout import Scene, rotz


@dataclass
class Camera:
    """A pinhole RGB-D camera: intrinsics ``K`` (3x3, px), image size (px), centre ``C`` (world, m) and ``R_wc``
    (columns = optical axes in world)."""

    K: np.ndarray
    width: int
    height: int
    C: np.ndarray
    R_wc: np.ndarray

    def to_cam(self, p: np.ndarray) -> np.ndarray:
        """World points (...,3) to the camera optical frame."""
        return (np.asarray(p) - self.C) @ self.R_wc

    @property
    def up(self) -> np.ndarray:
        """Gravity-up unit vector in the camera optical frame."""
        return self.R_wc.T @ np.array([0.0, 0.0, 1.0])


def sample_intrinsics(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Pinhole K near Kinect v1/v2 / RealSense values (scaled to the resolution), jittered."""
    s = width / 640.0
    fx = rng.uniform(500.0, 620.0) * s
    fy = fx * rng.uniform(0.995, 1.005)
    cx = (width - 1) / 2.0 + rng.normal(0, 5.0) * s
    cy = (height - 1) / 2.0 + rng.normal(0, 5.0) * s
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def rotation_from_ypr(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``R_wc`` for a camera looking along heading ``yaw`` (world), ``pitch`` up (+) / down (-), ``roll``."""
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    r = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    d = np.cross(f, r)
    cr, sr = np.cos(roll), np.sin(roll)
    r2 = r * cr + d * sr
    d2 = -r * sr + d * cr
    return np.stack([r2, d2, f], axis=1)


def _blocked(scene: Scene, xy: np.ndarray, margin: float, clearance: float = 0.4) -> bool:
    if not (margin <= xy[0] <= scene.rx - margin and margin <= xy[1] <= scene.ry - margin):
        return True
    for p in scene.objects + scene.clutter:
        if p.model.name == "rug":
            continue
        c, half, yaw = p.footprint()
        local = rotz(-yaw)[:2, :2] @ (xy - c)
        if np.all(np.abs(local) <= half + clearance):
            return True
    return False


def look_at_pose(C: np.ndarray, target: np.ndarray, rng: np.random.Generator, yaw_sd: float = 0.2,
                 pitch_sd: float = 0.1) -> np.ndarray:
    """``R_wc`` looking from ``C`` towards ``target`` (world, m) with random heading / pitch / roll jitter (rad)."""
    d = target - C
    yaw = float(np.arctan2(d[1], d[0])) + rng.normal(0, yaw_sd)
    pitch = 0.75 * float(np.arctan2(d[2], np.linalg.norm(d[:2]))) + rng.normal(-0.06, pitch_sd)
    pitch = float(np.clip(pitch, np.radians(-55), np.radians(20)))
    roll = rng.normal(0, np.radians(2.5)) if rng.random() < 0.85 else rng.normal(0, np.radians(8))
    return rotation_from_ypr(yaw, pitch, float(roll))


def sample_pose(scene: Scene, rng: np.random.Generator, height_range: tuple[float, float] = (0.8, 1.8),
                dist_range: tuple[float, float] = (1.0, 5.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera centre, ``R_wc`` and the world look-at target (a labelled object, seen mostly from its front)."""
    h = float(np.clip(rng.triangular(height_range[0], 1.3, height_range[1]), *height_range))
    objs = scene.objects
    target = np.array([scene.rx / 2, scene.ry / 2, 0.5])
    facing = None
    dmin = dist_range[0]
    if objs:
        o = objs[int(rng.integers(len(objs)))]
        lo, hi = o.model.bounds()
        c = o.pos + rotz(o.yaw) @ (0.5 * (lo + hi))
        target = np.array([c[0], c[1], o.pos[2] + (hi[2] - lo[2]) * rng.uniform(0.2, 0.7)])
        facing = o.yaw
        dmin = max(dist_range[0], 0.5 * float(np.linalg.norm((hi - lo)[:2])) + 0.7)
        if rng.random() < 0.4 and len(objs) > 1:  # look between two objects
            o2 = objs[int(rng.integers(len(objs)))]
            c2 = o2.pos + rotz(o2.yaw) @ (0.5 * np.sum(o2.model.bounds(), axis=0))
            target[:2] = 0.5 * (target[:2] + c2[:2])
    C = None
    for i in range(80):
        d = float(rng.triangular(dmin, max(2.6, dmin), max(dist_range[1], dmin + 0.5))) if i < 40 \
            else rng.uniform(0.8, 3.0)
        if facing is not None and rng.random() < 0.8 and i < 60:
            ang = facing + rng.uniform(-1.4, 1.4)
        else:
            ang = rng.uniform(-np.pi, np.pi)
        xy = target[:2] + d * np.array([np.cos(ang), np.sin(ang)])
        if not _blocked(scene, xy, 0.25, 0.45 if i < 50 else 0.2):
            C = np.array([xy[0], xy[1], h])
            break
    if C is None:  # fall back to any free spot, relaxing the clearance
        for j in range(300):
            xy = np.array([rng.uniform(0.25, scene.rx - 0.25), rng.uniform(0.25, scene.ry - 0.25)])
            if not _blocked(scene, xy, 0.25, 0.3 if j < 150 else 0.0):
                break
        C = np.array([xy[0], xy[1], h])
    return C, look_at_pose(C, target, rng), target


def trajectory(scene: Scene, rng: np.random.Generator, n: int, dt: float,
               height_range: tuple[float, float] = (0.8, 1.8)) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` smooth poses (hand-held walk / pan around a target) sampled every ``dt`` s.

    The walk keeps clear of furniture (resampled a few times, else the camera stands still).
    """
    C0, _, target = sample_pose(scene, rng, height_range)
    roll0 = rng.normal(0, np.radians(2.0))
    tvel = rng.normal(0, 0.15, 3) * np.array([1, 1, 0.2])
    vel = np.zeros(3)
    for _ in range(20):
        speed = rng.uniform(0.1, 0.35)
        ang = rng.uniform(-np.pi, np.pi)
        v = speed * np.array([np.cos(ang), np.sin(ang), 0.0])
        if not any(_blocked(scene, (C0 + v * i * dt)[:2], 0.25, 0.3) for i in range(n)):
            vel = v
            break
    out = []
    for i in range(n):
        t = i * dt
        C = C0 + vel * t
        tg = target + tvel * t
        d = tg - C
        yaw = float(np.arctan2(d[1], d[0])) + np.radians(1.0) * np.sin(2.1 * t)
        pitch = 0.75 * float(np.arctan2(d[2], np.linalg.norm(d[:2]))) - 0.06 + np.radians(0.8) * np.sin(3.3 * t + 1)
        roll = roll0 + np.radians(0.6) * np.sin(2.7 * t + 2)
        out.append((C.copy(), rotation_from_ypr(yaw, pitch, roll)))
    return out


__all__ = ["Camera", "sample_intrinsics", "rotation_from_ypr", "sample_pose", "trajectory", "look_at_pose"]
