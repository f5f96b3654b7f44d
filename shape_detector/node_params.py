"""The live node's parameters without ROS: the detector's settings
(:class:`~shape_detector.detector_config.DetectorConfig`, realtime preset) and the node's own
(:class:`NodeConfig`), their validation at start and on every change, and building the detector."""

from __future__ import annotations

import time
from dataclasses import dataclass
from collections.abc import Callable
from typing import Any

from .detector_config import DetectorConfig, detector_specs, preset, resolved_workers
from .settings import Spec, check, setting, specs

@dataclass(frozen=True)
class NodeConfig:
    """The live node's own settings (the detector's are :class:`DetectorConfig`)."""

    pipeline: bool = setting(True, "two worker threads: the next frame's gravity, proposals and frustums run while "
                             "the network finishes the current one (output in input order); false = one thread")
    pipeline_split: str = setting("auto", "with pipeline: where the network's first pass runs: prepare (second "
                                  "thread), network (first thread) or auto (split over both, the share of the "
                                  "frame's frustums that balances the threads)",
                                  choices=("auto", "prepare", "network"))
    detector_processes: int = setting(0, "run the detector in worker processes: with pipeline, the two frames in "
                                      "flight run in parallel outside this process's interpreter lock (about 150 "
                                      "MiB each; the node keeps two frames in flight, so 2 is the useful value); "
                                      "0 = in the node's own threads", range=(0, 2))
    sync_slop: float = setting(0.02, "approximate time synchroniser slop between image and depth stamps, s",
                               range=(0.0, 10.0), node="dynamic")
    sync_queue_size: int = setting(10, "synchroniser queue size per input topic", range=(1, 1000), node="dynamic")
    depth_scale: float = setting(0.0, "metres per raw unit of integer depth images; 0 = by encoding (16UC1: "
                                 "0.001, 32FC1: 1)", range=(0.0, 1000.0), node="dynamic")
    size_mismatch: str = setting("rescale", "depth and colour of different sizes: rescale (colour to the depth "
                                 "size, intrinsics scaled) or skip the frame", choices=("rescale", "skip"),
                                 node="dynamic")
    up_source: str = setting("auto", "gravity direction: auto (the scene's camera pose where one is known at the "
                             "frame's stamp, else estimated), pose (the same, warned about when none is known), "
                             "estimate (from the scene), fixed (parameter up) or imu (the imu topic, low-passed)",
                             choices=("auto", "pose", "estimate", "fixed", "imu"), node="dynamic")
    up: list = setting([0.0, -1.0, 0.0], "fixed gravity-up vector, camera optical frame (up_source fixed; "
                       "normalised)", length=3, node="dynamic")
    imu_to_camera: list = setting([0.0, 0.0, 0.0, 1.0], "rotation IMU frame -> camera optical frame as quaternion "
                                  "x, y, z, w", length=4, node="dynamic")
    imu_time_constant: float = setting(0.5, "low-pass time constant of the IMU gravity filter, s",
                                       range=(0.0, 60.0), node="dynamic")
    qos: str = setting("sensor_data", "input QoS: sensor_data (best effort, depth 5) or reliable",
                       choices=("sensor_data", "reliable"))
    qos_depth: int = setting(5, "input subscription queue depth", range=(1, 100))
    publish_detections: bool = setting(True, "publish ~/detections (vision_msgs/Detection3DArray) when "
                                       "vision_msgs is installed")
    stats_period: float = setting(10.0, "seconds between throughput / latency log lines (0 = off)",
                                  range=(0.0, 3600.0), node="dynamic")
    warn_image_bytes: int = setting(33554432, "warn (once per topic) about input images larger than this, bytes: "
                                    "best-effort messages larger than the shared-memory segment are dropped by the "
                                    "transport (qos reliable avoids it)", range=(1, 2**40), node="dynamic")
    detector_factory: str = setting("", "'package.module:callable' building the detector from ShapeDetector's "
                                    "keyword arguments; empty = ShapeDetector")
    publish_scene: bool = setting(True, "keep a scene map: publish ~/scene, ~/map and ~/surfaces each processed "
                                  "frame and serve ~/get_plan")
    world_frame: str = setting("odom", "fixed world frame of the scene map (z up)")
    pose_source: str = setting("auto", "camera pose: tf (/tf, /tf_static), odom (odom_topic), pose (pose_topic), "
                               "none (static camera) or auto (any of them that delivers; static camera until one "
                               "does)", choices=("auto", "tf", "odom", "pose", "none"))
    odom_topic: str = setting("odom", "nav_msgs/Odometry topic giving the camera pose (child_frame_id: a frame "
                              "linked to the camera by TF, the camera frame, or empty = the camera)")
    pose_topic: str = setting("pose", "geometry_msgs/PoseStamped topic giving the camera pose")
    pose_timeout: float = setting(0.1, "longest wait for a camera pose at a frame's stamp when the newest pose "
                                  "is older (odom_topic, pose_topic, /tf without tf2_ros), s", range=(0.0, 5.0))
    grid_resolution: float = setting(0.05, "navigation grid cell size (~/map), m", range=(0.005, 1.0))
    inflation_radius: float = setting(0.2, "agent radius: the grid is inflated by it for ~/get_plan, m",
                                      range=(0.0, 5.0))
    plan_unknown: str = setting("interior", "what ~/get_plan makes of unknown grid cells: interior (unseen floor "
                                "enclosed by seen cells is walkable at twice the cost, as nav2 allows unknown "
                                "space), blocked (seen floor only) or free", choices=("interior", "blocked", "free"))
    plan_uncertainty: float = setting(0.5, "~/get_plan keeps this many standard deviations of each box face's "
                                      "spread over its observations as extra distance (at most 10 cm; 0 = none)",
                                      range=(0.0, 5.0))
    plan_squeeze: float = setting(0.02, "where no ~/get_plan path keeps inflation_radius (and the margins), one may "
                                  "pass up to this much closer to the map's obstacles at a high cost, m (0 = never)",
                                  range=(0.0, 0.5))
    scene_confirm_observations: int = setting(3, "a tracked object is published once detected in this many "
                                              "frames", range=(1, 1000))
    scene_delete_misses: int = setting(3, "a tracked object is removed after this many frames that see its space "
                                       "empty", range=(1, 1000))
    scene_publish_score: float = setting(0.5, "a confirmed tracked object is published (scene, map grid, JSON) "
                                         "while its score, which grows with consistent detections, is at least "
                                         "this (0 = as soon as confirmed)", range=(0.0, 1.0))
    scene_track_classifier: str = setting("default", "decides each published tracked object's class and score "
                                          "from the whole track (its class evidence, fused size, detections and "
                                          "neighbours): default (the packaged one), a weights file from "
                                          "shape-detector train-track-classifier, or empty (the class evidence "
                                          "alone decides)")
    scene_in: str = setting("", "scene JSON to continue at start (written by scene_out or replay --scene-out, in "
                            "world_frame, e.g. a robot's map frame); empty = start a fresh map")
    scene_out: str = setting("", "file the scene map is written to as JSON (atomically) by ~/save_scene, every "
                             "scene_save_period and at shutdown; empty = none")
    scene_save_period: float = setting(0.0, "with scene_out: write the map every this many seconds when it changed "
                                       "(0 = only on ~/save_scene and at shutdown), s", range=(0.0, 86400.0))


