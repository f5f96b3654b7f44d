"""Run a detector over frames with ground truth and compute every metric.

:func:`evaluate` calls ``detect_fn(frame, boxes2d)`` on each frame, then computes

* detection AP at each IoU threshold and mAP (:mod:`.ap`); GT objects with
  ``visible_fraction < min_visible`` are *ignored* GT (detections on them count neither
  way);
* box errors (:mod:`.box_metrics`) over **pairs**: in GT-box mode each detection is paired
  with the GT object whose 2D box it was given (recognised by equal ``box2d`` and class),
  so failures with low IoU are included as in the thesis' Table 4.1; detections whose box
  is not recognised, and all detections in detector-box mode, are paired through the AP
  matching at the lowest IoU threshold. Ignored GT form no pairs;
* shape metrics (:mod:`.shape_metrics`) for pairs whose GT has ``parts``: in the camera
  frame and in each box's own normalised frame (predicted primitives in the predicted
  box frame, GT parts in the GT box frame, both scaled to unit box diagonal), and the IoU
  box-relative (each set scaled per axis to its own box's unit cube). Pairs whose
  detection has no primitives are counted as ``missing_primitives``, not scored;
* seconds per ``detect_fn`` call.

Segmentation accuracy: taken from a detection's ``seg_accuracy`` attribute when present;
otherwise computed when the detection carries ``pixel_index`` (flat ``v * W + u`` indices
of its frustum points, as :class:`shape_detector.frustum.Frustum`) and ``seg_labels``
(per-point 0/1 or probabilities) and the frame has an ``instance_mask``: the GT label of
a point is ``instance_mask.flat[pixel_index] == gt.instance_id``. Otherwise it is skipped.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..classes import CLASSES
from ..types import Frame, Object3D
from .ap import evaluate_detections, expand_class_hypotheses, is_ignored, thr_key
from .box_metrics import aggregate_box_errors, pair_errors, segmentation_accuracy
from .report import to_jsonable
from .shape_metrics import box_relative_iou, shape_iou, surface_distance, to_box_frame

DetectFn = Callable[[Frame, "list[tuple[float, float, float, float, str]] | None"], "list[Object3D]"]


def gt_boxes2d(frame: Frame, classes: Sequence[str] = CLASSES) -> tuple[list[tuple], list[int]]:
    """The frame's GT 2D boxes ``(x1, y1, x2, y2, class)`` of visible objects of ``classes``
    and, for each, the index of its GT object."""
    boxes, src = [], []
    for i, g in enumerate(frame.objects):
        x1, y1, x2, y2 = (float(v) for v in g.box2d)
        if g.class_name in classes and x2 > x1 and y2 > y1 and float(g.visible_fraction) > 0.0:
            boxes.append((x1, y1, x2, y2, g.class_name))
            src.append(i)
    return boxes, src


#: ``--gt-2d`` of the walk-through evaluations: the true 2D boxes instead of the proposals
GT_2D_CHOICES = ("boxes", "classes")


def given_boxes2d(frame: Frame, gt_2d: str | None) -> list[tuple] | None:
    """The 2D boxes a walk-through evaluation gives the detector for ``frame``: None (its own
    proposals) without ``gt_2d``; the frame's GT boxes (:func:`gt_boxes2d`) with their class
    for ``"classes"``, without it for ``"boxes"``. An upper bound for analysis: what an ideal
    2D detector (class-agnostic, or with classes) would give the rest of the pipeline."""
    if gt_2d is None:
        return None
    if gt_2d not in GT_2D_CHOICES:
        raise ValueError(f"gt_2d must be one of {GT_2D_CHOICES} or None, got {gt_2d!r}")
    boxes, _ = gt_boxes2d(frame)
    return boxes if gt_2d == "classes" else [b[:4] for b in boxes]


def detect_walkthrough_frame(detector: Any, frame: Frame, up: np.ndarray | None, gt_2d: str | None) -> list[Any]:
    """``detector.detect`` on a walk-through frame with its own proposals, or with the boxes
    of :func:`given_boxes2d`; with ``gt_2d`` and nothing in view, no call and no objects (a 2D
    detector that finds nothing)."""
    boxes = given_boxes2d(frame, gt_2d)
    if boxes is None:
        return detector.detect(frame.rgb, frame.depth, frame.K, up=up)
    return detector.detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes, up=up) if boxes else []


def _stats(values: Sequence[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "median": float("nan")}
    return {"mean": float(v.mean()), "median": float(np.median(v))}


def _seg_gt_ids(det: Any, frame: Frame) -> np.ndarray | None:
    """Instance ids under a detection's points (for seg accuracy), or None."""
    if getattr(det, "seg_accuracy", None) is not None or frame.instance_mask is None:
        return None
    idx = getattr(det, "pixel_index", None)
    if idx is None or getattr(det, "seg_labels", None) is None:
        return None
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    flat = np.asarray(frame.instance_mask).reshape(-1)
    if idx.size == 0 or idx.min() < 0 or idx.max() >= flat.size:
        return None
    return flat[idx]


