"""Every runtime setting of the detector, once: :class:`DetectorConfig` and its presets.

``ShapeDetector``, the node's parameters, the command-line tools' flags,
``config/detector.yaml`` and ``docs/parameters.md`` all come from these declarations
(:mod:`shape_detector.settings`). Two named presets:

* ``realtime`` -- the defaults: what ``ShapeDetector()``, the node and ``replay`` run;
* ``accurate`` -- more proposals per frame and fp32 everywhere, for offline evaluation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from .model.devices import usable_cores
from .settings import Spec, check, coerce, setting, specs

PROPOSAL_SOURCES = ("geometric", "learned", "hybrid", "external", "onnx")
#: the proposal sources built into the package (no boxes or model file from outside)
BUILTIN_PROPOSAL_SOURCES = ("geometric", "learned", "hybrid")
PRECISIONS = ("auto", "fp32", "bf16", "int8")
BACKENDS = ("auto", "onnxruntime", "torch")


@dataclass(frozen=True)
class DetectorConfig:
    """The detector's settings (camera optical frame, metres, probabilities in [0, 1])."""

    weights: str = setting("", "network weights file; empty = the packaged weights", node="rebuild")
    device: str = setting("cpu", "compute device: cpu, cuda, cuda:N or auto", node="rebuild")
    backend: str = setting("auto", "inference runtime: auto (ONNX Runtime when installed, else PyTorch), "
                           "onnxruntime or torch", choices=BACKENDS, node="rebuild")
    classifier: str = setting("", "proposal classifier that decides class and score of built-in proposals and of "
                              "given boxes without a class; empty = the packaged one trained on the proposer's "
                              "candidates (hybrid: classifier_hybrid.pt, else classifier.pt), 'none' = off, or a file",
                              node="rebuild")
    proposal_source: str = setting("hybrid", "2D proposals: geometric (built in, from the depth), learned "
                                   "(built in, a small network on colour and depth), hybrid (both: the network's objects with the "
                                   "geometric edges where they agree), external (boxes given with "
                                   "each frame / the detections2d topic) or onnx (a YOLO ONNX file, proposal_model)",
                                   choices=PROPOSAL_SOURCES)
    proposal_model: str = setting("", "YOLOv5/v8 ONNX file for proposal_source onnx (COCO classes mapped to ours); "
                                  "for learned or hybrid, another network from train-proposer (empty = the packaged one)")
    score_threshold: float = setting(0.3, "minimum score of a published object", range=(0.0, 1.0), node="dynamic")
    max_objects: int = setting(8, "built-in proposals (frustums) per frame, best first: the speed knob "
                               "(given 2D boxes are all run)",
                               range=(1, 1000), node="dynamic")
    frustum_points: int = setting(0, "points sampled per frustum; 0 = the count the network was trained "
                                  "with (512 for the packaged one). Fewer cost less in every pass, given boxes "
                                  "too: 256 takes about 0.8x the time on a 2-core CPU without AMX, at about a "
                                  "point of built-in mAP@0.25 (docs/model_card.md)", range=(0, 8192),
                                  node="rebuild")
    nms_iou: float = setting(0.25, "3D IoU above which the lower-scoring of two built-in detections is "
                             "suppressed", range=(0.0, 1.0), node="dynamic")
    nms_decay: float = setting(0.1, "score factor kept by a suppressed detection (Soft-NMS); 0 drops it",
                               range=(0.0, 1.0), node="dynamic")
    refine: bool = setting(True, "run each built-in proposal scored >= refine_min_score again with its decided "
                           "class given (that class's box prior)", node="dynamic")
    refine_min_score: float = setting(0.3, "score a built-in proposal needs for the class-given second pass",
                                      range=(0.0, 1.0), node="dynamic")
    refine_nms: bool = setting(True, "before the second pass, suppress built-in proposals whose first-pass box "
                               "duplicates a better one (3D NMS at nms_iou; their score times nms_decay): "
                               "the second pass then runs on one proposal per object", node="dynamic")
    mirror_tta: str = setting("never", "also run each frustum mirrored and merge: given (external boxes only), "
                              "always or never", choices=("given", "always", "never"))
    precision: str = setting("auto", "network arithmetic: auto (onnxruntime: int8 for the class-agnostic "
                             "first pass, whose boxes are never published, and for given 2D boxes with their class, "
                             "fp32 for the class-given second pass; torch: bfloat16 "
                             "for 4+ frustums on CPUs with AMX, else fp32), fp32, bf16 (torch), or int8 "
                             "(onnxruntime: every pass's box and shape PointNets in int8, a quarter less network "
                             "time, accuracy in the model card); int8 also runs the learned 2D proposer "
                             "(proposal_source learned / hybrid) in int8", choices=PRECISIONS)
    trace: bool = setting(True, "run the PyTorch network as frozen TorchScript graphs (releases the GIL)")
    num_threads: int = setting(1, "intra-op threads of the network; 0 keeps the runtime's default",
                               range=(0, 256))
    workers: int = setting(0, "threads a frame's frustums are split over, each single-threaded; 1 = serial; "
                           "0 = auto: 2 on a machine with two or more cores, 1 inside the node's two-stage "
                           "pipeline (which already keeps two cores busy)", range=(0, 64))
    point_fit: float = setting(0.15, "grow each box to its segmented points between this quantile and its "
                               "complement per axis; 0 = off", range=(0.0, 0.5), hi_open=True, node="dynamic")
    fit_confidence: float = setting(0.8, "foreground probability a point needs to count as the object's in "
                                    "point fit and free-space carving", range=(0.5, 1.0), hi_open=True,
                                    node="dynamic")
    floor_snap: float = setting(0.25, "put a box's bottom on the measured floor when within this many metres; "
                                "0 = off", range=(0.0, 5.0), node="dynamic")
    free_space: bool = setting(True, "shrink boxes out of space the depth map sees through, never past measured "
                               "points", node="dynamic")
    snap_primitives: bool = setting(True, "turn nearly box-aligned primitives to the box axes and clip them to "
                                    "the box", node="dynamic")

    def replace(self, **changes: Any) -> DetectorConfig:
        """A copy with ``changes`` applied and validated (ValueError names every problem)."""
        return make_config(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain name -> value."""
        return dataclasses.asdict(self)


#: preset name -> the changes it makes to the defaults
PRESETS: dict[str, dict[str, Any]] = {
    "realtime": {},
    "accurate": {"max_objects": 25, "workers": 2, "precision": "fp32", "mirror_tta": "given", "refine_nms": False},
}


def resolved_workers(workers: int, pipelined: bool = False) -> int:
    """Frustum worker threads for a ``workers`` setting: 0 (auto) is 1 in the node's two-stage
    pipeline and otherwise 2 where this process may use two or more cores; others as given."""
    if workers > 0:
        return int(workers)
    if pipelined:
        return 1
    return 2 if usable_cores() >= 2 else 1

def detector_specs() -> dict[str, Spec]:
    """name -> :class:`~shape_detector.settings.Spec` of every detector setting."""
    return specs(DetectorConfig)


def problems(values: dict[str, Any]) -> list[str]:
    """Why each of ``values`` is not acceptable (unknown names included); empty when all are."""
    table = detector_specs()
    out = []
    for name, value in values.items():
        if name not in table:
            out.append(f"unknown detector setting {name!r}")
        elif (p := check(table[name], value)) is not None:
            out.append(p)
    return out


def make_config(base: DetectorConfig | None = None, **changes: Any) -> DetectorConfig:
    """``base`` (default: the defaults) with ``changes``, validated: ValueError lists every
    invalid value with the reason."""
    found = problems(changes)
    if found:
        raise ValueError("; ".join(found))
    table = detector_specs()
    values = {k: coerce(table[k], v) for k, v in changes.items()}
    return dataclasses.replace(base or DetectorConfig(), **values)


def preset(name: str, **changes: Any) -> DetectorConfig:
    """The named preset (``realtime`` or ``accurate``) with ``changes`` on top."""
    if name not in PRESETS:
        raise ValueError(f"preset must be one of {tuple(PRESETS)}, got {name!r}")
    return make_config(None, **{**PRESETS[name], **changes})
