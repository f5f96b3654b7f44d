"""Frames -> training candidates for the proposal classifier (:mod:`shape_detector.model.classifier`).

Each frame goes through the detector exactly as at inference without 2D boxes: gravity
estimated, built-in proposals (top ``max_objects``), frustums, the network's
class-agnostic first pass. Every candidate then gets the label that the AP evaluation
would give it:

* the labelled object whose visible 2D box it overlaps most (2D IoU >= ``min_iou2d``) is
  tried first: the network's class-given pass with that object's class (the second pass
  the detector runs, :meth:`FrustumPredictor.refine`) must give a box with 3D IoU >=
  ``iou3d`` with it;
* otherwise the first pass's box must overlap some labelled object by 3D IoU >= ``iou3d``;
* otherwise the candidate is background (index ``num_classes``).

Candidates whose match is an object less than ``min_visible`` visible (the evaluation's
"don't care" objects), or that overlap one by 3D IoU >= ``iou3d`` without a match, get
weight 0. Arrays: ``points`` (K,N,7) float16, ``globals`` (K,G) float32 (see
:func:`~shape_detector.model.classifier.candidate_inputs`), ``label`` (K,) int16, ``weight``
(K,) float32, ``frame_index`` (K,) int32, ``iou3d`` (K,) float32 (of the labelled match).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from ..classes import CLASS_TO_ID, NUM_CLASSES
from ..box_iou import box2d_iou, box3d_iou
from ..model.classifier import frame_inputs
from ..types import Frame


def label_candidates(
    first: list[Any], refined: dict[int, tuple[int, Any]], objects: list[Any], up: np.ndarray,
    iou3d: float = 0.25, min_visible: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(label, weight, iou)`` per candidate (see the module docstring).

    ``first``: first-pass predictions (camera-frame ``center``/``size``/``rotation``);
    ``refined``: candidate index -> (index of the object tried, the class-given prediction
    for that object's class); ``objects``: the frame's GT; ``up`` the gravity-up used.
    """
    n = len(first)
    label = np.full(n, NUM_CLASSES, np.int16)
    weight = np.ones(n, np.float32)
    best = np.zeros(n, np.float32)
    for i, p in enumerate(first):
        ious = [_iou(p, g, up) for g in objects]
        if i in refined:
            j, q = refined[i]
            ious[j] = max(ious[j], _iou(q, objects[j], up))
        match = [k for k, v in enumerate(ious) if v >= iou3d and objects[k].class_name in CLASS_TO_ID]
        if not match:
            continue
        k = max(match, key=lambda m: ious[m])
        best[i] = ious[k]
        if float(objects[k].visible_fraction) < min_visible:
            weight[i] = 0.0
            continue
        label[i] = CLASS_TO_ID[objects[k].class_name]
    return label, weight, best


#: ``1 - cos(2 degrees)``: labelling treats a GT box whose vertical is this close to the
#: estimated ``up`` as upright about it (the exact prism IoU instead of the 100x slower grid)
LABEL_VERTICAL_TOL = 1.0 - float(np.cos(np.radians(2.0)))


def _iou(a: Any, b: Any, up: np.ndarray) -> float:
    """3D IoU of two boxes; 0 without computing it when their bounding spheres are apart."""
    reach = 0.5 * (np.linalg.norm(a.size) + np.linalg.norm(b.size))
    if np.linalg.norm(np.asarray(a.center) - np.asarray(b.center)) >= reach:
        return 0.0
    return box3d_iou(a.center, a.size, a.rotation, b.center, b.size, b.rotation, up, vertical_tol=LABEL_VERTICAL_TOL)


def tried_objects(boxes2d: list, objects: list[Any], min_iou2d: float = 0.25) -> dict[int, int]:
    """Candidate index -> the labelled object whose visible 2D box it overlaps most (2D IoU
    >= ``min_iou2d``); candidates without one are absent."""
    out: dict[int, int] = {}
    for i, b in enumerate(boxes2d):
        ious = [box2d_iou(b, g.box2d) if g.class_name in CLASS_TO_ID else 0.0 for g in objects]
        if ious and max(ious) >= min_iou2d:
            out[i] = int(np.argmax(ious))
    return out


def frame_candidates(
    detector: Any, frame: Frame, min_iou2d: float = 0.25, **label_kw: Any
) -> dict[str, np.ndarray] | None:
    """Classifier training rows of one frame (None: no candidate with valid depth)."""
    prep = detector.prepare(frame.rgb, frame.depth, frame.K)
    if not prep.frustums:
        return None
    pred = detector.predictor
    first = pred.predict(prep.frustums, [None] * len(prep.frustums), keep_features=True)  # reused below
    boxes = [b for b, _, _ in prep.boxes]
    objects = list(frame.objects)
    tried = tried_objects(boxes, objects, min_iou2d)
    idx = sorted(tried)
    refined: dict[int, tuple[int, Any]] = {}
    if idx:
        second = pred.predict(
            [prep.frustums[i] for i in idx],
            [CLASS_TO_ID[objects[tried[i]].class_name] for i in idx],
            seg_features=[first[i].seg_features for i in idx],
        )
        refined = {i: (tried[i], q) for i, q in zip(idx, second)}
    label, weight, iou = label_candidates(first, refined, objects, prep.up, **label_kw)
    h, w = prep.depth.shape
    pts, glob = frame_inputs(prep.frustums, first, boxes, [s for _, _, s in prep.boxes], (w, h), prep.floor_height)
    return {"points": pts.astype(np.float16), "globals": glob, "label": label, "weight": weight, "iou3d": iou}


def build_candidates(
    detector: Any, frames: Iterable[Frame], progress: bool = False, **label_kw: Any
) -> dict[str, np.ndarray]:
    """:func:`frame_candidates` of every frame, concatenated (``frame_index`` added)."""
    rows: dict[str, list[np.ndarray]] = {}
    nf = 0
    for fi, frame in enumerate(frames):
        nf += 1
        got = frame_candidates(detector, frame, **label_kw)
        if got is None:
            continue
        got["frame_index"] = np.full(len(got["label"]), fi, np.int32)
        for k, v in got.items():
            rows.setdefault(k, []).append(v)
        if progress and nf % 100 == 0:
            n = sum(len(x) for x in rows["label"])
            print(f"  candidates: {nf} frames, {n} rows", flush=True)
    out = {k: np.concatenate(v, 0) for k, v in rows.items()}
    out["num_frames"] = np.array(nf, np.int64)
    return out
