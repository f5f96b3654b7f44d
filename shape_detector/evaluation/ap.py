"""Detection average precision, VOC / SUN RGB-D style, on 3D box IoU.

Per class and IoU threshold:

1. All detections of the class over all frames are sorted by score, highest first
   (ties keep their input order: frame order, then list order).
2. Each detection, in that order, is matched greedily to the **still unmatched,
   non-ignored** ground-truth object of its class in its frame with the highest 3D IoU,
   if that IoU is >= the threshold -> true positive, and that GT is used up. Otherwise,
   if it overlaps an *ignored* GT of its class by >= the threshold it is **ignored**
   (neither TP nor FP; it does not appear in the precision/recall curve; several
   detections may fall on one ignored GT). Otherwise it is a false positive -- this
   includes duplicates of a GT that an earlier (higher-scored) detection already took.
3. ``recall = cumTP / nGT`` (nGT counts the non-ignored GT only) and
   ``precision = cumTP / (cumTP + cumFP)`` along the ranked list.
4. AP is the all-points interpolated AP (VOC 2010+, SUN RGB-D / VoteNet): the area under
   the monotone precision envelope ``p_interp(r) = max_{r' >= r} p(r')``, computed
   exactly as a step integral over the recall values where recall changes.

Ignored ("difficult") GT: an object is ignored when it has a truthy ``ignore`` or
``difficult`` attribute, or when its ``visible_fraction`` is below ``min_visible``, or
when the caller passes explicit flags via ``ignore_per_frame``.

A class with no (non-ignored) GT has AP = NaN and is left out of the mAP (the mean over
the classes in ``classes`` that have GT). A class with GT but no detections has AP 0.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..classes import CLASSES
from ..box_iou import iou_matrix


def thr_key(t: float) -> str:
    """Dictionary key for an IoU threshold: ``0.25 -> "0.25"``, ``0.5 -> "0.5"``."""
    return f"{float(t):g}"


def voc_ap(recall: np.ndarray, precision: np.ndarray) -> float:
    """All-points interpolated AP: area under the monotone precision envelope.

    ``recall`` must be non-decreasing (as along a ranked list). Empty input gives 0.
    """
    rec = np.asarray(recall, dtype=np.float64).reshape(-1)
    prec = np.asarray(precision, dtype=np.float64).reshape(-1)
    if rec.size == 0:
        return 0.0
    mrec = np.concatenate([[0.0], rec, [1.0]])
    mpre = np.concatenate([[0.0], prec, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]  # envelope: max over recall >= r
    idx = np.nonzero(mrec[1:] != mrec[:-1])[0]
    return float(np.sum((mrec[idx + 1] - mrec[idx]) * mpre[idx + 1]))


def is_ignored(gt: Any, min_visible: float = 0.0) -> bool:
    """Whether a GT object is 'difficult': ``ignore``/``difficult`` flag or too occluded."""
    if bool(getattr(gt, "ignore", False)) or bool(getattr(gt, "difficult", False)):
        return True
    return float(getattr(gt, "visible_fraction", 1.0)) < float(min_visible)


def match_class(
    scores: Sequence[float],
    det_frames: Sequence[int],
    ious: Sequence[np.ndarray],
    gt_ignored: Sequence[np.ndarray],
    threshold: float,
) -> dict[str, Any]:
    """Greedy matching of one class's detections (see the module docstring).

    ``scores[d]``/``det_frames[d]``: score and frame index of detection ``d`` (class-local
    numbering); ``ious[f]``: (nDet_f, nGT_f) IoUs of frame ``f``'s detections of the class
    (rows in the order those detections appear in the global list) against its GT of the
    class; ``gt_ignored[f]``: (nGT_f,) bool. Returns ``order`` (detections by rank),
    ``status`` per detection (``"tp"``, ``"fp"``, ``"ignored"``), ``gt_index`` (frame-local
    GT column for TPs/ignored, -1 for FPs) and ``iou`` (the IoU of that match, or the best
    IoU for a FP).
    """
    n = len(scores)
    scores = np.asarray(scores, dtype=np.float64).reshape(n)
    det_frames = np.asarray(det_frames, dtype=np.int64).reshape(n)
    order = np.argsort(-scores, kind="stable")
    # row of each detection inside its frame's IoU matrix
    row = np.zeros(n, dtype=np.int64)
    counters: dict[int, int] = {}
    for d in range(n):
        f = int(det_frames[d])
        row[d] = counters.get(f, 0)
        counters[f] = row[d] + 1
    used = {f: np.zeros(len(gt_ignored[f]), dtype=bool) for f in counters}
    status = np.empty(n, dtype=object)
    gt_index = np.full(n, -1, dtype=np.int64)
    best_iou = np.zeros(n, dtype=np.float64)
    for d in order:
        f = int(det_frames[d])
        ign = np.asarray(gt_ignored[f], dtype=bool)
        ov = np.asarray(ious[f], dtype=np.float64)[row[d]] if ign.size else np.zeros(0)
        best_iou[d] = float(ov.max()) if ov.size else 0.0
        cand = np.where(~ign & ~used[f] & (ov >= threshold), ov, -np.inf)
        if cand.size and np.isfinite(cand.max()):
            g = int(np.argmax(cand))
            used[f][g] = True
            status[d], gt_index[d], best_iou[d] = "tp", g, float(ov[g])
            continue
        cand = np.where(ign & (ov >= threshold), ov, -np.inf)
        if cand.size and np.isfinite(cand.max()):
            g = int(np.argmax(cand))
            status[d], gt_index[d], best_iou[d] = "ignored", g, float(ov[g])
            continue
        status[d] = "fp"
    return {"order": order, "status": status, "gt_index": gt_index, "iou": best_iou}


def pr_curve(status_ranked: Sequence[str], num_gt: int) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall arrays along a ranked list of ``"tp"/"fp"/"ignored"`` statuses
    (ignored entries are dropped). Recall is NaN-free only when ``num_gt > 0``."""
    st = np.asarray([s for s in status_ranked if s != "ignored"], dtype=object)
    tp = np.cumsum(st == "tp").astype(np.float64)
    fp = np.cumsum(st == "fp").astype(np.float64)
    prec = tp / np.maximum(tp + fp, np.finfo(np.float64).eps)
    rec = tp / num_gt if num_gt > 0 else np.full_like(tp, np.nan)
    return prec, rec


