"""The live node's parameters without ROS: declarations (default, description, whether
read-only, range) and their validation, used at start and on every change."""

from __future__ import annotations

import time
from typing import Any, Callable

from .validation import check_choice, check_number, check_vector

#: name -> (default, description, read_only, extra: "range" (lo, hi) inclusive, "dynamic_typing")
PARAMETERS: dict[str, tuple[Any, str, bool, dict[str, Any]]] = {
    "weights": ("", "network weights file; empty = the packaged default (reloaded when changed)", False, {}),
    "device": ("cpu", "torch device: cpu, cuda, cuda:0 ... (detector reloaded when changed)", False, {}),
    "score_threshold": (0.3, "minimum detection score", False,
                        {"range": (0.0, 1.0)}),
    "max_objects": (10, "built-in proposals (frustums) per frame, best proposer score first: the speed knob "
                    "(10: real time on 2 cores; ShapeDetector and the offline tools use 25, the accuracy setting)", False,
                    {"range": (1, 1000)}),
    "nms_decay": (0.1, "built-in proposals: score factor of the boxes 3D NMS suppresses, kept after the others "
                  "(0 = drop them; with score_threshold 0.3 none is published)", False,
                  {"range": (0.0, 1.0)}),
    "refine": (True, "built-in proposals: run each frustum scored >= refine_min_score a second time with its "
               "predicted class given (that class's box prior)", False, {}),
    "refine_min_score": (0.3, "score (after the proposal classifier) a built-in proposal needs for the class-given "
                         "second pass", False,
                         {"range": (0.0, 1.0)}),
    "free_space": (True, "shrink boxes out of space the depth map sees through (side faces; the top of "
                   "flat-topped classes), never past measured points", False, {}),
    "classifier": ("", "proposal classifier file that re-decides the class of built-in proposals; empty = the "
                   "packaged one, 'none' = off (the network's class head decides) (detector reloaded when "
                   "changed)", False, {}),
    "workers": (1, "threads the network splits a frame's frustums over (single-threaded ops each; 1 = serial; "
                "2 is faster with pipeline false, slower with it)", True,
                {"range": (1, 64)}),
    "pipeline": (True, "two worker threads: the next frame's gravity, proposals and frustums run while the "
                 "network finishes the current one (higher throughput, output in input order); false = one thread",
                 True, {}),
    "pipeline_split": ("auto", "with pipeline: where the network's first pass runs: 'prepare' (second thread, "
                       "with the rest of the network), 'network' (first thread, after prepare) or 'auto' (whichever "
                       "balances the two threads better, judged from the last frame's stage times)", True, {}),
    "precision": ("auto", "network arithmetic: 'auto' (bfloat16 for 4 or more frustums on CPUs with AMX, "
                  "else fp32), 'fp32' or 'bf16' (faster with many frustums on AMX / AVX512-BF16 CPUs, "
                  "much slower without)", True, {}),
    "mirror_tta": ("given", "also run each frustum mirrored and average: 'given' (external boxes only), "
                   "'always' or 'never'", True, {}),
    "proposal_source": ("geometric", "2D proposals: 'geometric' (built in) or 'external' (the detections2d "
                        "topic, vision_msgs/Detection2DArray, synchronised with the image)", True, {}),
    "sync_slop": (0.02, "approximate time synchroniser slop between image and depth stamps, seconds", False,
                  {"range": (0.0, 10.0)}),
    "sync_queue_size": (10, "synchroniser queue size per input topic", False,
                        {"range": (1, 1000)}),
    "depth_scale": (0.0, "metres per raw unit of integer depth images; 0 = by encoding (16UC1: 0.001, 32FC1: 1)",
                    False, {"range": (0.0, 1000.0)}),
    "size_mismatch": ("rescale", "depth and colour of different sizes: 'rescale' (colour resized to the depth "
                      "size, intrinsics scaled) or 'skip' the frame", False, {}),
    "up_source": ("estimate", "gravity direction: 'estimate' (from the scene), 'fixed' (parameter up) or "
                  "'imu' (the imu topic, low-passed)", False, {}),
    "up": ([0.0, -1.0, 0.0], "fixed gravity-up vector in the camera optical frame (up_source=fixed; normalised)",
           False, {"dynamic_typing": True}),
    "imu_to_camera": ([0.0, 0.0, 0.0, 1.0], "rotation IMU frame -> camera optical frame as quaternion x, y, z, w "
                      "(identity: the IMU reports in the camera optical frame)", False, {"dynamic_typing": True}),
    "imu_time_constant": (0.5, "low-pass time constant of the IMU gravity filter, seconds", False,
                          {"range": (0.0, 60.0)}),
    "qos": ("sensor_data", "input QoS: 'sensor_data' (best effort, depth 5) or 'reliable'", True, {}),
    "qos_depth": (5, "input subscription queue depth", True,
                  {"range": (1, 100)}),
    "publish_detections": (True, "publish ~/detections (vision_msgs/Detection3DArray) when vision_msgs is installed",
                           True, {}),
    "stats_period": (10.0, "seconds between throughput / latency log lines (0 = off)", False,
                     {"range": (0.0, 3600.0)}),
    "warn_image_bytes": (33554432, "log a warning (once per topic) for input images larger than this, bytes: "
                         "with best-effort QoS, messages larger than the shared-memory segment are dropped "
                         "by the transport before the node sees them (qos:=reliable avoids it)", False,
                         {"range": (1, 2**40)}),
    "detector_factory": ("", "'package.module:callable' building the detector (same keyword arguments as "
                         "ShapeDetector); empty = shape_detector.detector.ShapeDetector", True, {}),
}

