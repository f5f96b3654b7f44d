"""Generate one synthetic RGB-D frame (or a sequence) with full ground truth.

``generate_frame(seed, config)`` is deterministic in ``seed``: the scene, the camera, the
rendering randomness and the sensor noise each draw from their own child stream of
``np.random.SeedSequence(seed)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import rotation_to_heading
from ..types import Cuboid, Frame, GTObject
from . import render as rd
from . import textures as tx
from .camera import Camera, sample_intrinsics, sample_pose, trajectory
from .layout import Scene, build_scene, rotz
from .noise import NoiseParams, apply_depth_noise

FRAME_ID = "camera_color_optical_frame"
#: bump whenever a seed renders a different frame (new layout rules, materials, camera, noise):
#: data-set indexes record it, and training caches are keyed by it
GENERATOR_VERSION = 1
STAMP0_NS = 1_700_000_000_000_000_000
CLUTTER_OWNER = 1000


@dataclass
class SynthConfig:
    """Generator settings. ``min_objects``/``max_objects`` bound the labelled objects in the room
    (not all of them are in view)."""

    width: int = 640
    height: int = 480
    noise: bool = True
    min_objects: int = 2
    max_objects: int = 12
    clutter: float = 1.0  # clutter amount multiplier (0 = none)
    camera_height: tuple[float, float] = (0.8, 1.8)
    room_type: str | None = None
    jpeg: bool = True  # JPEG-compress part of the RGB frames (artefacts like Kinect datasets)
    near: float = 0.05
    min_clutter_pixels: int = 30  # clutter_boxes: only items with at least this many visible pixels
    stamp0_ns: int = STAMP0_NS
    period_ns: int = 200_000_000  # generate_frame(seed) stamps: stamp0 + seed * period
    noise_params: NoiseParams | None = None  # fixed sensor model; None samples one per frame
    extra: dict = field(default_factory=dict)


def _streams(seed: int) -> list[np.random.Generator]:
    ss = np.random.SeedSequence(int(seed) & 0xFFFFFFFFFFFFFFFF)
    return [np.random.default_rng(s) for s in ss.spawn(4)]


def _scene_arrays(scene: Scene):
    cen, siz, rot, mats, own = [], [], [], [], []
    for st in scene.structure:
        cen.append(st.center[None])
        siz.append(st.size[None])
        rot.append(st.R[None])
        mats.append(st.mat.as_row()[None])
        own.append(np.zeros(1, np.int64))
    for code0, lst in ((1, scene.objects), (CLUTTER_OWNER, scene.clutter)):
        for i, p in enumerate(lst):
            c, s, R, ms = p.cuboids()
            cen.append(c)
            siz.append(s)
            rot.append(np.broadcast_to(R, (len(c), 3, 3)))
            mats.append(np.stack([m.as_row() for m in ms]))
            own.append(np.full(len(c), code0 + i, np.int64))
    return (np.concatenate(cen), np.concatenate(siz), np.concatenate(rot), np.concatenate(mats).astype(np.float32),
            np.concatenate(own))


def _mask_box(mask: np.ndarray) -> tuple[float, float, float, float]:
    """Pixel-edge bounding box (x1, y1, x2, y2) of a non-empty boolean mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return (float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1))


