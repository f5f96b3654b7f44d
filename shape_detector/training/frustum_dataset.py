"""Frames -> a flat dataset of training frustums (numpy arrays, cached as ``.npz``).

For each frame, every labelled object with enough visible points yields
``augment_copies`` frustums: copy 0 from its exact visible 2D box, the others from a
jittered box (centre shifted and sides scaled by up to ``box_jitter`` of the box size, as
Frustum PointNets' ``random_shift_box2d``). Segmentation labels are
``instance_mask[pixel] == instance_id``. Each frame also yields ``negatives_per_frame``
negative frustums, cycling through: unlabelled clutter boxes, random background boxes
(walls / floor, IoU < ``neg_max_iou`` with every object box) and partial-object boxes
(a sub-box of an object box with IoU < ``neg_max_iou``); negatives are labelled all
background and class ``num_classes`` (background).

Proposal frustums (``proposal_positives`` / ``proposal_negatives`` > 0): the built-in
geometric proposer (gravity estimated, as at inference) runs on the frame and its top
``proposal_top`` boxes become training frustums, so the network learns the box
distribution it meets without GT boxes. A proposal whose 2D IoU with an eligible object's
visible box is >= ``proposal_pos_iou`` is a positive of that object; one below
``proposal_neg_iou`` with every labelled object box is a hard negative (kind 4:
clutter, wall remnants, pieces of objects, merged neighbours); the rest are skipped.
At most that many of each per frame, drawn at random. ``gt_frustums=False`` builds the
proposal frustums only (to add to an existing GT-box dataset).

Arrays (K frustums, N points, P max parts, S surface samples)::

    points (K,N,6) float16     xyz in the frustum frame F, rgb in [0,1]
    seg (K,N) uint8            1 = the object's points
    class_id (K,) int16        class index, -1 for negatives
    is_negative (K,) bool, neg_kind (K,) int8   0 pos, 1 clutter, 2 background, 3 partial
    center (K,3), size (K,3), heading (K,) float32   GT amodal box in F (heading_F)
    has_shape (K,) bool        GT parts known
    parts_center (K,P,3), parts_size (K,P,3), parts_rotation (K,P,3,3) float32,
    parts_count (K,) int16     GT parts in the GT box's canonical frame (centre, x = heading)
    surface (K,S,3) float16    samples on the GT parts' union surface, canonical frame
    phi (K,), R_cu (K,3,3)     frustum angle and upright rotation (F -> camera: R_cu rot_z(-phi))
    box2d (K,4) float32, valid (K,) int32, frame_index (K,) int32, object_index (K,) int16
    fg_valid (K,) int32        valid object pixels inside the 2D box
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..classes import CLASS_TO_ID, NUM_CLASSES
from ..box_iou import box2d_iou
from ..frustum import backproject, clip_box, extract_frustum
from ..geometry import rotation_to_heading, upright_rotation, wrap_angle
from ..model.primitives import sample_parts_surface_np
from ..types import Frame

NEG_POSITIVE, NEG_CLUTTER, NEG_BACKGROUND, NEG_PARTIAL, NEG_PROPOSAL = 0, 1, 2, 3, 4


@dataclass
class FrustumDatasetConfig:
    """How frustums are cut from generated frames: points per frustum, jittered copies of each
    GT 2D box, negatives, GT shape samples, and the built-in proposer's frustums (positives by
    2D IoU >= ``proposal_pos_iou``, hard negatives below ``proposal_neg_iou``)."""

    num_points: int = 512
    augment_copies: int = 2
    rng_seed: int = 0
    negatives_per_frame: int = 1
    surface_samples: int = 256
    max_parts: int = 32
    min_points: int = 30
    min_visible: float = 0.1
    box_jitter: float = 0.1
    neg_max_iou: float = 0.3
    neg_min_side: int = 24
    max_depth: float = 10.0
    gt_frustums: bool = True
    proposal_positives: int = 0
    proposal_negatives: int = 0
    proposal_top: int = 20
    proposal_pos_iou: float = 0.5
    proposal_neg_iou: float = 0.25

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> FrustumDatasetConfig:
        """Settings from overrides of the defaults (other keys are ignored: a TrainConfig's
        ``data`` may carry them)."""
        d = dict(d or {})
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every field."""
        return asdict(self)


