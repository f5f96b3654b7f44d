"""Box error metrics for matched (prediction, ground truth) pairs -- thesis Table 4.1.

Array functions work on N pairs at once; :func:`pair_errors` computes every metric of one
pair of box-like objects (``.center/.size/.rotation``), :func:`aggregate_box_errors` turns
a list of such records into per-class means/medians.

* centroid error: Euclidean distance of the box centres (m);
* size error: per-dimension absolute ``|l-l*|, |w-w*|, |h-h*|`` (m) and relative
  ``|s-s*| / s*``; the scalar summaries are the mean over the three dimensions;
* heading error: ``|wrap(theta - theta*)|`` in [0, pi]; the 180-degree-symmetric version
  ``min(e, pi - e)`` in [0, pi/2] ignores front/back flips (a box is the same set either
  way);
* corner error: mean distance between corresponding corners of
  :func:`shape_detector.geometry.box_corners` (same corner ordering -- this *is* the
  correspondence, so heading flips are penalised); the flip-invariant variant takes the
  smaller of that and the error against the GT box turned by 180 degrees about its
  vertical (the Frustum-PointNet corner-loss convention);
* 3D IoU: :func:`shape_detector.box_iou.box3d_iou`;
* segmentation accuracy: share of points whose predicted object/background label equals
  the GT label.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from ..classes import CLASSES
from ..geometry import box_corners, rotation_to_heading, wrap_angle
from ..box_iou import box3d_iou

#: corner permutation of :func:`box_corners` for the same box turned 180 degrees about z
_FLIP_Z = np.array([2, 3, 0, 1, 6, 7, 4, 5])


def centroid_error(pred_centers: np.ndarray, gt_centers: np.ndarray) -> np.ndarray:
    """(N,) distances between (N,3) predicted and GT centres."""
    p = np.asarray(pred_centers, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(gt_centers, dtype=np.float64).reshape(-1, 3)
    return np.linalg.norm(p - g, axis=1)


def size_error(pred_sizes: np.ndarray, gt_sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension absolute (N,3) and relative (N,3) size errors (relative: ``/ gt``)."""
    p = np.asarray(pred_sizes, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(gt_sizes, dtype=np.float64).reshape(-1, 3)
    ab = np.abs(p - g)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(g > 0, ab / np.where(g > 0, g, 1.0), np.nan)
    return ab, rel


def heading_error(pred_headings: np.ndarray, gt_headings: np.ndarray, symmetric: bool = False) -> np.ndarray:
    """(N,) absolute wrapped heading differences in radians, in [0, pi].

    ``symmetric=True``: modulo 180 degrees, ``min(e, pi - e)`` in [0, pi/2].
    """
    e = np.abs(wrap_angle(np.asarray(pred_headings, dtype=np.float64) - np.asarray(gt_headings, dtype=np.float64)))
    e = np.minimum(e, 2 * np.pi - e)  # wrap_angle gives [-pi, pi): |.| may be pi exactly
    if symmetric:
        e = np.minimum(e, np.pi - e)
    return np.atleast_1d(e)


def corner_error(pred_corners: np.ndarray, gt_corners: np.ndarray, flip_invariant: bool = False) -> np.ndarray:
    """(N,) mean distance between corresponding corners of (N,8,3) corner sets.

    ``flip_invariant``: also compare against the GT corners of the box turned by 180
    degrees about its vertical (z) axis and keep the smaller error.
    """
    p = np.asarray(pred_corners, dtype=np.float64).reshape(-1, 8, 3)
    g = np.asarray(gt_corners, dtype=np.float64).reshape(-1, 8, 3)
    e = np.linalg.norm(p - g, axis=2).mean(1)
    if flip_invariant:
        e = np.minimum(e, np.linalg.norm(p - g[:, _FLIP_Z], axis=2).mean(1))
    return e


def segmentation_accuracy(pred_labels: np.ndarray, gt_labels: np.ndarray) -> float:
    """Share of points whose predicted label equals the GT label (NaN for no points).

    Labels are compared as integers after thresholding floats at 0.5 (so probabilities
    or bool masks may be given for the binary object/background case).
    """
    p = np.asarray(pred_labels).reshape(-1)
    g = np.asarray(gt_labels).reshape(-1)
    if p.shape != g.shape:
        raise ValueError(f"label arrays differ in length: {p.shape} vs {g.shape}")
    if p.size == 0:
        return float("nan")
    if p.dtype.kind == "f":
        p = p >= 0.5
    if g.dtype.kind == "f":
        g = g >= 0.5
    return float(np.mean(p.astype(np.int64) == g.astype(np.int64)))


def heading_of(box: Any, up: np.ndarray | None) -> float:
    """Heading (rad) of a box's x axis in the upright frame of ``up``."""
    return rotation_to_heading(np.asarray(box.rotation, dtype=np.float64), up)


def pair_errors(pred: Any, gt: Any, up: np.ndarray | None = None) -> dict[str, Any]:
    """Every Table-4.1 metric for one matched pair of box-like objects (same frame).

    ``up``: the vertical used for headings and the exact IoU; None -> the z column of the
    GT rotation (gravity-up by convention). The record also carries ``class`` (from
    ``gt.class_name`` when present) and ``seg_accuracy`` when ``pred`` has that attribute.
    """
    u = np.asarray(gt.rotation, dtype=np.float64)[:, 2] if up is None else np.asarray(up, dtype=np.float64)
    ab, rel = size_error(pred.size, gt.size)
    hp, hg = heading_of(pred, u), heading_of(gt, u)
    cp = box_corners(pred.center, pred.size, pred.rotation)[None]
    cg = box_corners(gt.center, gt.size, gt.rotation)[None]
    rec: dict[str, Any] = {
        "class": getattr(gt, "class_name", getattr(pred, "class_name", "")),
        "centroid_error": float(centroid_error(pred.center, gt.center)[0]),
        "size_abs_error": ab[0].tolist(),
        "size_rel_error": rel[0].tolist(),
        "heading_error_rad": float(heading_error(hp, hg)[0]),
        "heading_error_sym_rad": float(heading_error(hp, hg, symmetric=True)[0]),
        "corner_error": float(corner_error(cp, cg)[0]),
        "corner_error_flip": float(corner_error(cp, cg, flip_invariant=True)[0]),
        "iou3d": box3d_iou(pred.center, pred.size, pred.rotation, gt.center, gt.size, gt.rotation, u),
    }
    seg = getattr(pred, "seg_accuracy", None)
    if seg is not None:
        rec["seg_accuracy"] = float(seg)
    return rec


def _stats(values: Sequence[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "median": float("nan")}
    return {"mean": float(v.mean()), "median": float(np.median(v))}


def summarize_box_errors(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Means/medians of :func:`pair_errors` records (any subset, e.g. one class)."""
    n = len(records)
    out: dict[str, Any] = {"n": n}
    if n == 0:
        return out
    ab = np.asarray([r["size_abs_error"] for r in records], dtype=np.float64).reshape(n, 3)
    rel = np.asarray([r["size_rel_error"] for r in records], dtype=np.float64).reshape(n, 3)
    out["centroid_error"] = _stats([r["centroid_error"] for r in records])
    out["size_abs_error"] = _stats(ab.mean(1).tolist())
    out["size_abs_error_per_dim"] = np.nanmean(ab, axis=0).tolist()
    out["size_rel_error"] = _stats(np.nanmean(rel, axis=1).tolist())
    out["size_rel_error_per_dim"] = np.nanmean(rel, axis=0).tolist()
    for key in ("heading_error", "heading_error_sym"):
        rad = [r[key + "_rad"] for r in records]
        out[key + "_rad"] = _stats(rad)
        out[key + "_deg"] = _stats(np.degrees(rad).tolist())
    out["corner_error"] = _stats([r["corner_error"] for r in records])
    out["corner_error_flip"] = _stats([r["corner_error_flip"] for r in records])
    out["iou3d"] = _stats([r["iou3d"] for r in records])
    seg = [r["seg_accuracy"] for r in records if r.get("seg_accuracy") is not None]
    if seg:
        out["seg_accuracy"] = _stats(seg)
        out["seg_accuracy"]["n"] = len(seg)
    return out


def aggregate_box_errors(records: Iterable[dict[str, Any]], classes: Sequence[str] = CLASSES) -> dict[str, Any]:
    """Per-class and overall summaries: ``{"per_class": {cls: summary}, "all": summary}``.

    Classes without pairs get ``{"n": 0}``; records of classes outside ``classes`` count
    in ``"all"`` only.
    """
    recs = list(records)
    per = {c: summarize_box_errors([r for r in recs if r.get("class") == c]) for c in classes}
    return {"per_class": per, "all": summarize_box_errors(recs)}
