"""Walk-through sequences: one generated room, a camera walking and panning through it.

``walkthrough(seed, frames)`` builds one room with :func:`.layout.build_scene`, plans a
smooth walk (a few waypoints in free floor space, eased between) at a hand-held height
while the view pans from object to object, and renders each view with
:func:`.generate.render_view` (noisy RGB-D, per-frame camera-frame ground truth).

Frames and transforms (metres, stamps int ns):

* world: the room's frame, z up, floor at z = 0 (:mod:`.layout`); published as ``odom``;
* ``T_world_camera`` (4x4): camera **optical** frame (x right, y down, z forward) -> world,
  ``p_world = R @ p_cam + t`` with ``t`` the camera centre;
* for bags: ``odom -> camera_link`` per frame (:func:`link_poses`; ``camera_link`` is x
  forward, y left, z up) and the static ``camera_link -> camera_color_optical_frame``
  (:data:`T_LINK_OPTICAL`: zero translation, the usual ROS optical rotation: optical z =
  link x, optical x = -link y, optical y = -link z), so that
  ``T_world_camera = T_world_link @ T_LINK_OPTICAL``.

Seeds draw from ``SeedSequence([seed, WALK_TAG])``: walk-throughs never share a random
stream with :func:`.generate.generate_frame` (training data), whatever the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..types import Cuboid, Frame, GTObject
from . import render as rd
from .camera import Camera, _blocked, rotation_from_ypr, sample_intrinsics
from .generate import STAMP0_NS, SynthConfig, _scene_arrays, render_view
from .layout import Scene, build_scene, rotz
from .noise import NoiseParams

#: mixed into the seed so walk-throughs never share streams with single generated frames
WALK_TAG = 0x5CE7E
WORLD_FRAME = "odom"
LINK_FRAME = "camera_link"
OPTICAL_FRAME = "camera_color_optical_frame"
#: camera_link -> camera_color_optical_frame (columns: optical axes in link coordinates)
T_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


@dataclass
class Walkthrough:
    """One walk-through: ``frames[i]`` seen from ``poses[i]`` (T_world_camera, 4x4);
    ``gt_world`` every labelled object of the room in the world frame (with parts)."""

    frames: list[Frame]
    poses: list[np.ndarray]
    gt_world: list[GTObject]
    scene: Scene | None = field(default=None, repr=False)

    @property
    def stamps_ns(self) -> list[int]:
        """Stamp of each frame, int ns."""
        return [int(f.stamp_ns) for f in self.frames]


def _waypoints(scene: Scene, rng: np.random.Generator, n: int = 3, clearance: float = 0.45) -> np.ndarray:
    """(n, 2) waypoints on free floor, each leg free of furniture; the legs are long enough
    to pass several objects."""
    free = [p for p in (np.array([rng.uniform(0.3, scene.rx - 0.3), rng.uniform(0.3, scene.ry - 0.3)])
                        for _ in range(300)) if not _blocked(scene, p, 0.3, clearance)]
    if not free:
        return np.tile([scene.rx / 2, scene.ry / 2], (n, 1))
    pts = [free[int(rng.integers(len(free)))]]
    for _ in range(n - 1):
        best, best_d = None, -1.0
        for q in free:  # far from every earlier waypoint: the walk goes on rather than back
            d = min(float(np.linalg.norm(q - p)) for p in pts)
            if d > best_d and float(np.linalg.norm(q - pts[-1])) < 3.0 and _leg_free(scene, pts[-1], q):
                best, best_d = q, d
        pts.append(best if best is not None else pts[-1])
    return np.stack(pts)


def _leg_free(scene: Scene, a: np.ndarray, b: np.ndarray) -> bool:
    steps = max(2, int(np.linalg.norm(b - a) / 0.1))
    return not any(_blocked(scene, a + (b - a) * t, 0.25, 0.25) for t in np.linspace(0, 1, steps))


def _ease(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def _path(way: np.ndarray, n: int, max_len: float) -> np.ndarray:
    """(n, 2) positions along the waypoint legs (their first ``max_len`` metres), eased at
    each waypoint, spaced by length."""
    seg = np.linalg.norm(np.diff(way, axis=0), axis=1)
    total = min(float(seg.sum()), max_len)
    if total < 1e-6:
        return np.tile(way[0], (n, 1))
    s = np.linspace(0.0, total, n)
    out = np.zeros((n, 2))
    edges = np.concatenate([[0.0], np.cumsum(seg)])
    for i, si in enumerate(s):
        k = min(int(np.searchsorted(edges, si, side="right")) - 1, len(seg) - 1)
        t = (si - edges[k]) / max(seg[k], 1e-9)
        out[i] = way[k] + (way[k + 1] - way[k]) * _ease(np.clip(t, 0.0, 1.0))
    return out


def _object_centres(scene: Scene) -> np.ndarray:
    out = []
    for p in scene.objects:
        lo, hi = p.model.bounds()
        c = p.pos + rotz(p.yaw) @ (0.5 * (lo + hi))
        out.append([c[0], c[1], p.pos[2] + 0.5 * (hi[2] - lo[2])])
    return np.asarray(out, dtype=np.float64).reshape(-1, 3)


def plan_poses(scene: Scene, rng: np.random.Generator, n: int, dt: float = 0.2,
               height: tuple[float, float] = (1.1, 1.6), speed: tuple[float, float] = (0.25, 0.45)) \
        -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` camera poses ``dt`` seconds apart (centre C (3,), R_wc (3,3) columns = optical
    axes in the world): a walk through free floor at a walking ``speed`` (m/s) while the view
    pans smoothly over the room's objects (each in turn, ordered by bearing from the walk's middle)."""
    path = _path(_waypoints(scene, rng), n, rng.uniform(*speed) * dt * max(n - 1, 1))
    h = rng.uniform(*height)
    targets = _object_centres(scene)
    if len(targets) == 0:
        targets = np.array([[scene.rx / 2, scene.ry / 2, 0.5]])
    mid = path[n // 2]
    order = np.argsort(np.arctan2(targets[:, 1] - mid[1], targets[:, 0] - mid[0]))
    targets = targets[order]
    if rng.random() < 0.5:
        targets = targets[::-1]
    roll0 = rng.normal(0, np.radians(1.5))
    out = []
    for i in range(n):
        s = (len(targets) - 1) * i / max(n - 1, 1)
        k = min(int(np.floor(s)), len(targets) - 2) if len(targets) > 1 else 0
        f = _ease(np.array(s - k)) if len(targets) > 1 else 0.0
        tg = targets[k] if len(targets) == 1 else targets[k] + (targets[k + 1] - targets[k]) * f
        C = np.array([path[i, 0], path[i, 1], h + 0.02 * np.sin(1.7 * i / 5.0)])
        d = tg - C
        if np.linalg.norm(d[:2]) < 0.3:  # target right under the camera: keep looking ahead
            d[:2] = (path[min(i + 1, n - 1)] - path[max(i - 1, 0)]) + 1e-3
        yaw = float(np.arctan2(d[1], d[0]))
        pitch = float(np.clip(0.75 * np.arctan2(d[2], np.linalg.norm(d[:2])) - 0.08, np.radians(-50), np.radians(10)))
        roll = roll0 + np.radians(0.5) * np.sin(2.7 * i / 5.0)
        out.append((C, rotation_from_ypr(yaw, pitch, roll)))
    return out


def world_gt(scene: Scene) -> list[GTObject]:
    """Every labelled object of ``scene`` in the world frame (z up), with its parts;
    ``instance_id`` = its value in the frames' instance masks."""
    out = []
    for i, p in enumerate(scene.objects):
        lo, hi = p.model.bounds()
        R = rotz(p.yaw)
        pc, ps, _, _ = p.cuboids()
        out.append(GTObject(class_name=p.model.name, box2d=(0.0, 0.0, 0.0, 0.0), center=p.pos + R @ (0.5 * (lo + hi)),
                            size=hi - lo, rotation=R, heading=float(p.yaw),
                            parts=[Cuboid(c, s, R) for c, s in zip(pc, ps)], instance_id=i + 1))
    return out


def pose_matrix(C: np.ndarray, R_wc: np.ndarray) -> np.ndarray:
    """T_world_camera (4x4) of a camera centre and its optical axes (columns of ``R_wc``)."""
    T = np.eye(4)
    T[:3, :3] = R_wc
    T[:3, 3] = C
    return T


def walkthrough(seed: int, frames: int = 40, rate_hz: float = 5.0, config: SynthConfig | None = None,
                min_objects: int = 4) -> Walkthrough:
    """A rendered walk-through of ``frames`` frames at ``rate_hz`` (deterministic in
    ``seed``; see the module docstring). ``config`` sets resolution, noise and clutter
    (its ``min_objects`` is raised to ``min_objects``)."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    cfg = config or SynthConfig()
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, WALK_TAG])
    r_scene, r_cam, r_render, r_noise = (np.random.default_rng(s) for s in ss.spawn(4))
    scene = build_scene(r_scene, max(cfg.min_objects, min_objects), max(cfg.max_objects, min_objects),
                        cfg.room_type, cfg.clutter)
    K = sample_intrinsics(r_cam, cfg.width, cfg.height)
    poses = plan_poses(scene, r_cam, frames, 1.0 / rate_hz)
    cfg2 = replace(cfg, noise_params=cfg.noise_params or NoiseParams.sample(r_noise))
    arrays = _scene_arrays(scene)
    response = rd.Response.sample(r_render, cfg.jpeg)
    period = int(round(1e9 / rate_hz))
    out_frames, mats = [], []
    for i, (C, R) in enumerate(poses):
        cam = Camera(K, cfg.width, cfg.height, C, R)
        out_frames.append(render_view(scene, cam, r_render, r_noise, cfg2, STAMP0_NS + i * period, arrays, response))
        mats.append(pose_matrix(C, R))
    return Walkthrough(out_frames, mats, world_gt(scene), scene)


def camera_poses(wt: Walkthrough) -> list[tuple[int, np.ndarray]]:
    """Per frame: (stamp_ns, T_world_camera (4x4), optical frame -> world)."""
    return [(int(f.stamp_ns), T.copy()) for f, T in zip(wt.frames, wt.poses)]


def link_poses(wt: Walkthrough) -> list[tuple[int, np.ndarray]]:
    """Per frame: (stamp_ns, T_world_link (4x4)), ``odom -> camera_link`` for ``/tf`` and
    ``/odom``; ``T_world_link @ T_LINK_OPTICAL`` is the frame's ``T_world_camera``."""
    inv = np.linalg.inv(T_LINK_OPTICAL)
    return [(s, T @ inv) for s, T in camera_poses(wt)]