_CHOICES = {
    "pipeline_split": ("auto", "prepare", "network"),
    "proposal_source": ("geometric", "external"),
    "size_mismatch": ("rescale", "skip"),
    "up_source": ("estimate", "fixed", "imu"),
    "qos": ("sensor_data", "reliable"),
}
CHOICES: dict[str, tuple[str, ...]] = {
    "pipeline_split": ("auto", "prepare", "network"),
    "proposal_source": ("geometric", "external"),
    "size_mismatch": ("rescale", "skip"),
    "up_source": ("estimate", "fixed", "imu"),
    "qos": ("sensor_data", "reliable"),
    "precision": ("auto", "fp32", "bf16"),
    "mirror_tta": ("given", "always", "never"),
}
#: changing these rebuilds the detector
REBUILD = ("weights", "device", "classifier")
#: parameters the node sets on a built detector that has the attribute (custom factories
#: need not take them as constructor arguments); dynamic
DETECTOR_ATTRS = ("score_threshold", "max_objects", "nms_decay", "refine", "refine_min_score", "free_space")
_VECTORS = {"up": 3, "imu_to_camera": 4}


def validate(name: str, value: Any) -> str | None:
    """Why ``value`` is not acceptable for parameter ``name``; None if it is (or ``name``
    is not one of the node's)."""
    if name not in PARAMETERS:
        return None
    default, _, _, extra = PARAMETERS[name]
    if name in CHOICES:
        return check_choice(name, value, CHOICES[name])
    if name in _VECTORS:
        return check_vector(name, value, _VECTORS[name])
    if isinstance(default, bool):
        return None if isinstance(value, bool) else f"{name} must be true or false, got {value!r}"
    if isinstance(default, (int, float)):
        lo, hi = extra.get("range", (None, None))
        return check_number(name, value, lo, hi, integer=isinstance(default, int))
    if isinstance(default, str) and not isinstance(value, str):
        return f"{name} must be a string, got {value!r}"
    return None


def validate_all(values: dict[str, Any]) -> list[str]:
    """The problems of every parameter in ``values`` (empty: all fine)."""
    return [p for p in (validate(k, v) for k, v in values.items()) if p]


def build_detector(p: dict[str, Any], external: bool, factory: Callable[..., Any] | None,
                   info: Callable[[str], Any], warning: Callable[[str], Any]) -> Any:
    """The detector the parameter values ``p`` ask for (``factory``, else the
    ``detector_factory`` parameter, else ShapeDetector), warmed up; ``info``/``warning``
    log a line."""
    from .detector import ShapeDetector, classifier_option
    from .replay import load_factory

    kwargs = dict(weights=p["weights"] or None, device=p["device"], score_threshold=float(p["score_threshold"]),
                  max_objects=int(p["max_objects"]), workers=int(p["workers"]), precision=str(p["precision"]),
                  mirror_tta=str(p["mirror_tta"]),
                  # external 2D boxes come with every frame: no built-in proposer needed
                  proposals="none" if external else "geometric")
    if (classifier := classifier_option(p["classifier"])) is not None:
        kwargs["classifier"] = classifier
    if factory is None and p["detector_factory"]:
        factory = load_factory(p["detector_factory"])
    t = time.perf_counter()
    det = (factory or ShapeDetector)(**kwargs)
    for name in ("nms_decay", "refine", "refine_min_score", "free_space"):  # not constructor arguments: custom
        if hasattr(det, name):  # factories need not take them
            setattr(det, name, type(getattr(det, name))(p[name]))
    if hasattr(det, "warm_up"):  # first-call costs now, not on the first camera frame
        try:
            det.warm_up()
        except Exception as exc:  # a failed warm-up must not stop the node; frames will tell
            warning(f"detector warm-up failed: {exc!r}")
    info(f"detector {type(det).__name__} ready in {time.perf_counter() - t:.2f} s "
         f"(weights={kwargs['weights'] or 'default'}, device={kwargs['device']})")
    return det
