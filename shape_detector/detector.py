"""``ShapeDetector``: the one public entry point that glues the pipeline together.

rgb + depth + K  ->  gravity ``up``  ->  2D proposals (given or built-in)  ->  frustums
->  batched network forward  ->  :class:`~shape_detector.types.Object3D` list (+ 3D NMS).

All outputs are in the camera optical frame (x right, y down, z forward), metres.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .classes import CLASS_TO_ID
from .frustum import Frustum, extract_frustum, pixel_points, valid_depth
from .geometry import upright_rotation
from .inputs import normalize_inputs
from .floor import snap_to_floor
from .nms import nms_3d
from .free_space import carve_all
from .point_fit import grow_all_to_points
from .primitive_snap import snap_primitives
from .types import Object3D

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "default.pt"
DEFAULT_CLASSIFIER = Path(__file__).resolve().parent / "weights" / "classifier.pt"


@dataclass
class PreparedFrame:
    """A frame after :meth:`ShapeDetector.prepare`: what :meth:`ShapeDetector.finish` needs.

    ``depth`` HxW float32 metres and ``K`` (3,3) as normalised; ``up`` (3,) the gravity-up
    used (given or estimated, camera frame) with its ``up_confidence``; ``floor_height``
    the camera's height above the floor (m, None: not measured); ``boxes`` the
    ``(box2d, class_name or None, proposal score)`` of the frustums kept (those with valid
    depth), ``frustums`` their points; ``given_boxes``: the boxes came from the caller;
    ``timing`` the stages' milliseconds so far; ``first`` the network's first pass (set by
    :meth:`ShapeDetector.first_pass`, else None).
    """

    depth: np.ndarray
    K: np.ndarray
    up: np.ndarray
    up_confidence: float
    floor_height: float | None
    boxes: list[tuple[tuple[float, float, float, float], str | None, float]]
    frustums: list[Frustum]
    given_boxes: bool
    timing: dict[str, float] = field(default_factory=dict)
    #: the network's first-pass predictions once :meth:`ShapeDetector.first_pass` ran
    first: list | None = None


def _parse_box(box: Any) -> tuple[tuple[float, float, float, float], str | None]:
    """(x1, y1, x2, y2[, class_name]) or an object with ``box2d``/``class_name`` attributes."""
    if hasattr(box, "box2d"):
        coords, name = box.box2d, getattr(box, "class_name", None)
    else:
        seq = list(box)
        if len(seq) < 4:
            raise ValueError(f"a 2D box needs (x1, y1, x2, y2[, class_name]), got {box!r}")
        coords, name = seq[:4], (seq[4] if len(seq) > 4 else None)
    x1, y1, x2, y2 = (float(v) for v in coords)
    if not np.all(np.isfinite([x1, y1, x2, y2])):
        raise ValueError(f"2D box has non-finite coordinates: {box!r}")
    return (x1, y1, x2, y2), (name if isinstance(name, str) and name in CLASS_TO_ID else None)


#: timing keys (ms) of the stages before the network, the first pass, and what follows it
_BEFORE_KEYS = ("inputs_ms", "proposals_ms", "frustums_ms")
_AFTER_KEYS = ("classifier_ms", "refine_ms", "post_ms")


def first_pass_early(timing: dict[str, float] | None, margin: float = 0.1) -> bool:
    """Whether a two-stage pipeline (one thread :meth:`ShapeDetector.prepare`, the other
    :meth:`ShapeDetector.finish`) is faster with the network's first pass moved into the
    first stage, judged from a frame's ``last_timing`` (ms): ``a`` before the network,
    ``n`` the first pass, ``b`` after it; the pipeline runs at the pace of its slower
    stage, ``max(a, n + b)`` or ``max(a + n, b)``; the first pass moves only when that
    shortens the slower stage by more than ``margin`` (10%), so near balance the split does
    not flip from frame to frame. False without timings."""
    if not timing or "network_ms" not in timing:
        return False
    a = sum(float(timing.get(k, 0.0)) for k in _BEFORE_KEYS)
    n = float(timing["network_ms"])
    b = sum(float(timing.get(k, 0.0)) for k in _AFTER_KEYS)
    return max(a + n, b) < (1.0 - margin) * max(a, n + b)


def classifier_option(text: str | None) -> str | bool | None:
    """A front end's classifier setting (CLI option, node parameter) as the ``classifier``
    argument of :class:`ShapeDetector` and of detector factories: None or ``""`` = not
    given (None: leave the argument out, the packaged classifier), ``"none"`` = False
    (off), anything else = a path."""
    if not text:
        return None
    return False if text == "none" else text


def _load_classifier(spec: str | Path | bool, precision: str = "fp32", trace: bool = True):
    """The proposal classifier for ``ShapeDetector(classifier=spec)`` (a
    :class:`~shape_detector.model.classifier.ClassifierPredictor` with that ``precision`` and
    ``trace``), or None."""
    if spec is False or spec is None:
        return None
    path = DEFAULT_CLASSIFIER if spec is True else Path(spec)
    if not path.is_file():
        if spec is True:
            warnings.warn(f"no packaged proposal classifier at {path}; the network's class head decides", stacklevel=3)
            return None
        raise FileNotFoundError(f"proposal classifier {path} not found")
    from .model.classifier import ClassifierPredictor, load_classifier

    return ClassifierPredictor(load_classifier(path)[0], precision=precision, trace=trace)


def reclassify(classifier: Any, frame: PreparedFrame, preds: list) -> list:
    """First-pass predictions of a frame's built-in proposals with the class, class
    probabilities and score the proposal classifier gives them (class = the most probable
    of the ten, score = its probability); frustums without valid points keep score 0."""
    from dataclasses import replace

    from .classes import CLASSES
    from .model.classifier import frame_inputs

    h, w = frame.depth.shape
    pts, glob = frame_inputs(
        frame.frustums, preds, [b for b, _, _ in frame.boxes], [s for _, _, s in frame.boxes], (w, h),
        frame.floor_height, classifier.config,
    )
    probs = classifier.probabilities(pts, glob)
    out = []
    for p, pr in zip(preds, probs):
        k = int(np.argmax(pr[: len(CLASSES)]))
        score = float(pr[k]) if p.num_points_valid > 0 else 0.0
        out.append(replace(p, class_name=CLASSES[k], class_probs=pr, score=score))
    return out


class ShapeDetector:
    """Detect furniture with amodal 3D boxes and cuboid primitives in one RGB-D frame.

    ``weights``: a checkpoint written by ``shape-detector train`` (default: the packaged
    weights). ``device``: 'cpu', 'cuda' or 'auto'. ``proposals``: 'geometric' (built-in,
    class-agnostic 3D-geometry proposals) or 'none' (then ``detect`` needs ``boxes2d``).
    ``score_threshold`` drops low-confidence objects; ``max_objects`` caps frustums per
    frame (highest-score proposals first); ``nms_iou`` is the 3D IoU above which the
    lower-scoring of two detections is suppressed, or with ``nms_decay`` > 0 kept at that
    fraction of its score (Soft-NMS; see :func:`~shape_detector.nms.nms_3d`).
    ``num_threads``: torch CPU threads for the network (default 1: a frame's batch is small,
    and on a loaded 2-core machine torch's intra-op threads wait on each other; None keeps
    torch's setting).
    The setting is process-wide (torch).
    ``workers``: split a frame's frustums over this many threads, each running single-threaded
    ops (data parallelism without OpenMP's barrier waits; faster on an idle multi-core CPU,
    no slower with another core busy). 1 = serial. ``floor_snap``: boxes whose bottom lies
    within this many metres of the floor measured in the depth get their bottom put on it (furniture
    stands on the floor; the top is kept), 0 = off; see :mod:`shape_detector.floor`.
    ``point_fit``: grow each box to cover its segmented points between this quantile and
    its complement along each box axis (0 = off; see :mod:`shape_detector.point_fit`).
    ``free_space``: after the floor snap, move each box's side faces (and the top face of
    flat-topped classes) inwards out of space the camera sees through, never past measured
    points or the object's own; chairs are left alone (see :mod:`shape_detector.free_space`).
    ``fit_confidence``: point fit and free-space carving take an object's own points to be
    those whose foreground probability exceeds this (the reported ``seg_labels`` stay the
    network's decision, > 0.5; 0.5 uses them). What leaks into a mask (a chair at a table,
    clutter on its top) is segmented less surely than the object, so the boxes no longer grow
    over it; the default was chosen on the validation frames
    (docs/experiments/code-comment-numbers.md).
    ``precision``: the network's arithmetic, ``"fp32"``, ``"bf16"`` (faster on CPUs with
    AMX / AVX512-BF16 for several frustums) or ``"auto"`` (bf16 for batches of 4 or more
    frustums on a CPU with AMX); see :class:`~shape_detector.model.predictor.FrustumPredictor`.
    ``mirror_tta``: also run each frustum mirrored and merge the two predictions
    (:func:`~shape_detector.model.predictor.merge_mirrored`) -- ``"given"`` (default: only
    for given ``boxes2d``, a few per frame), ``"always"`` or ``"never"``. It doubles the
    network work: worth it for a few given boxes, not for the 10-25 built-in
    proposals.
    ``snap_primitives``: turn nearly box-aligned primitives to the box axes and clip them to
    the box (see :mod:`shape_detector.primitive_snap`).
    ``classifier``: the proposal classifier (:mod:`shape_detector.model.classifier`) that
    re-decides the class and score of built-in proposals after the first pass, from the
    frustum, its height above the measured floor, the 2D box and the first pass's output:
    True = the packaged ``weights/classifier.pt`` (skipped with a warning if missing),
    False = off (the network's class head decides), or a path.
    ``trace``: run the network through frozen TorchScript graphs (CPU; same outputs, less
    per-op overhead, and the GIL is free while they run, so the node's two pipeline threads
    and ``workers`` really overlap; see :mod:`shape_detector.model.traced`); False = eager.
    ``refine``: a class-given second pass for class-agnostic frustums (built-in proposals,
    or given boxes without a class) whose score (the classifier's, else the first pass's)
    reaches ``refine_min_score``: they run again with their decided class as the
    one-hot, which gives the box that class's size cluster and prior (see
    :meth:`FrustumPredictor.refine <shape_detector.model.predictor.FrustumPredictor.refine>`).
    The classifier and the second pass each help built-in proposals, and most together
    (the defaults).
    """

    def __init__(
        self,
        weights: str | Path | None = None,
        device: str = "cpu",
        score_threshold: float = 0.3,
        max_objects: int = 25,
        proposals: str = "geometric",
        nms_iou: float = 0.25,
        nms_decay: float = 0.1,
        num_threads: int | None = 1,
        workers: int = 2,
        floor_snap: float = 0.25,
        point_fit: float = 0.15,
        free_space: bool = True,
        fit_confidence: float = 0.8,
        precision: str = "fp32",
        mirror_tta: str = "given",
        snap_primitives: bool = True,
        refine: bool = True,
        refine_min_score: float = 0.3,
        classifier: str | Path | bool = True,
        trace: bool = True,
    ) -> None:
        from .model.predictor import FrustumPredictor

        path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        if not path.is_file():
            raise FileNotFoundError(
                f"weights file {path} not found (train some with `shape-detector train`, "
                "or pass weights=...)"
            )
        self.weights = path
        self.predictor = FrustumPredictor(
            path, device=device, num_threads=num_threads, workers=workers, precision=precision, trace=trace
        )
        self.num_points = int(self.predictor.config.num_points)
        self.score_threshold = float(score_threshold)
        self.max_objects = int(max_objects)
        self.nms_iou = float(nms_iou)
        self.nms_decay = float(nms_decay)
        self.proposal_source = proposals
        self._proposer = None
        if proposals not in ("geometric", "none"):
            raise ValueError(f"proposals must be 'geometric' or 'none', got {proposals!r}")
        self.last_timing: dict[str, float] = {}
        self.last_up: np.ndarray | None = None
        self.last_up_confidence: float = 0.0
        self.last_floor_height: float | None = None
        self.floor_snap = float(floor_snap)
        self.point_fit = float(point_fit)
        if not 0.0 <= self.point_fit < 0.5:
            raise ValueError(f"point_fit is a quantile in [0, 0.5), got {point_fit}")
        self.free_space = bool(free_space)
        self.fit_confidence = float(fit_confidence)
        if not 0.5 <= self.fit_confidence < 1.0:
            raise ValueError(
                f"fit_confidence is a probability in [0.5, 1) (0.5: the mask itself), got {fit_confidence}"
            )
        if mirror_tta not in ("given", "always", "never"):
            raise ValueError(f"mirror_tta must be 'given', 'always' or 'never', got {mirror_tta!r}")
        self.mirror_tta = mirror_tta
        self.snap_primitives = bool(snap_primitives)
        self.refine = bool(refine)
        self.refine_min_score = float(refine_min_score)
        self.classifier = _load_classifier(classifier, precision, trace)

    # -- stages -----------------------------------------------------------------------
    def _get_proposer(self):
        if self._proposer is None:
            from .proposals.geometric import GeometricProposer

            self._proposer = GeometricProposer()
        return self._proposer

    def _gravity_and_proposals(
        self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, up: np.ndarray | None, need_boxes: bool
    ) -> tuple[np.ndarray, float, float | None, list[tuple[tuple[float, float, float, float], str | None, float]]]:
        """``up`` (given or estimated), its confidence, the camera's height above the floor
        (None: no floor seen, or not needed) and built-in proposals if needed."""
        if need_boxes:
            if self.proposal_source == "none":
                raise ValueError("detect() needs boxes2d when the detector was built with proposals='none'")
            gravity, props = self._get_proposer()(depth, K, up=up, rgb=rgb)
            boxes = [(tuple(p.box2d), p.class_name, float(p.score)) for p in props]
            if up is not None:
                return np.asarray(up, dtype=np.float64), 1.0, gravity.floor_height, boxes
            return np.asarray(gravity.up, dtype=np.float64), float(gravity.confidence), gravity.floor_height, boxes
        if up is not None and self.floor_snap <= 0.0:
            return np.asarray(up, dtype=np.float64), 1.0, None, []
        from .gravity import auto_stride, estimate_floor_along, estimate_up, make_grid

        if up is not None:  # measure the floor along the given up
            grid = make_grid(depth, K, stride=auto_stride(np.shape(depth)))
            gravity = estimate_floor_along(grid, np.asarray(K, np.float64), np.asarray(up, np.float64))
            return np.asarray(up, dtype=np.float64), 1.0, gravity.floor_height, []
        gravity = estimate_up(depth, K)
        return np.asarray(gravity.up, dtype=np.float64), float(gravity.confidence), gravity.floor_height, []

    # -- public -----------------------------------------------------------------------
    def detect(
        self,
        rgb: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        boxes2d: Sequence[Any] | None = None,
        up: np.ndarray | None = None,
        depth_scale: float | None = None,
    ) -> list[Object3D]:
        """Objects in one frame, camera optical frame, metres, sorted by score.

        ``rgb`` HxWx3 uint8 RGB; ``depth`` HxW float32 metres (0/NaN invalid) or uint16
        millimetres; ``K`` 3x3 intrinsics of both; ``boxes2d`` optional list of
        ``(x1, y1, x2, y2, class_name)`` pixel boxes used instead of the built-in proposals
        (class_name may be None or omitted: then the network classifies); ``up`` optional
        gravity-up unit vector in the camera frame (estimated from the depth when None).
        Same as ``finish(prepare(...))``.
        """
        return self.finish(self.prepare(rgb, depth, K, boxes2d=boxes2d, up=up, depth_scale=depth_scale))

    def prepare(
        self,
        rgb: np.ndarray,
        depth: np.ndarray,
        K: np.ndarray,
        boxes2d: Sequence[Any] | None = None,
        up: np.ndarray | None = None,
        depth_scale: float | None = None,
    ) -> PreparedFrame:
        """The stages before the network (inputs checked, gravity, proposals, frustums);
        arguments as :meth:`detect`. Touches no state :meth:`finish` uses, so one thread may
        prepare frame N+1 while another finishes frame N (the node's two-stage pipeline)."""
        t0 = time.perf_counter()
        rgb, depth, K = normalize_inputs(rgb, depth, K, depth_scale)
        t1 = time.perf_counter()
        if up is not None:
            up = np.asarray(up, dtype=np.float64).reshape(3)
            if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-6:
                raise ValueError(f"up must be a finite non-zero 3-vector, got {up}")
            up = up / np.linalg.norm(up)
        up_used, up_conf, floor_height, built_in = self._gravity_and_proposals(rgb, depth, K, up, boxes2d is None)
        if boxes2d is not None:
            parsed = [(*_parse_box(b), 1.0) for b in boxes2d]
        else:
            parsed = sorted(built_in, key=lambda p: -p[2])
        parsed = parsed[: self.max_objects]
        t2 = time.perf_counter()
        valid = valid_depth(depth) if parsed else None
        R_cu = upright_rotation(up_used)
        frustums = [
            extract_frustum(rgb, depth, K, box, self.num_points, up=up_used, valid=valid, R_cu=R_cu)
            for box, _, _ in parsed
        ]
        keep = [i for i, f in enumerate(frustums) if f.valid > 0]
        t3 = time.perf_counter()
        return PreparedFrame(
            depth=depth,
            K=K,
            up=up_used,
            up_confidence=up_conf,
            floor_height=floor_height,
            boxes=[parsed[i] for i in keep],
            frustums=[frustums[i] for i in keep],
            given_boxes=boxes2d is not None,
            timing={"inputs_ms": 1e3 * (t1 - t0), "proposals_ms": 1e3 * (t2 - t1), "frustums_ms": 1e3 * (t3 - t2)},
        )

    def _mirror(self, frame: PreparedFrame) -> bool:
        return self.mirror_tta == "always" or (self.mirror_tta == "given" and frame.given_boxes)

    def first_pass(self, frame: PreparedFrame) -> PreparedFrame:
        """The network's first pass over a prepared frame's frustums (``frame.first``; its
        time in ``frame.timing["network_ms"]``), which :meth:`finish` otherwise runs itself.
        The node's first stage calls it after :meth:`prepare` when the two stages are
        lopsided (``pipeline_split="network"``). Reads only the weights: safe beside a
        :meth:`finish` of another frame. Returns ``frame``."""
        t0 = time.perf_counter()
        class_ids = [CLASS_TO_ID[c] if c is not None else None for _, c, _ in frame.boxes]
        # the class-given second pass reuses the first pass's segmentation features
        keep = self.refine and any(c is None for c in class_ids)
        frame.first = self.predictor.predict(frame.frustums, class_ids, mirror=self._mirror(frame), keep_features=keep)
        frame.timing["network_ms"] = 1e3 * (time.perf_counter() - t0)
        return frame

    def finish(self, frame: PreparedFrame) -> list[Object3D]:
        """Network (first pass; for built-in proposals the proposal classifier and the
        class-given second pass) and post-processing (point fit, floor contact, 3D NMS for
        built-in proposals, primitive snapping) of a frame from :meth:`prepare`: its
        objects, sorted by score. Sets ``last_up``, ``last_up_confidence``,
        ``last_floor_height`` and ``last_timing`` (milliseconds per stage: ``network_ms``
        is the first pass, ``classifier_ms`` and ``refine_ms`` the other two)."""
        if frame.first is None:
            self.first_pass(frame)
        t_net = time.perf_counter()
        boxes = frame.boxes
        mirror = self._mirror(frame)
        preds = list(frame.first or [])
        agnostic = [i for i, (_, c, _) in enumerate(boxes) if c is None]
        if self.classifier is not None and not frame.given_boxes and agnostic:
            preds = reclassify(self.classifier, frame, preds)
        t_cls = time.perf_counter()
        if self.refine and agnostic:
            second = self.predictor.refine(
                [frame.frustums[i] for i in agnostic], [preds[i] for i in agnostic], mirror, self.refine_min_score
            )
            for i, p in zip(agnostic, second):
                preds[i] = p
        t4 = time.perf_counter()
        objects: list[Object3D] = []
        for (box, _, _), fr, pred in zip(boxes, frame.frustums, preds):
            if pred.class_name not in CLASS_TO_ID or pred.score < self.score_threshold:
                continue
            objects.append(
                Object3D(
                    class_name=pred.class_name,
                    score=float(pred.score),
                    center=pred.center,
                    size=pred.size,
                    rotation=pred.rotation,
                    box2d=box,
                    primitives=list(pred.primitives),
                    pixel_index=fr.pixel_index,
                    seg_labels=np.asarray(pred.seg_prob) > 0.5,
                    seg_prob=np.asarray(pred.seg_prob),
                    class_scores=np.asarray(pred.class_probs[: len(CLASS_TO_ID)], dtype=np.float64),
                )
            )
        points_cam = functools.partial(pixel_points, frame.depth, frame.K)
        objects = grow_all_to_points(objects, points_cam, self.point_fit, self.fit_confidence)
        objects = snap_to_floor(objects, frame.up, frame.floor_height, self.floor_snap)
        if self.free_space:  # after the floor snap: measured points near the box bottom are floor
            objects = carve_all(objects, frame.depth, frame.K, points_cam, min_prob=self.fit_confidence)
        if not frame.given_boxes:  # built-in proposals overlap by design; given boxes are one per object
            objects = nms_3d(objects, self.nms_iou, decay=self.nms_decay, min_score=self.score_threshold)
        if self.snap_primitives:
            objects = snap_primitives(objects)
        objects.sort(key=lambda o: -o.score)
        t5 = time.perf_counter()
        self.last_up, self.last_up_confidence = frame.up, frame.up_confidence
        self.last_floor_height = frame.floor_height
        timing = dict(frame.timing)
        timing.update(classifier_ms=1e3 * (t_cls - t_net), refine_ms=1e3 * (t4 - t_cls), post_ms=1e3 * (t5 - t4))
        timing["total_ms"] = sum(timing.values())
        timing["num_frustums"] = float(len(boxes))
        self.last_timing = timing
        return objects

    def warm_up(self) -> None:
        """Run the pipeline once on a tiny synthetic frame (floor + a box, 160x120), so the
        first real frame does not pay torch's and OpenCV's first-call costs, nor the
        tracing of the network's graphs and its kernels for each batch size up to
        ``max_objects`` (:meth:`FrustumPredictor.warm_up`)."""
        self.predictor.warm_up(max_batch=self.max_objects)
        if self.classifier is not None and hasattr(self.classifier, "warm_up"):
            self.classifier.warm_up(max_batch=self.max_objects)
        h, w = 120, 160
        K = np.array([[130.0, 0.0, 79.5], [0.0, 130.0, 59.5], [0.0, 0.0, 1.0]])
        v = np.arange(h, dtype=np.float64)[:, None] - K[1, 2]
        floor = 1.2 * K[1, 1] / np.where(v > 0, v, np.inf)  # floor 1.2 m below a level camera
        depth = np.where((floor > 0) & (floor < 4.0), floor, 4.0).repeat(w, axis=1).astype(np.float32)
        depth[50:100, 60:100] = 2.0
        rgb = np.full((h, w, 3), 128, np.uint8)
        self.detect(rgb, depth, K, boxes2d=[(60, 50, 100, 100, "chair")])
        if self.proposal_source != "none":
            self.detect(rgb, depth, K)

    def detect_frame(self, frame: Any, boxes2d: Sequence[Any] | None = None, use_gt_up: bool = False) -> list[Object3D]:
        """:meth:`detect` on a :class:`~shape_detector.types.Frame` (``use_gt_up`` passes ``frame.up``)."""
        return self.detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes2d, up=frame.up if use_gt_up else None)