def jitter_box(box, rng: np.random.Generator, ratio: float, width: int, height: int):
    """Shift the centre and scale the sides of a pixel-edge box by up to ``ratio``."""
    x1, y1, x2, y2 = (float(v) for v in box)
    w, h = x2 - x1, y2 - y1
    cx = 0.5 * (x1 + x2) + w * ratio * rng.uniform(-1, 1)
    cy = 0.5 * (y1 + y2) + h * ratio * rng.uniform(-1, 1)
    w2 = w * (1 + ratio * rng.uniform(-1, 1))
    h2 = h * (1 + ratio * rng.uniform(-1, 1))
    return (
        float(np.clip(cx - w2 / 2, 0, width)),
        float(np.clip(cy - h2 / 2, 0, height)),
        float(np.clip(cx + w2 / 2, 0, width)),
        float(np.clip(cy + h2 / 2, 0, height)),
    )


def _object_parts_canonical(obj, max_parts: int, n_surface: int, rng: np.random.Generator):
    """GT parts in the object's canonical frame (padded) and union-surface samples."""
    R = np.asarray(obj.rotation, np.float64)
    c0 = np.asarray(obj.center, np.float64)
    P = len(obj.parts)
    pc = np.zeros((max_parts, 3), np.float32)
    ps = np.zeros((max_parts, 3), np.float32)
    pr = np.tile(np.eye(3, dtype=np.float32), (max_parts, 1, 1))
    if P == 0:
        return pc, ps, pr, 0, np.zeros((n_surface, 3), np.float16)
    cen = np.stack([R.T @ (np.asarray(p.center) - c0) for p in obj.parts])
    siz = np.stack([np.asarray(p.size, np.float64) for p in obj.parts])
    rot = np.stack([R.T @ np.asarray(p.rotation, np.float64) for p in obj.parts])
    surf = sample_parts_surface_np(cen, siz, rot, n_surface, rng)
    order = np.argsort(-np.prod(siz, axis=1))[:max_parts]  # keep the largest parts
    k = len(order)
    pc[:k], ps[:k], pr[:k] = cen[order], siz[order], rot[order]
    return pc, ps, pr, k, surf.astype(np.float16)


def _random_background_box(frame: Frame, rng, cfg: FrustumDatasetConfig, gt_boxes):
    W, H = frame.width, frame.height
    for _ in range(20):
        w = rng.uniform(cfg.neg_min_side, 0.6 * W)
        h = rng.uniform(cfg.neg_min_side, 0.6 * H)
        x1 = rng.uniform(0, W - w)
        y1 = rng.uniform(0, H - h)
        b = (x1, y1, x1 + w, y1 + h)
        if all(box2d_iou(b, g) < cfg.neg_max_iou * 0.5 for g in gt_boxes):
            return b
    return None


def _partial_box(frame: Frame, rng, cfg: FrustumDatasetConfig, gt_boxes):
    if not gt_boxes:
        return None
    for _ in range(20):
        g = gt_boxes[rng.integers(len(gt_boxes))]
        gw, gh = g[2] - g[0], g[3] - g[1]
        if gw < cfg.neg_min_side or gh < cfg.neg_min_side:
            continue
        fw, fh = rng.uniform(0.25, 0.6), rng.uniform(0.25, 0.6)
        w, h = max(gw * fw, cfg.neg_min_side * 0.75), max(gh * fh, cfg.neg_min_side * 0.75)
        x1 = g[0] + rng.uniform(-0.3 * w, gw - 0.7 * w)
        y1 = g[1] + rng.uniform(-0.3 * h, gh - 0.7 * h)
        b = (max(0.0, x1), max(0.0, y1), min(float(frame.width), x1 + w), min(float(frame.height), y1 + h))
        if b[2] - b[0] < 4 or b[3] - b[1] < 4:
            continue
        if all(box2d_iou(b, gg) < cfg.neg_max_iou for gg in gt_boxes):
            return b
    return None


class _Builder:
    def __init__(self, cfg: FrustumDatasetConfig) -> None:
        self.cfg = cfg
        self.rows: dict[str, list] = {}

    def add(self, **kw) -> None:
        for k, v in kw.items():
            self.rows.setdefault(k, []).append(v)

    def arrays(self) -> dict[str, np.ndarray]:
        cfg = self.cfg
        dtypes = {
            "points": np.float16, "seg": np.uint8, "class_id": np.int16, "is_negative": bool,
            "neg_kind": np.int8, "center": np.float32, "size": np.float32, "heading": np.float32,
            "has_shape": bool, "parts_center": np.float32, "parts_size": np.float32,
            "parts_rotation": np.float32, "parts_count": np.int16, "surface": np.float16,
            "phi": np.float32, "R_cu": np.float32, "box2d": np.float32, "valid": np.int32,
            "frame_index": np.int32, "object_index": np.int16, "fg_valid": np.int32,
        }
        shapes = {
            "points": (cfg.num_points, 6), "seg": (cfg.num_points,), "center": (3,), "size": (3,),
            "parts_center": (cfg.max_parts, 3), "parts_size": (cfg.max_parts, 3),
            "parts_rotation": (cfg.max_parts, 3, 3), "surface": (cfg.surface_samples, 3),
            "R_cu": (3, 3), "box2d": (4,),
        }
        out = {}
        for k, dt in dtypes.items():
            rows = self.rows.get(k, [])
            if rows:
                out[k] = np.asarray(np.stack([np.asarray(r) for r in rows]), dtype=dt)
            else:
                out[k] = np.zeros((0,) + shapes.get(k, ()), dt)
        return out