#: name -> Spec of every node parameter: the detector's settings (realtime preset), then the node's own
PARAMETERS: dict[str, Spec] = {**specs(preset("realtime")), **specs(NodeConfig)}
#: parameters with a fixed set of values
CHOICES: dict[str, tuple[str, ...]] = {k: tuple(v.choices) for k, v in PARAMETERS.items() if v.choices}
#: changing these rebuilds the detector
REBUILD = tuple(k for k, v in PARAMETERS.items() if v.node == "rebuild")
#: detector settings the node changes on a built detector (``configure``, or the attribute
#: of a custom detector that has it)
DETECTOR_ATTRS = tuple(k for k in detector_specs() if PARAMETERS[k].node == "dynamic")


def descriptor_fields(spec: Spec) -> dict[str, Any]:
    """The fields of a ROS ParameterDescriptor for ``spec``; ranges as ``(lo, hi)`` under
    ``floating_point_range`` or ``integer_range`` (the node turns them into messages)."""
    out: dict[str, Any] = dict(description=spec.doc, read_only=spec.node == "read_only",
                               dynamic_typing=spec.length is not None)
    if spec.range is not None:
        key = "floating_point_range" if spec.kind is float else "integer_range"
        out[key] = (spec.range[0], spec.range[1])
    if spec.choices:
        out["additional_constraints"] = "one of: " + ", ".join(spec.choices)
    return out


