"""``ShapeDetector``: the one public entry point that glues the pipeline together.

rgb + depth + K  ->  gravity ``up``  ->  2D proposals (given or built-in)  ->  frustums
->  batched network forward  ->  :class:`~shape_detector.types.Object3D` list (+ 3D NMS).

All outputs are in the camera optical frame (x right, y down, z forward), metres.
"""

from __future__ import annotations

import inspect
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .classes import CLASS_TO_ID
from .detector_config import DetectorConfig, make_config, preset, resolved_workers
from .frustum import Frustum, extract_frustums, valid_depth
from .geometry import upright_rotation
from .inputs import normalize_inputs
from .model.prediction import refined_score
from .postprocess import Hook, PostContext, build_pipeline
from .proposal_source import make_proposer
from .types import Object3D

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "default.pt"
DEFAULT_CLASSIFIER = Path(__file__).resolve().parent / "weights" / "classifier.pt"
#: the packaged classifier trained on the hybrid proposer's candidates
HYBRID_CLASSIFIER = DEFAULT_CLASSIFIER.with_name("classifier_hybrid.pt")


def packaged_classifier(proposal_source: str, folder: str | Path | None = None) -> Path:
    """The proposal classifier for a proposer: the one trained on its candidates (``hybrid``:
    :data:`HYBRID_CLASSIFIER`'s file where there is one), else :data:`DEFAULT_CLASSIFIER`'s
    (trained on the geometric proposer's). ``folder``: look there instead of the packaged
    weights (the folder of other weights); the returned file may be missing."""
    hybrid, general = HYBRID_CLASSIFIER, DEFAULT_CLASSIFIER
    if folder is not None:
        hybrid, general = Path(folder) / hybrid.name, Path(folder) / general.name
    return hybrid if proposal_source == "hybrid" and hybrid.is_file() else general


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


def first_pass_share(timing: dict[str, float] | None) -> float:
    """The share of a frame's frustums whose first pass a two-stage pipeline (one thread
    :meth:`ShapeDetector.prepare`, the other :meth:`ShapeDetector.finish`) runs in its
    first stage, so both take as long, judged from the previous frame's ``last_timing``
    (ms): ``a`` before the network, ``n`` the whole first pass, ``b`` after it; the stages
    take ``a + s n`` and ``(1 - s) n + b``. 0 without timings."""
    if not timing or "network_ms" not in timing:
        return 0.0
    a = sum(float(timing.get(k, 0.0)) for k in _BEFORE_KEYS)
    n = float(timing["network_ms"])
    b = sum(float(timing.get(k, 0.0)) for k in _AFTER_KEYS)
    if n <= 0.0:
        return 0.0
    return float(np.clip((n + b - a) / (2.0 * n), 0.0, 1.0))


def classifier_option(text: str | None) -> str | bool | None:
    """A front end's classifier setting (CLI option, node parameter) as the ``classifier``
    argument of :class:`ShapeDetector` and of detector factories: None or ``""`` = not
    given (None: leave the argument out, the packaged classifier), ``"none"`` = False
    (off), anything else = a path."""
    if not text:
        return None
    return False if text == "none" else text


def _load_classifier(spec: str | Path | bool, cfg: DetectorConfig):
    """The proposal classifier for ``spec`` (True: the packaged one; False: none; a path)
    as a :class:`~shape_detector.model.classifier.ClassifierPredictor` with the config's
    precision, tracing and backend, or None."""
    if spec is False or spec is None:
        return None
    path = packaged_classifier(cfg.proposal_source) if spec is True else Path(spec)
    if not path.is_file():
        if spec is True:
            warnings.warn(f"no packaged proposal classifier at {path}; the network's class head decides", stacklevel=3)
            return None
        raise FileNotFoundError(f"proposal classifier {path} not found")
    from .model.classifier_runtime import ClassifierPredictor

    # from the file: under onnxruntime its cached graph serves without importing torch
    return ClassifierPredictor.from_file(path, precision=cfg.precision, trace=cfg.trace, backend=cfg.backend)


def _classifier_spec(text: str) -> str | bool:
    """The config's classifier text as :func:`_load_classifier`'s spec."""
    option = classifier_option(text)
    return True if option is None else option


def _backend_kw(cls: Any, cfg: DetectorConfig) -> dict[str, Any]:
    """``backend=`` for runtimes that offer a choice (custom predictors may not)."""
    return {"backend": cfg.backend} if "backend" in inspect.signature(cls).parameters else {}


def _preset(name: str) -> DetectorConfig:
    return preset(name)