def render_view(scene: Scene, cam: Camera, rng: np.random.Generator, noise_rng: np.random.Generator,
                config: SynthConfig, stamp_ns: int = 0, arrays=None, response: rd.Response | None = None) -> Frame:
    """Render ``scene`` from ``cam`` into a :class:`Frame` with ground truth.

    ``response``: fixed camera response (exposure target, white balance ...); None samples one.
    """
    W, H, K = cam.width, cam.height, cam.K
    cen, siz, rot, mats, own = arrays if arrays is not None else _scene_arrays(scene)
    Rw = cam.R_wc
    cen_c = (cen - cam.C) @ Rw
    rot_c = np.einsum("ji,njk->nik", Rw, rot)
    depth, fid, faces = rd.rasterize(cen_c, siz, rot_c, K, W, H, config.near)
    up = cam.up
    # instance ids / owners per pixel
    face_own = np.append(own[faces.cuboid], 0).astype(np.int32)  # index -1 (no face) -> owner 0
    owner_pix = face_own[fid]
    inst = np.where(owner_pix < CLUTTER_OWNER, owner_pix, 0).astype(np.int32)
    # ground truth objects
    objects: list[GTObject] = []
    counts = np.bincount(inst.ravel(), minlength=len(scene.objects) + 1)
    corners = None
    for i, p in enumerate(scene.objects):
        iid = i + 1
        if counts[iid] == 0:
            continue
        box2d = _mask_box(inst == iid)
        lo, hi = p.model.bounds()
        Rz = rotz(p.yaw)
        c_world = p.pos + Rz @ (0.5 * (lo + hi))
        R_cam = Rw.T @ Rz
        parts = []
        pc, ps, _, _ = p.cuboids()
        for c, s in zip(pc, ps):
            parts.append(Cuboid(cam.to_cam(c), s, R_cam))
        if corners is None:
            corners = rd.cuboid_corners(cen_c, siz, rot_c)
        full = rd.unoccluded_area(faces, np.nonzero(own == iid)[0], corners, K, W, H, config.near)
        vf = float(min(1.0, counts[iid] / max(full, 1)))
        objects.append(GTObject(
            class_name=p.model.name, box2d=box2d, center=cam.to_cam(c_world), size=hi - lo,
            rotation=R_cam, heading=rotation_to_heading(R_cam, up), parts=parts, visible_fraction=vf,
            instance_id=iid))
    clutter_boxes = []
    cl = owner_pix - CLUTTER_OWNER
    cl_counts = np.bincount(np.where(cl >= 0, cl, len(scene.clutter)).ravel(), minlength=len(scene.clutter) + 1)
    for j in np.nonzero(cl_counts[: len(scene.clutter)] >= config.min_clutter_pixels)[0]:
        clutter_boxes.append(_mask_box(cl == j))
    # shading
    o_cam = cam.to_cam(np.zeros(3))
    light = rd.Lighting(
        scene.ambient,
        [(cam.to_cam(pos), inten, col) for pos, inten, col in scene.lights],
        None if scene.sun is None else (Rw.T @ scene.sun[0], scene.sun[1]),
    )
    attrs = rd.surface_attributes(depth, fid, faces, K, o_cam)
    img, lum = rd.shade(depth, fid, faces, mats, K, o_cam, light, rng, attrs)
    rgb = rd.finish_rgb(img, rng, jpeg=config.jpeg, response=response)
    # depth
    if config.noise:
        pix, f, P, N, _, _ = attrs
        cos_inc = np.ones(H * W, np.float32)
        cos_inc[pix] = np.abs(N[0] * P[0] + N[1] * P[1] + N[2] * P[2]) / np.sqrt(P[0] ** 2 + P[1] ** 2 + P[2] ** 2)
        fm = mats[faces.cuboid]
        refl = np.ones(H * W, np.float32)
        refl[pix] = (fm[:, 9] * (1.0 - 0.5 * fm[:, 8]))[f] * np.sqrt(lum.ravel()[pix])
        glass = np.zeros(H * W, bool)
        glass[pix] = (fm[:, 0].astype(np.int32) == tx.GLASS)[f]
        params = config.noise_params or NoiseParams.sample(noise_rng)
        dn = apply_depth_noise(depth, K, noise_rng, params, cos_inc.reshape(H, W), refl.reshape(H, W),
                               glass.reshape(H, W))
    else:
        dn = depth.astype(np.float32).copy()
        dn[~np.isfinite(dn)] = np.nan
    return Frame(rgb=rgb, depth=dn, K=K.copy(), up=up, stamp_ns=int(stamp_ns), frame_id=FRAME_ID, objects=objects,
                 instance_mask=inst, clutter_boxes=clutter_boxes)


def _too_close(arrays, C: np.ndarray, R: np.ndarray, K: np.ndarray, W: int, H: int,
               near_m: float = 0.9, max_frac: float = 0.35) -> bool:
    """Cheap 64x48 probe render of the big cuboids: is more than ``max_frac`` of the view nearer than ``near_m``?"""
    cen, siz, rot, _, _ = arrays
    big = siz.max(axis=1) > 0.15
    s = 64.0 / W
    Ks = K.copy()
    Ks[:2] *= s
    Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    h = max(8, int(round(H * s)))
    depth, _, _ = rd.rasterize((cen[big] - C) @ R, siz[big], np.einsum("ji,njk->nik", R, rot[big]), Ks, 64, h)
    return float(np.mean(depth < near_m)) > max_frac


def generate_frame(seed: int, config: SynthConfig | None = None) -> Frame:
    """One frame of a new random room; same seed and config -> identical frame."""
    cfg = config or SynthConfig()
    r_scene, r_cam, r_render, r_noise = _streams(seed)
    scene = build_scene(r_scene, cfg.min_objects, cfg.max_objects, cfg.room_type, cfg.clutter)
    K = sample_intrinsics(r_cam, cfg.width, cfg.height)
    arrays = _scene_arrays(scene)
    for _ in range(4):  # re-draw views that a close obstacle would fill
        C, R, _ = sample_pose(scene, r_cam, cfg.camera_height)
        if not _too_close(arrays, C, R, K, cfg.width, cfg.height):
            break
    cam = Camera(K, cfg.width, cfg.height, C, R)
    return render_view(scene, cam, r_render, r_noise, cfg, cfg.stamp0_ns + int(seed) * cfg.period_ns, arrays)


def generate_sequence(seed: int, num_frames: int, rate_hz: float = 5.0, config: SynthConfig | None = None,
                      stamp0_ns: int | None = None) -> list[Frame]:
    """``num_frames`` frames of one room seen from a smoothly moving hand-held camera at ``rate_hz``."""
    cfg = config or SynthConfig()
    r_scene, r_cam, r_render, r_noise = _streams(seed)
    scene = build_scene(r_scene, cfg.min_objects, cfg.max_objects, cfg.room_type, cfg.clutter)
    K = sample_intrinsics(r_cam, cfg.width, cfg.height)
    poses = trajectory(scene, r_cam, num_frames, 1.0 / rate_hz, cfg.camera_height)
    params = cfg.noise_params or NoiseParams.sample(r_noise)
    cfg2 = SynthConfig(**{**cfg.__dict__, "noise_params": params})
    arrays = _scene_arrays(scene)
    response = rd.Response.sample(r_render, cfg.jpeg)
    t0 = cfg.stamp0_ns if stamp0_ns is None else stamp0_ns
    period = int(round(1e9 / rate_hz))
    frames = []
    for i, (C, R) in enumerate(poses):
        cam = Camera(K, cfg.width, cfg.height, C, R)
        frames.append(render_view(scene, cam, r_render, r_noise, cfg2, t0 + i * period, arrays, response))
    return frames