#: per-pair shape metrics: camera frame, isotropic object frame, box-relative (IoU only)
SHAPE_KEYS = ("iou_camera", "distance_camera", "iou_object", "distance_object", "iou_box")


def _summarize_shape(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {"n": len(records)}
    for key in SHAPE_KEYS:
        out[key] = _stats([r[key] for r in records])
    return out


def _class_mean(records: Sequence[dict[str, Any]], classes: Sequence[str]) -> dict[str, Any]:
    """Each shape metric's mean over the classes with pairs of their per-class means (the
    thesis' and the issue's 'averaged over classes'; ``all`` weights classes by pair count)."""
    out: dict[str, Any] = {"n": 0, "classes": 0}
    per = [[r for r in records if r["class"] == c] for c in classes]
    per = [rs for rs in per if rs]
    out["n"], out["classes"] = sum(len(rs) for rs in per), len(per)
    for key in SHAPE_KEYS:
        means = [_stats([r[key] for r in rs])["mean"] for rs in per]
        means = [m for m in means if np.isfinite(m)]
        out[key] = {"mean": float(np.mean(means)) if means else float("nan")}
    return out


@dataclass
class _Collected:
    """Per-frame detections, GT and what pairs them, gathered by :func:`_run_frames`."""

    dets: list[list[Any]] = field(default_factory=list)
    gts: list[list[Any]] = field(default_factory=list)
    ups: list[np.ndarray | None] = field(default_factory=list)
    provenance: list[dict[int, int]] = field(default_factory=list)  # det index -> GT index (GT-box mode)
    seg_ids: list[dict[int, np.ndarray]] = field(default_factory=list)
    times: list[float] = field(default_factory=list)


def _given_box_owner(dets: list[Any], boxes: list, src: list[int]) -> dict[int, int]:
    """Detection index -> GT index for detections made from a given GT 2D box."""
    prov: dict[int, int] = {}
    free = list(range(len(boxes)))
    for j, d in enumerate(dets):
        db = np.asarray(getattr(d, "box2d", (0, 0, 0, 0))[:4], dtype=np.float64)
        for k in free:  # by the box alone: without the GT class the detector may name another
            if np.allclose(db, boxes[k][:4], atol=1e-6):
                prov[j] = src[k]
                free.remove(k)
                break
    return prov


def _run_frames(detect_fn: DetectFn, frames: Iterable[Frame], use_gt_boxes: bool, classes: list[str],
                max_frames: int | None, progress: Callable[[int, float], None] | None,
                gt_class: bool = True) -> _Collected:
    """Run ``detect_fn`` on every frame, timing it, and keep what the metrics need; with
    ``gt_class`` false the GT boxes go without their class."""
    c = _Collected()
    for i, frame in enumerate(frames):
        if max_frames is not None and i >= max_frames:
            break
        boxes, src = gt_boxes2d(frame, classes) if use_gt_boxes else (None, [])
        given = boxes if gt_class or boxes is None else [b[:4] for b in boxes]
        t0 = time.perf_counter()
        dets = list(detect_fn(frame, given))
        dt = time.perf_counter() - t0
        c.times.append(dt)
        c.provenance.append(_given_box_owner(dets, boxes, src) if boxes else {})
        c.seg_ids.append({j: ids for j, d in enumerate(dets) if (ids := _seg_gt_ids(d, frame)) is not None})
        c.dets.append(dets)
        c.gts.append(list(frame.objects))
        c.ups.append(None if frame.up is None else np.asarray(frame.up, dtype=np.float64))
        if progress is not None:
            progress(i, dt)
    return c


def _pairs(c: _Collected, detection: dict[str, Any], key0: str | None, classes: list[str],
           min_visible: float) -> list[tuple[int, int, int, str]]:
    """``(frame, det, gt, how)``: each detection paired with the GT it was made from (given
    box) or matched to by AP at the lowest IoU threshold; each GT at most once."""
    ap_pairs = {(m["frame"], m["det"]): m["gt"] for m in detection["matches"].get(key0, [])} if key0 else {}
    pairs: list[tuple[int, int, int, str]] = []
    for f in range(len(c.dets)):
        used: set[int] = set()
        for j in range(len(c.dets[f])):
            if j in c.provenance[f]:
                g, how = c.provenance[f][j], "gt_box"
            elif (f, j) in ap_pairs:
                g, how = ap_pairs[(f, j)], f"iou>={key0}"
            else:
                continue
            gt = c.gts[f][g]
            if g in used or is_ignored(gt, min_visible) or gt.class_name not in classes:
                continue
            used.add(g)
            pairs.append((f, j, g, how))
    return pairs


def _shape_record(det: Any, gt: Any, shape_resolution: int, surface_samples: int,
                  rng: np.random.Generator) -> dict[str, Any]:
    """Shape metrics of a paired detection's primitives against the GT parts."""
    prims = list(det.primitives)
    po = to_box_frame(prims, det.center, det.rotation, det.size, normalise=True)
    go = to_box_frame(gt.parts, gt.center, gt.rotation, gt.size, normalise=True)
    return {
        "class": gt.class_name,
        "iou_camera": shape_iou(prims, gt.parts, shape_resolution),
        "distance_camera": surface_distance(prims, gt.parts, surface_samples, rng),
        "iou_object": shape_iou(po, go, shape_resolution),
        "distance_object": surface_distance(po, go, surface_samples, rng),
        "iou_box": box_relative_iou(
            prims, (det.center, det.rotation, det.size), gt.parts, (gt.center, gt.rotation, gt.size),
            shape_resolution,
        ),
    }


def _pair_records(c: _Collected, pairs: list[tuple[int, int, int, str]], shape_resolution: int,
                  surface_samples: int, rng: np.random.Generator) -> tuple[list[dict], list[dict], int]:
    """Box-error records of every pair, the shape records, and how many pairs had no primitives."""
    records, shape_records, missing = [], [], 0
    for f, j, g, how in pairs:
        det, gt = c.dets[f][j], c.gts[f][g]
        rec = pair_errors(det, gt, c.ups[f])
        rec.update({"frame": f, "det": j, "gt": g, "pairing": how, "score": float(getattr(det, "score", 0.0))})
        if "seg_accuracy" not in rec and j in c.seg_ids[f]:
            labels = np.asarray(det.seg_labels).reshape(-1)
            ids = c.seg_ids[f][j]
            if labels.size == ids.size:
                rec["seg_accuracy"] = segmentation_accuracy(labels, ids == int(gt.instance_id))
        if gt.parts:
            if not list(getattr(det, "primitives", []) or []):
                missing += 1
            else:
                s = _shape_record(det, gt, shape_resolution, surface_samples, rng)
                shape_records.append(s)
                rec.update({k: v for k, v in s.items() if k != "class"})
        records.append(rec)
    return records, shape_records, missing


def _shape_summary(shape_records: list[dict], classes: list[str], missing: int, shape_resolution: int,
                   surface_samples: int) -> dict[str, Any]:
    return {
        "per_class": {c: _summarize_shape([r for r in shape_records if r["class"] == c]) for c in classes},
        "all": _summarize_shape(shape_records),
        "class_mean": _class_mean(shape_records, classes),
        "missing_primitives": missing,
        "note": (
            f"IoU: {shape_resolution}^3 voxel grid over the union bounds; surface distance: symmetric "
            f"chamfer of {surface_samples} surface samples per set over the GT corner-set diameter. "
            "Object frame: each set in its own box frame scaled to unit box diagonal. "
            "Box-relative: each set in its own box scaled per axis to the unit cube (the box error "
            "left out; the GT parts in any box score 1). "
            f"{missing} paired detections had no primitives (not scored)."
        ),
    }


def _timing(times: list[float]) -> dict[str, Any]:
    t = np.asarray(times, dtype=np.float64)
    timing: dict[str, Any] = {"frames": int(t.size)}
    if t.size:
        timing.update({
            "total_s": float(t.sum()), "mean_s": float(t.mean()), "median_s": float(np.median(t)),
            "p90_s": float(np.percentile(t, 90)), "max_s": float(t.max()),
            "fps": float(1.0 / t.mean()) if t.mean() > 0 else float("nan"),
        })
    timing["per_frame_s"] = t.tolist()
    return timing


def evaluate(
    detect_fn: DetectFn,
    frames: Iterable[Frame],
    use_gt_boxes: bool,
    min_visible: float = 0.0,
    *,
    iou_thresholds: Sequence[float] = (0.25, 0.5),
    classes: Sequence[str] = CLASSES,
    shape_resolution: int = 32,
    surface_samples: int = 5000,
    seed: int = 0,
    max_frames: int | None = None,
    progress: Callable[[int, float], None] | None = None,
    keep_pairs: bool = True,
    class_hypotheses: int = 1,
    gt_class: bool = True,
) -> dict[str, Any]:
    """Evaluate ``detect_fn`` on ``frames`` (each with GT ``objects``); JSON-able result.

    ``detect_fn(frame, boxes2d)`` gets the GT 2D boxes (``(x1, y1, x2, y2, class)``, see
    :func:`gt_boxes2d`; with ``gt_class`` false ``(x1, y1, x2, y2)``: the detector names the
    class) when ``use_gt_boxes`` is true, else None, and returns
    ``Object3D``-like detections. ``surface_samples`` points per set for the surface
    distance, ``shape_resolution`` voxels per axis for the shape IoU, ``seed`` for the
    surface sampling. ``progress(i, seconds)`` is called after each frame.

    Returns ``{"settings", "num_frames", "detection" (see
    :func:`~.ap.evaluate_detections`), "box_errors" ({"pairing", "per_class", "all"}),
    "shape" ({"per_class", "all", "missing_primitives", "note"}), "timing", "pairs"}``
    with NaN turned into None.
    """
    classes = list(classes)
    thresholds = [float(t) for t in iou_thresholds]
    c = _run_frames(detect_fn, frames, use_gt_boxes, classes, max_frames, progress, gt_class)
    detection = evaluate_detections(c.dets, c.gts, thresholds, classes, min_visible=min_visible, ups_per_frame=c.ups)
    hypotheses = None
    if class_hypotheses > 1 and not (use_gt_boxes and gt_class):
        h = evaluate_detections([expand_class_hypotheses(d, class_hypotheses, classes) for d in c.dets],
                                c.gts, thresholds, classes, min_visible=min_visible, ups_per_frame=c.ups)
        hypotheses = {"k": int(class_hypotheses), "ap": h["ap"], "mAP": h["mAP"], "num_det": h["num_det"]}

    key0 = thr_key(min(thresholds)) if thresholds else None
    pairs = _pairs(c, detection, key0, classes, min_visible)
    records, shape_records, missing = _pair_records(c, pairs, shape_resolution, surface_samples,
                                                    np.random.default_rng(seed))
    box = aggregate_box_errors(records, classes)
    n_gtbox = sum(1 for r in records if r["pairing"] == "gt_box")
    box["pairing"] = (
        f"{len(records)} pairs: {n_gtbox} by the GT 2D box the detection was given, "
        f"{len(records) - n_gtbox} by 3D IoU >= {key0} (AP matching)"
    )
    results = {
        "settings": {
            "mode": ("gt_boxes" if gt_class else "gt_boxes_without_class") if use_gt_boxes else "detector_boxes",
            "min_visible": float(min_visible),
            "iou_thresholds": thresholds,
            "shape_resolution": int(shape_resolution),
            "surface_samples": int(surface_samples),
            "seed": int(seed),
        },
        "num_frames": len(c.dets),
        "detection": detection,
        **({"detection_class_hypotheses": hypotheses} if hypotheses is not None else {}),
        "box_errors": box,
        "shape": _shape_summary(shape_records, classes, missing, shape_resolution, surface_samples),
        "timing": _timing(c.times),
    }
    if keep_pairs:
        results["pairs"] = records
    return to_jsonable(results)