def _class_overlaps(
    dets_per_frame: Sequence[Sequence[Any]], gts_per_frame: Sequence[Sequence[Any]],
    det_idx: list[list[int]], gt_idx: list[list[int]], min_visible: float,
    ignore_per_frame: Sequence[Sequence[bool]] | None, ups_per_frame: Sequence[np.ndarray | None] | None,
    iou_fn: Callable[[Sequence[Any], Sequence[Any]], np.ndarray] | None,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per frame, one class: which GT are ignored, and the (D, G) IoU matrix."""
    ignored, ious = [], []
    for f in range(len(gts_per_frame)):
        gts = [gts_per_frame[f][j] for j in gt_idx[f]]
        flags = [is_ignored(g, min_visible) for g in gts]
        if ignore_per_frame is not None:
            flags = [a or bool(ignore_per_frame[f][j]) for a, j in zip(flags, gt_idx[f])]
        ignored.append(np.asarray(flags, dtype=bool))
        dets = [dets_per_frame[f][j] for j in det_idx[f]]
        if dets and gts:
            if iou_fn is not None:
                m = np.asarray(iou_fn(dets, gts), dtype=np.float64)
            else:
                m = iou_matrix(dets, gts, up=None if ups_per_frame is None else ups_per_frame[f])
        else:
            m = np.zeros((len(dets), len(gts)))
        ious.append(m)
    return ignored, ious


def _score_class(
    res: dict[str, Any], cls: str, dets_per_frame: Sequence[Sequence[Any]], det_idx: list[list[int]],
    gt_idx: list[list[int]], ignored: list[np.ndarray], ious: list[np.ndarray],
    thresholds: list[float], keys: list[str],
) -> None:
    """Match one class's detections at every threshold and fill its rows of ``res``."""
    num_gt = int(sum(int((~ig).sum()) for ig in ignored))
    res["num_gt"][cls] = num_gt
    res["num_ignored_gt"][cls] = int(sum(int(ig.sum()) for ig in ignored))
    flat = [(f, j) for f in range(len(det_idx)) for j in det_idx[f]]
    res["num_det"][cls] = len(flat)
    scores = [float(dets_per_frame[f][j].score) for f, j in flat]
    frames = [f for f, _ in flat]
    for t, k in zip(thresholds, keys):
        m = match_class(scores, frames, ious, ignored, t)
        ranked = [m["status"][d] for d in m["order"]]
        prec, rec = pr_curve(ranked, num_gt)
        res["precision"][k][cls] = prec.tolist()
        res["recall"][k][cls] = rec.tolist()
        res["scores"][k][cls] = [scores[d] for d in m["order"] if m["status"][d] != "ignored"]
        res["ap"][k][cls] = voc_ap(rec, prec) if num_gt > 0 else float("nan")
        for d in m["order"]:
            f, j = flat[d]
            res["det_status"][k][f][j] = str(m["status"][d])
            if m["status"][d] == "tp":
                res["matches"][k].append({"frame": f, "det": j, "gt": gt_idx[f][int(m["gt_index"][d])],
                                          "iou": float(m["iou"][d]), "class": cls, "score": scores[d]})


def evaluate_detections(
    dets_per_frame: Sequence[Sequence[Any]],
    gts_per_frame: Sequence[Sequence[Any]],
    iou_thresholds: Sequence[float] = (0.25, 0.5),
    classes: Sequence[str] = CLASSES,
    *,
    min_visible: float = 0.0,
    ignore_per_frame: Sequence[Sequence[bool]] | None = None,
    ups_per_frame: Sequence[np.ndarray | None] | None = None,
    iou_fn: Callable[[Sequence[Any], Sequence[Any]], np.ndarray] | None = None,
) -> dict[str, Any]:
    """Per-class AP / mAP at each IoU threshold, plus the matching.

    ``dets_per_frame[f]``: detections of frame ``f`` with ``class_name``, ``score``,
    ``center``, ``size``, ``rotation`` (e.g. :class:`~shape_detector.types.Object3D`);
    ``gts_per_frame[f]``: its GT (e.g. :class:`~shape_detector.types.GTObject`).
    ``ignore_per_frame[f][g]`` forces GT ``g`` of frame ``f`` to be ignored (in addition to
    :func:`is_ignored` with ``min_visible``). ``ups_per_frame[f]``: the vertical for the
    exact IoU (None -> from the boxes). ``iou_fn(dets, gts) -> (D,G)`` replaces the 3D IoU.

    Returns (threshold keys from :func:`thr_key`; detection/GT indices are positions in
    the caller's per-frame lists)::

        {"iou_thresholds": [..], "classes": [..],
         "num_gt": {cls: n}, "num_ignored_gt": {cls: n}, "num_det": {cls: n},
         "ap": {"0.25": {cls: AP or nan}}, "mAP": {"0.25": mAP or nan},
         "precision": {"0.25": {cls: [..]}}, "recall": {...}, "scores": {...},
         "matches": {"0.25": [{"frame", "det", "gt", "iou", "class", "score"}]},   # TPs
         "det_status": {"0.25": [[status per det of frame f] for f]}}  # tp/fp/ignored/other
    """
    if len(dets_per_frame) != len(gts_per_frame):
        raise ValueError("dets_per_frame and gts_per_frame must have one entry per frame")
    nf = len(gts_per_frame)
    thresholds = [float(t) for t in iou_thresholds]
    keys = [thr_key(t) for t in thresholds]
    classes = list(classes)

    res: dict[str, Any] = {
        "iou_thresholds": thresholds,
        "classes": classes,
        "num_gt": {},
        "num_ignored_gt": {},
        "num_det": {},
        "ap": {k: {} for k in keys},
        "mAP": {},
        "precision": {k: {} for k in keys},
        "recall": {k: {} for k in keys},
        "scores": {k: {} for k in keys},
        "matches": {k: [] for k in keys},
        "det_status": {k: [["other"] * len(dets_per_frame[f]) for f in range(nf)] for k in keys},
    }

    for cls in classes:
        det_idx = [[j for j, d in enumerate(dets_per_frame[f]) if d.class_name == cls] for f in range(nf)]
        gt_idx = [[j for j, g in enumerate(gts_per_frame[f]) if g.class_name == cls] for f in range(nf)]
        ignored, ious = _class_overlaps(dets_per_frame, gts_per_frame, det_idx, gt_idx, min_visible,
                                        ignore_per_frame, ups_per_frame, iou_fn)
        _score_class(res, cls, dets_per_frame, det_idx, gt_idx, ignored, ious, thresholds, keys)
    for k in keys:
        vals = [v for c, v in res["ap"][k].items() if res["num_gt"][c] > 0]
        res["mAP"][k] = float(np.mean(vals)) if vals else float("nan")
    return res


def expand_class_hypotheses(dets: Sequence[Any], k: int, classes: Sequence[str] = CLASSES) -> list[Any]:
    """Each detection as up to ``k`` detections, one per class among its ``k`` most probable,
    scored by that class's probability (the per-class-proposal protocol VoteNet and others
    use on SUN RGB-D: a box may count for its second guess). Detections without
    ``class_scores`` (a per-class probability vector over ``classes``) pass through as they
    are; ``k`` <= 1 returns them unchanged. Copies; the inputs are not modified."""
    if k <= 1:
        return list(dets)
    out = []
    for d in dets:
        scores = getattr(d, "class_scores", None)
        if scores is None or len(scores) != len(classes):
            out.append(d)
            continue
        scores = np.asarray(scores, dtype=np.float64)
        for c in np.argsort(-scores, kind="stable")[:k]:
            e = copy.copy(d)
            e.class_name, e.score = classes[int(c)], float(scores[c])
            out.append(e)
    return out
