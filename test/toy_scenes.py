"""Ray-cast toy scenes for tests: a floor, optional walls and yaw-rotated boxes (objects made
of cuboid parts) seen by a tilted camera, as :class:`~shape_detector.types.Frame` with ground
truth; for checks that do not want the full scene generator."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from shape_detector.geometry import normalize, rot_z, upright_rotation
from shape_detector.proposals.evaluate import VGA_K
from shape_detector.types import Frame, GTObject


def up_from_pitch_roll(pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """Gravity-up in the camera frame of a camera pitched down by ``pitch`` and rolled by ``roll``."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    # level camera: up = (0, -1, 0); pitching the camera down tilts up towards -z ... (camera looks down)
    up = np.array([0.0, -np.cos(p), -np.sin(p)])
    c, s = np.cos(r), np.sin(r)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return normalize(Rz @ up)


@dataclass
class ToyPart:
    """An upright cuboid in the world frame (z up, floor at z = 0): centre, size (l, w, h), yaw."""

    center: Sequence[float]
    size: Sequence[float]
    yaw: float = 0.0


def _ray_box(d_w: np.ndarray, o_w: np.ndarray, part: ToyPart) -> np.ndarray:
    """Ray parameter t (HW,) of the first hit of rays ``o + t d`` with a yaw-rotated box (inf: miss)."""
    R = rot_z(-part.yaw)
    o = R @ (o_w - np.asarray(part.center, np.float64))
    d = d_w @ R.T
    half = 0.5 * np.asarray(part.size, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmax > 0)
    t = np.where(tmin > 0, tmin, np.inf)
    return np.where(hit, t, np.inf)


def _part_rays(part: ToyPart, o_w: np.ndarray, R_cu: np.ndarray, K: np.ndarray, H: int, W: int) -> np.ndarray | None:
    """Flat indices of the pixels inside the projected bounding rectangle of ``part`` (None:
    the part reaches behind the camera, test every ray)."""
    half = 0.5 * np.asarray(part.size, np.float64)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    corners = (signs * half) @ rot_z(part.yaw).T + np.asarray(part.center, np.float64)
    p_cam = (corners - o_w) @ R_cu.T
    if (p_cam[:, 2] < 0.05).any():
        return None
    uv = p_cam @ np.asarray(K).T
    uv = uv[:, :2] / uv[:, 2:3]
    u0, v0 = (int(np.clip(np.floor(uv[:, i].min()) - 1, 0, n)) for i, n in ((0, W), (1, H)))
    u1, v1 = (int(np.clip(np.ceil(uv[:, i].max()) + 2, 0, n)) for i, n in ((0, W), (1, H)))
    if u1 <= u0 or v1 <= v0:
        return np.zeros(0, np.int64)
    vv, uu = np.mgrid[v0:v1, u0:u1]
    return (vv * W + uu).ravel()