def _legacy(overrides: dict[str, Any]) -> dict[str, Any]:
    """Keyword arguments in the forms earlier releases took, as config values: paths for
    ``weights``/``classifier``, booleans for ``classifier``, ``proposals="none"``,
    ``num_threads=None``."""
    out = dict(overrides)
    if "proposals" in out:
        value = out.pop("proposals")
        out["proposal_source"] = "external" if value == "none" else value
    if "weights" in out:
        out["weights"] = "" if out["weights"] is None else str(out["weights"])
    if "classifier" in out:
        c = out["classifier"]
        out["classifier"] = "" if c is True or c is None else "none" if c is False else str(c)
    if out.get("num_threads", 0) is None:
        out["num_threads"] = 0
    return out


def _to_object(box: tuple[float, float, float, float], fr: Frustum, pred: Any) -> Object3D:
    """A network prediction for one frustum as an :class:`Object3D` (camera frame)."""
    return Object3D(
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


def reclassify(classifier: Any, frame: PreparedFrame, preds: list, which: Sequence[int] | None = None) -> list:
    """First-pass predictions of a frame's frustums with the class, class probabilities and
    score the proposal classifier gives those listed in ``which`` (indices; None = all):
    class = the most probable of the ten, score = its probability; frustums without valid
    points get score 0. The others are returned unchanged."""
    from dataclasses import replace

    from .classes import CLASSES
    from .model.classifier_inputs import frame_inputs

    idx = list(range(len(preds))) if which is None else list(which)
    if not idx:
        return list(preds)
    h, w = frame.depth.shape
    pts, glob = frame_inputs(
        [frame.frustums[i] for i in idx], [preds[i] for i in idx], [frame.boxes[i][0] for i in idx],
        [frame.boxes[i][2] for i in idx], (w, h), frame.floor_height, classifier.config,
    )
    probs = classifier.probabilities(pts, glob)
    out = list(preds)
    for i, pr in zip(idx, probs):
        k = int(np.argmax(pr[: len(CLASSES)]))
        score = float(pr[k]) if preds[i].num_points_valid > 0 else 0.0
        out[i] = replace(preds[i], class_name=CLASSES[k], class_probs=pr, score=score)
    return out


class ShapeDetector:
    """Detect furniture with amodal 3D boxes and cuboid primitives in one RGB-D frame.

    Settings come from one :class:`~shape_detector.detector_config.DetectorConfig`:
    ``ShapeDetector()`` runs the ``realtime`` preset (what the node runs),
    ``ShapeDetector(preset="accurate")`` the offline one, and keyword arguments change single
    settings (``ShapeDetector(score_threshold=0.5)``); ``docs/parameters.md`` lists them all.
    Invalid values raise ValueError with the reason. :meth:`configure` changes settings of a
    built detector that need no reload (thresholds, post-processing).
    """

    def __init__(self, config: DetectorConfig | None = None, *, preset: str | None = None, **overrides: Any) -> None:
        if config is not None and preset is not None:
            raise ValueError("pass a config or a preset, not both")
        base = config if config is not None else _preset(preset or "realtime")
        self.config = make_config(base, **_legacy(overrides))
        cfg = self.config
        from .model.predictor import FrustumPredictor

        path = Path(cfg.weights) if cfg.weights else DEFAULT_WEIGHTS
        if not path.is_file():
            raise FileNotFoundError(
                f"weights file {path} not found (train some with `shape-detector train`, or pass weights=...)"
            )
        self.weights = path
        self.predictor = FrustumPredictor(path, device=cfg.device, num_threads=cfg.num_threads or None,
                                          workers=resolved_workers(cfg.workers), precision=cfg.precision, trace=cfg.trace,
                                          points=cfg.frustum_points, **_backend_kw(FrustumPredictor, cfg))
        self.num_points = self.predictor.num_points
        self._proposer = make_proposer(cfg)
        self.postprocess = build_pipeline(cfg)
        self.classifier = _load_classifier(_classifier_spec(cfg.classifier), cfg)
        self.last_timing: dict[str, float] = {}
        self.last_up: np.ndarray | None = None
        self.last_up_confidence: float = 0.0
        self.last_floor_height: float | None = None

    def __getattr__(self, name: str) -> Any:
        # settings read as attributes (det.score_threshold): the config is their one home
        config = self.__dict__.get("config")
        if config is not None and name in config.__dataclass_fields__:
            return getattr(config, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def configure(self, **changes: Any) -> None:
        """Change settings that need no reload (see ``node: dynamic`` in docs/parameters.md);
        ValueError (nothing changed) names every invalid value."""
        from .detector_config import detector_specs

        fixed = [k for k in changes if k in detector_specs() and detector_specs()[k].node != "dynamic"]
        if fixed:
            raise ValueError(f"{', '.join(fixed)} cannot change on a built detector; build a new one")
        self.config = make_config(self.config, **changes)
        self.postprocess = build_pipeline(self.config)

    # -- stages -----------------------------------------------------------------------
    def _gravity_and_proposals(
        self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, up: np.ndarray | None, need_boxes: bool
    ) -> tuple[np.ndarray, float, float | None, list[tuple[tuple[float, float, float, float], str | None, float]]]:
        """``up`` (given or estimated), its confidence, the camera's height above the floor
        (None: no floor seen, or not needed) and built-in proposals if needed."""
        if need_boxes:
            if self._proposer is None:
                raise ValueError("detect() needs boxes2d when the detector was built with proposal_source 'external'")
            gravity, props = self._proposer(depth, K, up=up, rgb=rgb)
            boxes = [(tuple(p.box2d), p.class_name, float(p.score)) for p in props]
            if up is not None:
                return np.asarray(up, dtype=np.float64), 1.0, gravity.floor_height, boxes
            return np.asarray(gravity.up, dtype=np.float64), float(gravity.confidence), gravity.floor_height, boxes
        if up is not None and self.floor_snap <= 0.0:
            return np.asarray(up, dtype=np.float64), 1.0, None, []
        from .gravity import gravity_with_floor

        gravity = gravity_with_floor(depth, K, up)  # a given up: the floor measured along it
        if up is not None:
            return np.asarray(up, dtype=np.float64), 1.0, gravity.floor_height, []
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
        if boxes2d is not None:  # every given box: the caller chose them (max_objects caps the built-in ones)
            parsed = [(*_parse_box(b), 1.0) for b in boxes2d]
        else:
            parsed = sorted(built_in, key=lambda p: -p[2])[: self.config.max_objects]
        t2 = time.perf_counter()
        frustums = (extract_frustums(rgb, depth, K, [box for box, _, _ in parsed], self.num_points,
                                     valid=valid_depth(depth), R_cu=upright_rotation(up_used)) if parsed else [])
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
        mode = self.config.mirror_tta
        return mode == "always" or (mode == "given" and frame.given_boxes)

    def first_pass(self, frame: PreparedFrame, share: float = 1.0) -> PreparedFrame:
        """The network's first pass over a prepared frame's frustums (``frame.first``; its
        time in ``frame.timing["network_ms"]``), which :meth:`finish` otherwise runs itself.
        ``share`` (0..1): run it on only that share of the frustums (the first ones, rounded);
        :meth:`finish` runs the rest. The node's first stage calls it after :meth:`prepare`
        with the share that balances its two threads (:func:`first_pass_share`). Reads only
        the weights: safe beside a :meth:`finish` of another frame. Returns ``frame``."""
        done = len(frame.first or [])
        stop = len(frame.frustums) if share >= 1.0 else done + int(round(share * (len(frame.frustums) - done)))
        if stop <= done:
            return frame
        t0 = time.perf_counter()
        class_ids = [CLASS_TO_ID[c] if c is not None else None for _, c, _ in frame.boxes]
        # the class-given second pass reuses the first pass's segmentation features
        keep = self.config.refine and any(c is None for c in class_ids)
        preds = self.predictor.predict(frame.frustums[done:stop], class_ids[done:stop], mirror=self._mirror(frame),
                                       keep_features=keep, shapes=not self._second_pass_replaces_shapes(class_ids))
        frame.first = list(frame.first or []) + list(preds)
        frame.timing["network_ms"] = frame.timing.get("network_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        return frame

    def _second_pass_replaces_shapes(self, class_ids: Sequence[int | None]) -> bool:
        """Whether no first-pass primitive can reach the output: every frustum is
        class-agnostic, so it either gets the class-given second pass (score >=
        ``refine_min_score``; that pass's primitives replace the first's), or scores below
        ``refine_min_score`` <= ``score_threshold``, or is a duplicate suppressed before the
        second pass (``refine_nms``) whose decayed score (<= ``nms_decay``) stays below
        ``score_threshold``; neither is published. The first pass then skips the shape branch."""
        cfg = self.config
        return (bool(class_ids) and cfg.refine and all(c is None for c in class_ids)
                and cfg.refine_min_score <= cfg.score_threshold
                and (not cfg.refine_nms or cfg.nms_decay < cfg.score_threshold)
                and bool(getattr(self.predictor, "has_class_head", False)))

    def finish(self, frame: PreparedFrame, hook: Hook | None = None) -> list[Object3D]:
        """Network (first pass; for built-in proposals the proposal classifier and the
        class-given second pass) and the post-processing pipeline (:attr:`postprocess`;
        ``hook`` sees the objects before each of its steps) of a frame from :meth:`prepare`:
        its objects, sorted by score. Sets ``last_up``, ``last_up_confidence``,
        ``last_floor_height`` and ``last_timing`` (milliseconds per stage: ``network_ms``
        is the first pass, ``classifier_ms`` and ``refine_ms`` the other two)."""
        self.first_pass(frame)  # the frustums the first stage left (all when it ran none)
        cfg = self.config
        t_net = time.perf_counter()
        preds = list(frame.first or [])
        agnostic = [i for i, (_, c, _) in enumerate(frame.boxes) if c is None]
        if self.classifier is not None and agnostic:
            # given boxes without a class are classified as the built-in proposals are: the
            # classifier sees context the frustum network's class head does not
            preds = reclassify(self.classifier, frame, preds, agnostic)
        t_cls = time.perf_counter()
        if cfg.refine and agnostic:
            todo = self._suppress_duplicates(frame, preds, agnostic) if cfg.refine_nms else agnostic
            second = self.predictor.refine([frame.frustums[i] for i in todo], [preds[i] for i in todo],
                                           self._mirror(frame), cfg.refine_min_score)
            for i, p in zip(todo, second):
                preds[i] = p
        t4 = time.perf_counter()
        objects = [
            _to_object(box, fr, pred)
            for (box, _, _), fr, pred in zip(frame.boxes, frame.frustums, preds)
            if pred.class_name in CLASS_TO_ID and pred.score >= cfg.score_threshold
        ]
        ctx = PostContext(frame.depth, frame.K, frame.up, frame.floor_height, frame.given_boxes)
        objects = self.postprocess.run(objects, ctx, hook)
        t5 = time.perf_counter()
        self.last_up, self.last_up_confidence = frame.up, frame.up_confidence
        self.last_floor_height = frame.floor_height
        timing = dict(frame.timing)
        timing.update(classifier_ms=1e3 * (t_cls - t_net), refine_ms=1e3 * (t4 - t_cls), post_ms=1e3 * (t5 - t4))
        timing["total_ms"] = sum(timing.values())
        timing["num_frustums"] = float(len(frame.boxes))
        self.last_timing = timing
        return objects

    def _suppress_duplicates(self, frame: PreparedFrame, preds: list, agnostic: list[int]) -> list[int]:
        """The class-agnostic frustums worth a second pass: among those scored at least
        ``refine_min_score``, the survivors of a 3D NMS over their first-pass boxes (the
        final NMS would drop the others' refined boxes anyway); the rest of ``agnostic``
        as it is. The suppressed ones keep their first pass with the score times
        ``nms_decay`` (in place in ``preds``)."""
        from dataclasses import replace

        from .postprocess.nms import nms_keep

        cfg = self.config
        cand = [i for i in agnostic if preds[i].score >= cfg.refine_min_score and preds[i].num_points_valid > 0]
        if len(cand) < 2:
            return agnostic
        boxes = [_to_object(frame.boxes[i][0], frame.frustums[i], preds[i]) for i in cand]
        for b, i in zip(boxes, cand):
            # ranked by the score the second pass would give if its objectness matched the first's
            b.score = refined_score(preds[i].score, preds[i].objectness)
        _, kept = nms_keep(boxes, cfg.nms_iou)
        survivors = {cand[k] for k in kept}
        for i in cand:
            if i not in survivors:
                preds[i] = replace(preds[i], score=float(preds[i].score) * cfg.nms_decay)
        return [i for i in agnostic if i in survivors or i not in cand]

    def warm_up(self) -> None:
        """Run the pipeline once on a tiny synthetic frame (floor + a box, 160x120), so the
        first real frame does not pay torch's and OpenCV's first-call costs, nor the
        tracing of the network's graphs and its kernels for each batch size up to
        ``max_objects`` (:meth:`FrustumPredictor.warm_up`)."""
        self.predictor.warm_up(max_batch=self.config.max_objects)
        if self.classifier is not None and hasattr(self.classifier, "warm_up"):
            self.classifier.warm_up(max_batch=self.config.max_objects)
        h, w = 120, 160
        K = np.array([[130.0, 0.0, 79.5], [0.0, 130.0, 59.5], [0.0, 0.0, 1.0]])
        v = np.arange(h, dtype=np.float64)[:, None] - K[1, 2]
        floor = 1.2 * K[1, 1] / np.where(v > 0, v, np.inf)  # floor 1.2 m below a level camera
        depth = np.where((floor > 0) & (floor < 4.0), floor, 4.0).repeat(w, axis=1).astype(np.float32)
        depth[50:100, 60:100] = 2.0
        rgb = np.full((h, w, 3), 128, np.uint8)
        self.detect(rgb, depth, K, boxes2d=[(60, 50, 100, 100, "chair")])
        if self._proposer is not None:
            self.detect(rgb, depth, K)

    def detect_frame(self, frame: Any, boxes2d: Sequence[Any] | None = None, use_gt_up: bool = False) -> list[Object3D]:
        """:meth:`detect` on a :class:`~shape_detector.types.Frame` (``use_gt_up`` passes ``frame.up``)."""
        return self.detect(frame.rgb, frame.depth, frame.K, boxes2d=boxes2d, up=frame.up if use_gt_up else None)
