"""3D association of detections to tracks (world frame, z up).

The cost of pairing a detection with a track is their horizontal centre distance in units
of the pair's mean footprint radius, plus a height-offset term, plus a class term
``class_weight * (1 - p)``, where ``p`` is the track's accumulated probability of the
detection's class. A single frame's class flip therefore costs at most ``class_weight``
and still matches a nearby track; two different objects side by side keep their own
tracks because the Hungarian assignment takes the cheapest joint pairing.

Two tracks are one object (:func:`duplicates`) when their boxes overlap a lot (3D
IoU), or when one is mostly nested in the other and either their classes agree or it has
far less evidence (a partial view of a big object); a chair pushed under a table is nested
in it but keeps its own track. A weak track that overlaps a much stronger one of its class
only in part is a displaced duplicate (early views placed it beside the object) and is
dropped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..box_iou import clip_convex, polygon_area
from .tracks import Observation, Track, _CLASS_INDEX

#: cost of a forbidden pair (outside the gate)
BIG = 1e6
#: a track with at most this share of another's fusion weight, nested in it, merges whatever its class
WEAK_SHARE = 0.15


def footprint_radius(size: np.ndarray) -> np.ndarray:
    """Half the diagonal of the horizontal footprint (m), at least 0.15 m; size (..., 3)."""
    s = np.asarray(size, dtype=np.float64)
    return np.maximum(0.5 * np.hypot(s[..., 0], s[..., 1]), 0.15)


def cost_matrix(tracks: Sequence[Track], obs: Sequence[Observation], class_weight: float = 0.4) -> np.ndarray:
    """(T, D) association costs (dimensionless; < 1 is a plausible pair)."""
    if not tracks or not obs:
        return np.zeros((len(tracks), len(obs)))
    tc = np.stack([t.center for t in tracks])
    ts = np.stack([t.size for t in tracks])
    dc = np.stack([o.center for o in obs])
    ds = np.stack([o.size for o in obs])
    rad = 0.5 * (footprint_radius(ts)[:, None] + footprint_radius(ds)[None, :])
    dxy = np.linalg.norm(tc[:, None, :2] - dc[None, :, :2], axis=2)
    hh = 0.25 * (ts[:, None, 2] + ds[None, :, 2])
    dz = np.abs(tc[:, None, 2] - dc[None, :, 2]) / np.maximum(hh, 0.1)
    probs = np.stack([t.class_probs for t in tracks])
    idx = np.array([_CLASS_INDEX.get(o.class_name, 0) for o in obs])
    p = probs[:, idx]
    return dxy / rad + 0.3 * dz + class_weight * (1.0 - p)


def associate(cost: np.ndarray, gate: float) -> tuple[list[tuple[int, int]], list[int], list[int]]:
    """Hungarian assignment under ``gate``: (pairs (track, det), unmatched tracks,
    unmatched detections)."""
    T, D = cost.shape
    if T == 0 or D == 0:
        return [], list(range(T)), list(range(D))
    c = np.where(cost < gate, cost, BIG)
    rows, cols = linear_sum_assignment(c)
    pairs = [(int(r), int(k)) for r, k in zip(rows, cols) if c[r, k] < BIG]
    mt = {r for r, _ in pairs}
    md = {k for _, k in pairs}
    return pairs, [i for i in range(T) if i not in mt], [j for j in range(D) if j not in md]


def _footprint(t: Track) -> np.ndarray:
    """(4,2) world footprint corners of a track's box."""
    c, s, yaw = t.center, t.size, t.yaw
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    return (signs * 0.5 * s[:2]) @ R.T + c[:2]


def overlap(a: Track, b: Track) -> tuple[float, float]:
    """(IoU, intersection over the smaller volume) of two tracks' yaw-only boxes."""
    fa, fb = _footprint(a), _footprint(b)
    if np.any(fa.max(0) <= fb.min(0)) or np.any(fb.max(0) <= fa.min(0)):
        return 0.0, 0.0  # the footprints' bounding rectangles are apart (half of the pairs tested)
    inter2 = clip_convex(fa, fb)
    area = abs(polygon_area(inter2)) if len(inter2) >= 3 else 0.0
    if area <= 0.0:
        return 0.0, 0.0
    dz = min(a.center[2] + 0.5 * a.size[2], b.center[2] + 0.5 * b.size[2]) - \
        max(a.center[2] - 0.5 * a.size[2], b.center[2] - 0.5 * b.size[2])
    inter = area * max(dz, 0.0)
    va, vb = float(np.prod(a.size)), float(np.prod(b.size))
    return inter / max(va + vb - inter, 1e-9), inter / max(min(va, vb), 1e-9)


def class_similarity(a: Track, b: Track) -> float:
    """Probability that two tracks have the same class under their class distributions (0..1)."""
    return float(a.class_probs @ b.class_probs)


def duplicates(tracks: Sequence[Track], min_iou: float = 0.4, min_ios: float = 0.6,
               min_same_class: float = 0.2, displaced_iou: float = 0.0,
               displaced_share: float = 0.3) -> tuple[list[tuple[int, int]], list[int]]:
    """Tracks that are one object: (index pairs (i, j), i < j, to merge, most overlapping first;
    indices of displaced duplicates to drop).

    A pair merges at 3D IoU >= ``min_iou`` whatever their classes, or at intersection over the
    smaller box >= ``min_ios`` when their classes agree with probability >= ``min_same_class``
    (a chair pushed under a table overlaps it but keeps its own track). A track is a displaced
    duplicate when it overlaps (IoU >= ``displaced_iou`` > 0) a track of agreeing class that
    has at least 1 / ``displaced_share`` times its fusion weight: a few early, misplaced views
    of an object another track now holds. Its evidence is dropped rather than merged, which
    would pull the good box towards the misplaced one."""
    n = len(tracks)
    if n < 2:
        return [], []
    c = np.stack([t.center for t in tracks])
    r = 0.5 * np.stack([np.linalg.norm(t.size) for t in tracks])
    near = np.linalg.norm(c[:, None] - c[None], axis=2) < (r[:, None] + r[None])
    found, displaced = [], set()
    for i, j in zip(*np.nonzero(np.triu(near, 1))):
        iou, ios = overlap(tracks[i], tracks[j])
        wi, wj = tracks[i].weight_sum, tracks[j].weight_sum
        weak = min(wi, wj) <= WEAK_SHARE * max(wi, wj)  # a weak box nested in a strong one is part of it
        if iou >= min_iou or (ios >= min_ios and (weak or class_similarity(tracks[i], tracks[j]) >= min_same_class)):
            found.append((max(iou, ios), int(i), int(j)))
        elif (0.0 < displaced_iou <= iou and min(wi, wj) <= displaced_share * max(wi, wj)
              and class_similarity(tracks[i], tracks[j]) >= min_same_class):
            displaced.add(int(i) if wi < wj else int(j))
    found.sort(reverse=True)
    return [(i, j) for _, i, j in found], sorted(displaced)
