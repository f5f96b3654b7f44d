"""Proposal recall and gravity error on generated frames, plus a tiny ray-cast toy scene.

``evaluate_proposals(frames)`` runs the geometric proposer (gravity estimated, no ``up``
given) over frames with ground truth and reports, for objects with
``visible_fraction >= 0.3``, the share matched by some proposal at 2D IoU >= 0.5, the
number of proposals per frame, the angle between estimated and true ``up`` (median /
p90, degrees) and the time per frame.

``toy_scene`` ray-casts a floor, optional walls and yaw-rotated boxes (objects made of
cuboid parts) into a depth map seen by a tilted camera; tests and quick checks use it
when the full scene generator is not wanted.

``python -m shape_detector.proposals.evaluate --frames 100 --seed 70000`` prints the
numbers; ``--fit-ranker`` fits the proposals' ranking weights instead.
"""

from __future__ import annotations

import argparse
import itertools
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry import normalize, rot_z, upright_rotation
from ..types import Frame, GTObject

VGA_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


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


# ---------------------------------------------------------------------------------------


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU (len(a), len(b)) of pixel-edge boxes (x1, y1, x2, y2)."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    ix = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = ix * iy
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors in degrees."""
    c = float(normalize(np.asarray(a)) @ normalize(np.asarray(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def evaluate_proposals(
    frames: Iterable[Frame],
    proposer=None,
    min_visible: float = 0.3,
    iou_thr: float = 0.5,
    verbose: bool = False,
) -> dict:
    """Recall / proposals per frame / up error / time of ``proposer`` (default geometric) on ``frames``."""
    if proposer is None:
        from .geometric import GeometricProposer

        proposer = GeometricProposer()
    hits = total = 0
    nprops, up_err, times, confs = [], [], [], []
    per_class: dict[str, list[int]] = {}
    sources: dict[str, int] = {}
    misses = []
    for fi, f in enumerate(frames):
        t0 = time.perf_counter()
        grav, props = proposer(f.depth, f.K, up=None, rgb=f.rgb)
        times.append(1e3 * (time.perf_counter() - t0))
        nprops.append(len(props))
        sources[grav.source] = sources.get(grav.source, 0) + 1
        confs.append(grav.confidence)
        if f.up is not None:
            up_err.append(angle_deg(grav.up, f.up))
        gts = [o for o in f.objects if o.visible_fraction >= min_visible]
        if not gts:
            continue
        pb = np.array([p.box2d for p in props], np.float64).reshape(-1, 4)
        gb = np.array([o.box2d for o in gts], np.float64)
        best = box_iou(gb, pb).max(axis=1) if len(pb) else np.zeros(len(gb))
        for o, b in zip(gts, best):
            ok = int(b >= iou_thr)
            hits += ok
            total += 1
            per_class.setdefault(o.class_name, [0, 0])
            per_class[o.class_name][0] += ok
            per_class[o.class_name][1] += 1
            if not ok:
                misses.append((fi, o.class_name, round(float(b), 2), round(o.visible_fraction, 2)))
    up_err_a = np.asarray(up_err) if up_err else np.zeros(1)
    res = {
        "frames": len(times),
        "objects": total,
        "recall": hits / max(total, 1),
        "proposals_per_frame": float(np.mean(nprops)) if nprops else 0.0,
        "up_err_median_deg": float(np.median(up_err_a)),
        "up_err_p90_deg": float(np.percentile(up_err_a, 90)),
        "up_err_max_deg": float(np.max(up_err_a)),
        "up_confidence_mean": float(np.mean(confs)) if confs else 0.0,
        "gravity_sources": sources,
        "ms_median": float(np.median(times)) if times else 0.0,
        "recall_per_class": {k: v[0] / max(v[1], 1) for k, v in sorted(per_class.items())},
    }
    if verbose:
        res["misses"] = misses
    return res


def fit_ranker(
    frames: Iterable[Frame], lam: float = 1e-3, min_visible: float = 0.3, iou_thr: float = 0.5
) -> np.ndarray:
    """Weights of the proposals' quadratic logistic ranking (``geometric._RANK_W`` over
    ``geometric.rank_features``) fitted on frames with ground truth. Every candidate
    hypothesis (before NMS / the cap) is a sample, positive when it matches a GT box (IoU >=
    ``iou_thr``, visible >= ``min_visible``). The positives of each object share one unit of
    weight (an object matched by 40 hypotheses counts as much as one matched by 2), and all
    positives together weigh as much as all negatives. L2-regularised (``lam``), Newton
    iterations. On 200 validation frames this raised the share of objects with a good
    proposal among the first 10 / 15 / 20 from 78.2 / 86.4 / 91.8% (linear, class-balanced)
    to 85.1 / 91.3 / 93.8%."""
    from .geometric import GeometricConfig, GeometricProposer, rank_features

    prop = GeometricProposer(GeometricConfig(max_proposals=1))
    X, Y, W = [], [], []
    for f in frames:
        prop(f.depth, f.K, rgb=f.rgb)
        F, B = prop.debug.features, prop.debug.candidates
        if F is None or B is None or not len(B):
            continue
        gts = [o.box2d for o in f.objects if o.visible_fraction >= min_visible]
        y, wpos = np.zeros(len(B)), np.zeros(len(B))
        if gts:
            iou = box_iou(B, np.array(gts))
            y = (iou.max(axis=1) >= iou_thr).astype(float)
            owner = iou.argmax(axis=1)
            count = np.bincount(owner[y > 0], minlength=len(gts))
            wpos[y > 0] = 1.0 / count[owner[y > 0]]
        X.append(rank_features(F))
        Y.append(y)
        W.append(wpos)
    Xa, Ya, Wa = np.concatenate(X), np.concatenate(Y), np.concatenate(W)
    sw = np.where(Ya > 0, Wa * (1.0 - Ya).sum() / max(Wa.sum(), 1e-9), 1.0)
    w = np.zeros(Xa.shape[1])
    for _ in range(60):
        p = 1.0 / (1.0 + np.exp(-(Xa @ w)))
        g = Xa.T @ (sw * (p - Ya)) / len(Ya) + lam * w
        Hm = (Xa * (sw * p * (1 - p))[:, None]).T @ Xa / len(Ya) + lam * np.eye(len(w))
        step = np.linalg.solve(Hm, g)
        w -= step
        if np.abs(step).max() < 1e-7:
            break
    return w


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--seed", type=int, default=50_000, help="first generator seed")
    p.add_argument("--no-rgb", action="store_true", help="depth only (no colour edges)")
    p.add_argument("--fit-ranker", action="store_true", help="fit and print the ranking weights instead")
    p.add_argument("--data", default=None, help="use the first --frames frames of this dataset instead of generating")
    p.add_argument("--verbose", action="store_true")
    args = p.parse_args(argv)
    from ..synth.generate import generate_frame

    if args.data:
        from ..synth.dataset import iter_frames

        frames = itertools.islice(iter_frames(args.data), args.frames)
    else:
        frames = (generate_frame(args.seed + i) for i in range(args.frames))
    if args.fit_ranker:
        w = fit_ranker(frames)
        print("_RANK_W = [" + ", ".join(f"{v:.4f}" for v in w) + "]")
        return 0
    proposer = None
    if args.no_rgb:
        from .geometric import GeometricProposer

        geo = GeometricProposer()

        def proposer(depth, K, up=None, rgb=None):
            return geo(depth, K, up=up)

    res = evaluate_proposals(frames, proposer=proposer, verbose=args.verbose)
    for k, v in res.items():
        print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