def _frame_frustums(frame: Frame, fi: int, cfg: FrustumDatasetConfig, rng: np.random.Generator, b: _Builder) -> None:
    W, H = frame.width, frame.height
    pts_cam = backproject(frame.depth, frame.K)
    depth_ok = np.isfinite(frame.depth) & (frame.depth > 0) & (frame.depth < cfg.max_depth)
    R_cu = upright_rotation(frame.up)
    mask = frame.instance_mask
    gt_boxes = [tuple(o.box2d) for o in frame.objects]
    eye = np.tile(np.eye(3, dtype=np.float32), (cfg.max_parts, 1, 1))

    def extract(box):
        return extract_frustum(
            frame.rgb, frame.depth, frame.K, box, cfg.num_points, up=frame.up, rng=rng,
            max_depth=cfg.max_depth, points_cam=pts_cam,
        )

    eligible = _eligible_objects(frame, cfg, depth_ok)
    parts: dict[int, tuple] = {}  # object index -> canonical parts, drawn on first use

    def add_positive(oi: int, box) -> None:
        obj = frame.objects[oi]
        fg_valid, cid, heading_u = eligible[oi]
        if oi not in parts:
            parts[oi] = _object_parts_canonical(obj, cfg.max_parts, cfg.surface_samples, rng)
        pc, ps, pr, npart, surf = parts[oi]
        fr = extract(box)
        if fr.valid == 0:
            return
        seg = (mask.reshape(-1)[fr.pixel_index] == obj.instance_id).astype(np.uint8)
        if int(seg.sum()) < min(cfg.min_points, cfg.num_points // 16):
            return
        R_fc = fr.R_cf.T
        b.add(
            points=fr.points, seg=seg, class_id=cid, is_negative=False, neg_kind=NEG_POSITIVE,
            center=R_fc @ np.asarray(obj.center, np.float64), size=np.asarray(obj.size),
            heading=float(wrap_angle(heading_u + fr.phi)), has_shape=npart > 0,
            parts_center=pc, parts_size=ps, parts_rotation=pr, parts_count=npart, surface=surf,
            phi=fr.phi, R_cu=R_cu, box2d=np.asarray(box, np.float32), valid=fr.valid,
            frame_index=fi, object_index=oi, fg_valid=fg_valid,
        )

    def add_negative(box, kind: int) -> None:
        fr = extract(box)
        if fr.valid < cfg.min_points:
            return
        b.add(
            points=fr.points, seg=np.zeros(cfg.num_points, np.uint8), class_id=-1, is_negative=True,
            neg_kind=kind, center=np.zeros(3), size=np.ones(3), heading=0.0, has_shape=False,
            parts_center=np.zeros((cfg.max_parts, 3)), parts_size=np.zeros((cfg.max_parts, 3)),
            parts_rotation=eye, parts_count=0, surface=np.zeros((cfg.surface_samples, 3)),
            phi=fr.phi, R_cu=R_cu, box2d=np.asarray(box, np.float32), valid=fr.valid,
            frame_index=fi, object_index=-1, fg_valid=0,
        )

    if cfg.proposal_positives > 0 or cfg.proposal_negatives > 0:
        _proposal_frustums(frame, cfg, rng, eligible, gt_boxes, add_positive, add_negative)
    if not cfg.gt_frustums:
        return

    for oi in eligible:
        obj = frame.objects[oi]
        for copy in range(max(1, cfg.augment_copies)):
            box = tuple(obj.box2d) if copy == 0 else jitter_box(obj.box2d, rng, cfg.box_jitter, W, H)
            add_positive(oi, box)

    _gt_negatives(frame, cfg, rng, gt_boxes, add_negative)


def _eligible_objects(frame: Frame, cfg: FrustumDatasetConfig, depth_ok: np.ndarray) -> dict[int, tuple]:
    """Object index -> (visible foreground pixels with valid depth, class id, heading about up)
    of the labelled objects visible enough to train on."""
    W, H = frame.width, frame.height
    mask = frame.instance_mask
    eligible: dict[int, tuple] = {}
    for oi, obj in enumerate(frame.objects):
        if obj.class_name not in CLASS_TO_ID or mask is None:
            continue
        if obj.visible_fraction < cfg.min_visible:
            continue
        x1, y1, x2, y2 = clip_box(obj.box2d, W, H)
        if x2 <= x1 or y2 <= y1:
            continue
        fg_valid = int(np.count_nonzero((mask[y1:y2, x1:x2] == obj.instance_id) & depth_ok[y1:y2, x1:x2]))
        if fg_valid < cfg.min_points:
            continue
        eligible[oi] = (fg_valid, CLASS_TO_ID[obj.class_name], rotation_to_heading(obj.rotation, frame.up))
    return eligible


def _gt_negatives(frame: Frame, cfg: FrustumDatasetConfig, rng: np.random.Generator, gt_boxes: list,
                  add_negative) -> None:
    """``cfg.negatives_per_frame`` negative frustums, cycling through clutter, partial-object
    and background boxes (each falling back to the next kind when none is found)."""
    W, H = frame.width, frame.height
    clutter = list(frame.clutter_boxes)
    kinds = (NEG_CLUTTER, NEG_BACKGROUND, NEG_PARTIAL)
    start = int(rng.integers(3))
    for n in range(cfg.negatives_per_frame):
        kind = kinds[(start + n) % 3]
        box = None
        if kind == NEG_CLUTTER and clutter:
            box = jitter_box(clutter[int(rng.integers(len(clutter)))], rng, cfg.box_jitter, W, H)
            if any(box2d_iou(box, g) >= cfg.neg_max_iou for g in gt_boxes):
                box = None
        if box is None and kind in (NEG_CLUTTER, NEG_PARTIAL):
            box = _partial_box(frame, rng, cfg, gt_boxes)
            kind = NEG_PARTIAL if box is not None else NEG_BACKGROUND
        if box is None:
            box = _random_background_box(frame, rng, cfg, gt_boxes)
            kind = NEG_BACKGROUND
        if box is None:
            continue
        add_negative(box, kind)


@functools.lru_cache(maxsize=1)
def _proposer():
    """The built-in proposer, built once per process (its config is the detector's default)."""
    from ..proposals.geometric import GeometricProposer

    return GeometricProposer()


def _proposal_frustums(frame: Frame, cfg: FrustumDatasetConfig, rng: np.random.Generator, eligible, gt_boxes,
                       add_positive, add_negative) -> None:
    """Positives / hard negatives from the built-in proposer's boxes (see the module docstring)."""
    _, props = _proposer()(frame.depth, frame.K, up=None, rgb=frame.rgb)
    pos, neg = [], []
    for p in props[: cfg.proposal_top]:
        ious = [box2d_iou(p.box2d, g) for g in gt_boxes]
        best = int(np.argmax(ious)) if ious else -1
        if best >= 0 and ious[best] >= cfg.proposal_pos_iou:
            if best in eligible:
                pos.append((best, p.box2d))
        elif not ious or ious[best] < cfg.proposal_neg_iou:
            neg.append(p.box2d)
    for i in rng.permutation(len(pos))[: cfg.proposal_positives]:
        add_positive(*pos[int(i)])
    for i in rng.permutation(len(neg))[: cfg.proposal_negatives]:
        add_negative(neg[int(i)], NEG_PROPOSAL)


def build_frustum_dataset(
    frames: Iterable[Frame],
    num_points: int = 512,
    augment_copies: int = 2,
    rng_seed: int = 0,
    negatives_per_frame: int = 1,
    config: FrustumDatasetConfig | dict | None = None,
    progress: bool = False,
    **kwargs: Any,
) -> dict[str, np.ndarray]:
    """Training frustums of ``frames`` as a dict of numpy arrays (see the module docstring).

    Keyword arguments override fields of :class:`FrustumDatasetConfig` (``surface_samples``,
    ``max_parts``, ``min_points``, ``min_visible``, ``box_jitter``, ...). The result also
    holds ``"__config__"`` (a JSON string of the config) and ``"num_frames"``.
    """
    if isinstance(config, FrustumDatasetConfig):
        cfg = FrustumDatasetConfig(**config.to_dict())
    else:
        cfg = FrustumDatasetConfig.from_dict(config)
    cfg.num_points, cfg.augment_copies = int(num_points), int(augment_copies)
    cfg.rng_seed, cfg.negatives_per_frame = int(rng_seed), int(negatives_per_frame)
    for k, v in kwargs.items():
        if k not in cfg.__dataclass_fields__:
            raise TypeError(f"unknown dataset option {k!r}")
        setattr(cfg, k, v)
    b = _Builder(cfg)
    nf = 0
    for fi, frame in enumerate(frames):
        rng = np.random.default_rng([cfg.rng_seed, fi])
        _frame_frustums(frame, fi, cfg, rng, b)
        nf += 1
        if progress and nf % 100 == 0:
            print(f"  frustums: {nf} frames, {len(b.rows.get('seg', []))} frustums", flush=True)
    out = b.arrays()
    out["__config__"] = np.array(json.dumps(cfg.to_dict()))
    out["num_frames"] = np.array(nf, np.int64)
    return out


def cls_labels(ds: dict[str, np.ndarray], num_classes: int = NUM_CLASSES) -> np.ndarray:
    """Classification targets: class id, or ``num_classes`` (background) for negatives."""
    return np.where(ds["is_negative"], num_classes, ds["class_id"]).astype(np.int64)


def num_frustums(ds: dict[str, np.ndarray]) -> int:
    """Number of frustums (rows) of a dataset."""
    return int(ds["seg"].shape[0])


def subset(ds: dict[str, np.ndarray], idx: np.ndarray) -> dict[str, np.ndarray]:
    """Rows ``idx`` of every per-frustum array (scalars / strings copied)."""
    K = num_frustums(ds)
    return {k: (v[idx] if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == K else v) for k, v in ds.items()}


def concat(dsets: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate datasets built with the same config (frame indices are offset)."""
    out: dict[str, np.ndarray] = {}
    off = 0
    parts = []
    for d in dsets:
        d = dict(d)
        d["frame_index"] = d["frame_index"] + off
        off += int(d.get("num_frames", d["frame_index"].max() + 1 if len(d["frame_index"]) else 0))
        parts.append(d)
    for k in parts[0]:
        v = parts[0][k]
        if isinstance(v, np.ndarray) and v.ndim >= 1:
            out[k] = np.concatenate([p[k] for p in parts], 0)
        else:
            out[k] = v
    out["num_frames"] = np.array(off, np.int64)
    return out


def split_frames(frame_index: np.ndarray, val_fraction: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (train, val) of a split with whole frames on one side: ``val_fraction``
    of the distinct values of ``frame_index``, drawn with ``seed``."""
    frame_index = np.asarray(frame_index)
    frames = np.unique(frame_index)
    rng = np.random.default_rng(seed)
    nval = int(round(len(frames) * val_fraction))
    val_frames = rng.choice(frames, nval, replace=False) if nval > 0 else frames[:0]
    is_val = np.isin(frame_index, val_frames)
    return np.nonzero(~is_val)[0], np.nonzero(is_val)[0]


def split_by_frame(ds: dict[str, np.ndarray], val_fraction: float, seed: int = 0):
    """(train, val) split with whole frames on one side (:func:`split_frames`)."""
    tr, va = split_frames(ds["frame_index"], val_fraction, seed)
    return subset(ds, tr), subset(ds, va)


def save(ds: dict[str, np.ndarray], path: str | Path) -> Path:
    """Write to ``path`` (.npz, uncompressed: float16 point clouds barely compress)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **ds)
    tmp.replace(path)
    return path


def load(path: str | Path) -> dict[str, np.ndarray]:
    """A dataset written by :func:`save` (no pickled objects)."""
    with np.load(Path(path), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def dataset_config(ds: dict[str, np.ndarray]) -> dict[str, Any]:
    """The extraction settings a dataset was built with ({} when not recorded)."""
    return json.loads(str(ds["__config__"])) if "__config__" in ds else {}


def summary(ds: dict[str, np.ndarray]) -> dict[str, Any]:
    """Counts of a dataset: frustums, positives, negatives, frames, per class and negative kind."""
    neg = ds["is_negative"]
    cls = ds["class_id"][~neg]
    return {
        "frustums": num_frustums(ds),
        "positives": int((~neg).sum()),
        "negatives": int(neg.sum()),
        "frames": int(ds.get("num_frames", 0)),
        "with_shape": int(ds["has_shape"].sum()),
        "per_class": {int(c): int((cls == c).sum()) for c in np.unique(cls)},
        "neg_kinds": {int(k): int((ds["neg_kind"] == k).sum()) for k in np.unique(ds["neg_kind"][neg])},
    }
