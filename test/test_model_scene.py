"""A tiny ray-cast RGB-D scene maker for the model / training tests (numpy only).

Not the project's generator: a few cuboid-part objects standing on a floor in front of a
wall, ray-cast into a small depth map with an instance mask, so the model tests do not
depend on ``shape_detector.synth``. Imported by the other ``test_model_*`` / training tests.
"""

from __future__ import annotations

import numpy as np

from shape_detector.classes import MEAN_SIZES, class_id
from shape_detector.geometry import rot_z, upright_rotation
from shape_detector.types import Cuboid, Frame, GTObject

W, H = 128, 96
K = np.array([[110.0, 0, W / 2 - 0.5], [0, 110.0, H / 2 - 0.5], [0, 0, 1]])


def _parts_local(name: str, l: float, w: float, h: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(lo, hi) corners of the parts in the object frame (x front, z up, floor z=0)."""
    t = 0.05
    if name in ("table", "desk"):
        parts = [((-l / 2, -w / 2, h - t), (l / 2, w / 2, h))]
        for sx in (-1, 1):
            for sy in (-1, 1):
                x0 = sx * (l / 2 - t)
                y0 = sy * (w / 2 - t)
                parts.append(((min(x0, sx * l / 2), min(y0, sy * w / 2), 0), (max(x0, sx * l / 2), max(y0, sy * w / 2), h - t)))
    elif name == "chair":
        sh = 0.5 * h
        parts = [((-l / 2, -w / 2, sh - t), (l / 2, w / 2, sh)), ((-l / 2, -w / 2, sh), (-l / 2 + t, w / 2, h))]
        for sx in (-1, 1):
            for sy in (-1, 1):
                x0, y0 = sx * (l / 2 - t), sy * (w / 2 - t)
                parts.append(((min(x0, sx * l / 2), min(y0, sy * w / 2), 0), (max(x0, sx * l / 2), max(y0, sy * w / 2), sh - t)))
    else:  # a block with a back panel (bed / sofa / dresser ...)
        parts = [((-l / 2, -w / 2, 0), (l / 2, w / 2, 0.6 * h)), ((-l / 2, -w / 2, 0.6 * h), (-l / 2 + 0.2 * l, w / 2, h))]
    return [(np.array(a, float), np.array(b, float)) for a, b in parts]


def _ray_boxes(dirs: np.ndarray, centers, sizes, rots) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit distance along unit-ish rays from the origin and the hit box index."""
    best = np.full(len(dirs), np.inf)
    idx = np.full(len(dirs), -1)
    for k, (c, s, R) in enumerate(zip(centers, sizes, rots)):
        o = R.T @ (-c)
        d = dirs @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-s / 2 - o) / d
            t2 = (s / 2 - o) / d
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tmax >= np.maximum(tmin, 0)) & (tmin > 0)
        better = hit & (tmin < best)
        best[better] = tmin[better]
        idx[better] = k
    return best, idx