def validate(name: str, value: Any) -> str | None:
    """Why ``value`` is not acceptable for parameter ``name``; None if it is (or ``name``
    is not one of the node's)."""
    return check(PARAMETERS[name], value) if name in PARAMETERS else None


def validate_all(values: dict[str, Any]) -> list[str]:
    """The problems of every parameter in ``values`` (empty: all fine)."""
    return [p for p in (validate(k, v) for k, v in values.items()) if p]


def detector_config(p: dict[str, Any], external: bool) -> DetectorConfig:
    """The detector settings among the parameter values ``p`` (external boxes: no proposer)."""
    values = {k: p[k] for k in detector_specs() if k in p}
    if external:
        values["proposal_source"] = "external"
    if p.get("pipeline") and not values.get("workers"):  # auto: the pipeline's two stages use the cores
        values["workers"] = resolved_workers(0, pipelined=True)
    return preset("realtime", **values)


def apply_to_detector(det: Any, name: str, value: Any) -> bool:
    """Set a dynamic detector setting on a built detector; False when it has no such setting."""
    if hasattr(det, "configure") and hasattr(det, "config"):
        det.configure(**{name: value})
        return True
    if hasattr(det, name):
        setattr(det, name, type(getattr(det, name))(value))
        return True
    return False


def build_detector(p: dict[str, Any], external: bool, factory: Callable[..., Any] | None,
                   info: Callable[[str], Any], warning: Callable[[str], Any]) -> Any:
    """The detector the parameter values ``p`` ask for (``factory``, else the
    ``detector_factory`` parameter, else ShapeDetector; in ``detector_processes`` worker
    processes unless ``factory`` is given), warmed up; ``info``/``warning`` log a line."""
    from .detector import ShapeDetector
    from .bags.detector_factory import factory_kwargs, load_factory

    config = detector_config(p, external)
    processes = int(p.get("detector_processes", 0)) if factory is None else 0
    t = time.perf_counter()
    if processes > 0:  # the workers build it from the factory's name: a callable cannot travel
        from .process_detector import ProcessDetector

        # workers that cannot start would fail every frame: started() says so at once instead
        det: Any = ProcessDetector.started(config, processes, p["detector_factory"])
        name = f"{p['detector_factory'] or 'ShapeDetector'} in {processes} worker process(es)"
    else:
        if factory is None and p["detector_factory"]:
            factory = load_factory(p["detector_factory"])
        if factory is None:
            det = ShapeDetector(config)
        else:  # custom factories take ShapeDetector's keyword arguments; dynamic settings follow as attributes
            det = factory(**factory_kwargs(config))
            for attr in DETECTOR_ATTRS:
                apply_to_detector(det, attr, p[attr])
        name = type(det).__name__
    if hasattr(det, "warm_up") and processes <= 0:  # first-call costs now, not on the first camera frame
        try:
            det.warm_up()
        except Exception as exc:  # a failed warm-up must not stop the node; frames will tell
            warning(f"detector warm-up failed: {exc!r}")
    pred = getattr(det, "predictor", None)
    runtime = (f", backend={pred.backend}, precision={pred.precision}"
               if hasattr(pred, "backend") and hasattr(pred, "precision") else "")
    info(f"detector {name} ready in {time.perf_counter() - t:.2f} s "
         f"(weights={config.weights or 'default'}, device={config.device}{runtime})")
    return det