def toy_scene(
    objects: Sequence[tuple[str, Sequence[ToyPart]]],
    up: np.ndarray | None = None,
    cam_height: float = 1.3,
    K: np.ndarray | None = None,
    size: tuple[int, int] = (480, 640),
    floor: bool = True,
    walls: Sequence[tuple[float, float]] = (),
    ceiling: float | None = None,
    noise: float = 0.0015,
    dropout: float = 0.01,
    seed: int = 0,
    min_visible_px: int = 50,
) -> Frame:
    """Ray-cast a toy RGB-D frame. ``objects``: (class name, parts) in the world frame (z up,
    camera above the origin at ``cam_height``, looking along +y when level); ``walls``:
    vertical planes as (normal azimuth rad, distance from the camera axis m); ``noise``:
    depth sigma at 1 m (grows with z^2). Returns a :class:`Frame` with GT boxes (visible
    2D boxes; ``visible_fraction`` 1) and an instance mask."""
    H, W = size
    K = VGA_K if K is None else np.asarray(K, np.float64)
    up = up_from_pitch_roll(0.0) if up is None else normalize(np.asarray(up, np.float64))
    R_cu = upright_rotation(up)
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d_cam = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1).reshape(-1, 3)
    d_w = d_cam @ R_cu  # upright (world) directions; depth = t since d_cam.z = 1
    o_w = np.array([0.0, 0.0, cam_height])
    t = np.full(H * W, np.inf)
    label = np.zeros(H * W, np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        if floor:
            tf = np.where(d_w[:, 2] < 0, -cam_height / d_w[:, 2], np.inf)
            t = np.minimum(t, tf)
        if ceiling is not None:
            tc = np.where(d_w[:, 2] > 0, (ceiling - cam_height) / d_w[:, 2], np.inf)
            t = np.minimum(t, tc)
        for az, dist in walls:
            nrm = np.array([np.cos(az), np.sin(az), 0.0])
            dn = d_w @ nrm
            tw = np.where(dn > 0, dist / dn, np.inf)
            t = np.minimum(t, tw)
    for i, (_name, parts) in enumerate(objects, start=1):
        for part in parts:
            rows = _part_rays(part, o_w, R_cu, K, H, W)
            if rows is None:
                tp = _ray_box(d_w, o_w, part)
                closer = tp < t
                t = np.where(closer, tp, t)
                label[closer] = i
                continue
            if rows.size == 0:
                continue
            tp = _ray_box(d_w[rows], o_w, part)
            closer = tp < t[rows]
            t[rows[closer]] = tp[closer]
            label[rows[closer]] = i
    depth = t.reshape(H, W)
    label = label.reshape(H, W)
    rng = np.random.default_rng(seed)
    finite = np.isfinite(depth)
    depth = np.where(finite, depth, np.nan)
    depth = depth + rng.normal(0.0, 1.0, depth.shape) * noise * np.nan_to_num(depth) ** 2
    if dropout > 0:
        depth[rng.random(depth.shape) < dropout] = np.nan
    gts = []
    for i, (name, parts) in enumerate(objects, start=1):
        ys, xs = np.nonzero(label == i)
        if xs.size < min_visible_px:
            continue
        box = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
        lo = np.min([np.asarray(p.center) - 0.5 * np.asarray(p.size) for p in parts], axis=0)
        hi = np.max([np.asarray(p.center) + 0.5 * np.asarray(p.size) for p in parts], axis=0)
        c_w = 0.5 * (lo + hi) - o_w
        gts.append(
            GTObject(name, box, R_cu @ c_w, hi - lo, R_cu, visible_fraction=1.0, instance_id=i)
        )
    rgb = np.full((H, W, 3), 128, np.uint8)
    return Frame(rgb, depth.astype(np.float32), K, up=up, objects=gts, instance_mask=label)


def box_part(x: float, y: float, l: float, w: float, h: float, yaw: float = 0.0, z0: float = 0.0) -> ToyPart:
    """A cuboid standing on height ``z0`` with footprint centre (x, y)."""
    return ToyPart((x, y, z0 + 0.5 * h), (l, w, h), yaw)


def placed_box_scene(
    name: str,
    size: Sequence[float],
    x: float,
    y: float,
    yaw: float = 0.0,
    pitch_deg: float = 12.0,
    cam_height: float = 1.3,
    walls: Sequence[tuple[float, float]] = (),
    seed: int = 3,
) -> tuple[Frame, np.ndarray, np.ndarray]:
    """One box of class ``name`` and full extent ``size`` (l, w, h metres) placed by hand on the
    floor at world (x, y) with ``yaw`` (rad), seen by a camera ``cam_height`` m high pitched
    ``pitch_deg`` down (see :func:`toy_scene`). Returns the frame and the box's centre (3,) and
    rotation (3x3, columns = box axes) in the camera optical frame."""
    size = np.asarray(size, dtype=np.float64)
    frame = toy_scene([(name, [box_part(x, y, *size, yaw=yaw)])], up=up_from_pitch_roll(pitch_deg),
                      cam_height=cam_height, walls=walls, seed=seed)
    R_cu = upright_rotation(frame.up)
    centre = R_cu @ (np.array([x, y, size[2] / 2]) - np.array([0.0, 0.0, cam_height]))
    return frame, centre, R_cu @ rot_z(yaw)


def chair_parts(x: float, y: float, yaw: float = 0.0, seat_h: float = 0.45, leg: float = 0.04) -> list[ToyPart]:
    """A chair: 4 thin legs, a seat slab and a back rest, facing -y before ``yaw``."""
    R = rot_z(yaw)[:2, :2]
    parts = []
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        off = R @ np.array([sx * 0.2, sy * 0.2])
        parts.append(box_part(x + off[0], y + off[1], leg, leg, seat_h - 0.04, yaw))
    parts.append(box_part(x, y, 0.46, 0.46, 0.04, yaw, z0=seat_h - 0.04))
    off = R @ np.array([0.0, 0.21])
    parts.append(box_part(x + off[0], y + off[1], 0.46, 0.04, 0.45, yaw, z0=seat_h))
    return parts