def make_frame(seed: int = 0, n_objects: int = 2, classes=("table", "chair", "bed"), pitch_deg: float = 12.0) -> Frame:
    """A random frame with ``n_objects`` labelled objects (parts GT) and one clutter box."""
    rng = np.random.default_rng(seed)
    pitch = np.deg2rad(pitch_deg + rng.uniform(-3, 3))
    # camera tilted down by `pitch`: up in the camera frame
    up = np.array([0.0, -np.cos(pitch), -np.sin(pitch)])
    R_cu = upright_rotation(up)
    cam_h = 1.3
    objs_u = []  # (name, centre_U, size, heading, parts list of (c_U, s, R_U))
    xs = np.linspace(-1.0, 1.0, n_objects) if n_objects > 1 else np.array([0.0])
    for i in range(n_objects):
        name = classes[int(rng.integers(len(classes)))] if i > 0 else classes[seed % len(classes)]
        l, w, h = MEAN_SIZES[class_id(name)] * rng.uniform(0.85, 1.15, 3)
        if name == "bed":
            l, w = l * 0.7, w * 0.7
        heading = rng.uniform(-np.pi, np.pi)
        c = np.array([xs[i] * 1.1 + rng.uniform(-0.2, 0.2), rng.uniform(2.6, 3.6) + 0.3 * i, -cam_h + h / 2])
        Rz = rot_z(heading)
        parts = []
        for lo, hi in _parts_local(name, l, w, h):
            pc_local = 0.5 * (lo + hi) - np.array([0, 0, h / 2])
            parts.append((c + Rz @ pc_local, hi - lo, Rz))
        objs_u.append((name, c, np.array([l, w, h]), heading, parts))
    # clutter: a small box on the floor
    clutter = (np.array([rng.uniform(-1.5, 1.5), rng.uniform(1.8, 2.3), -cam_h + 0.1]), np.array([0.25, 0.25, 0.2]), rot_z(rng.uniform(0, 3)))

    # scene boxes in camera frame
    centers, sizes, rots, owner = [], [], [], []
    for oi, (_, _, _, _, parts) in enumerate(objs_u):
        for pc, ps, pr in parts:
            centers.append(R_cu @ pc)
            sizes.append(ps)
            rots.append(R_cu @ pr)
            owner.append(oi + 1)
    centers.append(R_cu @ clutter[0])
    sizes.append(clutter[1])
    rots.append(R_cu @ clutter[2])
    owner.append(-1)
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    dirs = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu, float)], -1).reshape(-1, 3)
    t_box, k_box = _ray_boxes(dirs, centers, sizes, rots)
    d_u = dirs @ R_cu  # ray directions in U
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d_u[:, 2] < -1e-6, -cam_h / d_u[:, 2], np.inf)
        t_wall = np.where(d_u[:, 1] > 1e-6, 6.0 / d_u[:, 1], np.inf)
    t_bg = np.minimum(t_floor, t_wall)
    t = np.minimum(t_box, t_bg)
    depth = np.where(np.isfinite(t), t, np.nan).astype(np.float32)  # dirs have z = 1 -> t is depth
    inst = np.zeros(len(dirs), np.int32)
    on_box = t_box <= t_bg
    owners = np.array(owner)
    inst[on_box & (k_box >= 0)] = np.maximum(owners[k_box[on_box & (k_box >= 0)]], 0)
    inst = inst.reshape(H, W)
    depth = depth.reshape(H, W)
    depth = depth + rng.normal(0, 0.003, depth.shape).astype(np.float32)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[...] = (150, 140, 120)
    palette = rng.integers(40, 255, (len(objs_u) + 2, 3))
    for oi in range(len(objs_u)):
        rgb[inst == oi + 1] = palette[oi]
    clut_mask = (k_box.reshape(H, W) == len(owner) - 1) & on_box.reshape(H, W)
    rgb[clut_mask] = palette[-1]
    objects = []
    for oi, (name, c, size, heading, parts) in enumerate(objs_u):
        m = inst == oi + 1
        if not m.any():
            continue
        vs, us = np.nonzero(m)
        box2d = (float(us.min()), float(vs.min()), float(us.max() + 1), float(vs.max() + 1))
        objects.append(
            GTObject(
                class_name=name, box2d=box2d, center=R_cu @ c, size=size, rotation=R_cu @ rot_z(heading),
                heading=float(heading), parts=[Cuboid(R_cu @ pc, ps, R_cu @ pr) for pc, ps, pr in parts],
                visible_fraction=1.0, instance_id=oi + 1,
            )
        )
    clutter_boxes = []
    if clut_mask.any():
        vs, us = np.nonzero(clut_mask)
        clutter_boxes.append((float(us.min()), float(vs.min()), float(us.max() + 1), float(vs.max() + 1)))
    return Frame(rgb=rgb, depth=depth, K=K.copy(), up=up, objects=objects, instance_mask=inst, clutter_boxes=clutter_boxes)


def test_tiny_scene_is_consistent():
    from shape_detector.geometry import points_in_box
    from shape_detector.frustum import backproject

    f = make_frame(3)
    assert f.objects and f.instance_mask is not None
    pts = backproject(f.depth, f.K)
    for o in f.objects:
        p = pts[f.instance_mask == o.instance_id]
        assert len(p) > 30
        inside = points_in_box(p, o.center, o.size, o.rotation, margin=0.02)
        assert inside.mean() > 0.95
        # the rotation's z column is gravity up
        assert np.allclose(o.rotation[:, 2], f.up / np.linalg.norm(f.up), atol=1e-9)
