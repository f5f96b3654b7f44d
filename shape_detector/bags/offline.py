"""Offline replay: every synchronised frame of a bag through the detector into an output MCAP.

The output gets the input topics plus ``/shape_detector/markers`` (and ``/shape_detector/detections``)
at the input stamps and, with a scene (:class:`~.scene_record.SceneOptions`), ``/shape_detector/scene``
and ``/shape_detector/map`` once per frame plus the final map as JSON. Nothing is dropped
offline.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .output_safety import SafeOutputBag
from .reader import BagFrameReader
from .replay_loop import check_replay_args, count_damage, replay_loop
from .scene_record import SceneOptions, SceneRecorder
from .summary import Progress, ReplaySummary
from .topics import TopicSelection

_ROLES = {"image", "depth", "camera_info", "imu", "detections2d"}


def parse_up(up: Any) -> np.ndarray | None:
    """A unit gravity-up vector (camera optical frame) from ``"x,y,z"`` or three numbers; None stays None."""
    if up is None:
        return None
    v = np.asarray([float(x) for x in (up.split(",") if isinstance(up, str) else up)], dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
        raise ValueError(f"up must be three finite numbers, not all zero, got {up!r}")
    return v / np.linalg.norm(v)


def _topic_roles(topics: TopicSelection | dict[str, str] | None) -> dict[str, Any]:
    if isinstance(topics, TopicSelection):
        return {k: v for k, v in vars(topics).items() if v}
    sel = {k: v for k, v in dict(topics or {}).items() if v}
    unknown = set(sel) - _ROLES
    if unknown:
        raise ValueError(f"unknown topic roles {sorted(unknown)}")
    return sel


def replay_bag(
    in_path: str | Path,
    out_path: str | Path,
    detector: Any = None,
    topics: TopicSelection | dict[str, str] | None = None,
    progress: bool = True,
    *,
    slop: float = 0.02,
    queue_size: int = 30,
    depth_scale: float | None = None,
    up: Any = None,
    size_mismatch: str = "rescale",
    write_detections: bool = True,
    overwrite: bool = False,
    copy_input: bool = True,
    on_frame: Any = None,
    should_stop: Any = None,
    scene: SceneOptions | None = None,
) -> ReplaySummary:
    """Run ``detector`` over every synchronised frame of bag ``in_path`` and write ``out_path``
    (rosbag2 MCAP): the input topics (``copy_input``) plus markers and detections at the input stamps.

    ``detector``: anything with ``detect(rgb, depth, K, boxes2d=None, up=None)`` (default: a new
    :class:`shape_detector.detector.ShapeDetector`). ``topics``: a :class:`TopicSelection` or a dict
    with keys ``image, depth, camera_info, imu, detections2d`` (missing = chosen automatically).
    ``up``: fixed gravity-up vector (camera frame); else the IMU's when an imu topic is given, else
    estimated by the detector. ``depth_scale``: metres per raw depth unit (> 0; None = by encoding).
    ``on_frame(frame, prepared_or_None, objects)`` is called per frame. ``should_stop()``: polled
    between messages; a true value (e.g. ``'SIGTERM'``) ends the replay early with
    ``summary.interrupted`` set to it. ``scene``: also build the scene map (``summary.scene``).

    The output is written under a temporary sibling name and renamed into place when finalised (also
    after damage or a stop); ``overwrite`` replaces an old output only then. An output that is,
    contains or lies inside the input is refused (``UnsafeOutputError``, a ValueError). Damage in the
    input ends the replay early with ``summary.error`` set; damaged chunks are skipped and listed in
    ``summary.damage``. Unusable frames (bad encoding, sizes, missing camera_info) get an empty
    MarkerArray and are counted in ``summary.skipped``. Raises FileNotFoundError / ValueError /
    BagReadError when nothing could be read, FileExistsError, and ``OutputError`` (an OSError naming
    the output) when the output cannot be written.
    """
    t0 = time.perf_counter()
    check_replay_args(depth_scale, slop, queue_size)
    up_vec = parse_up(up)
    sel = _topic_roles(topics)
    safe = SafeOutputBag(in_path, out_path, overwrite=overwrite, write_detections=write_detections)
    recorder = None
    if scene is not None:
        recorder = SceneRecorder(in_path, scene, log=(lambda s: print(s, file=sys.stderr)) if progress else None)
    if detector is None:
        from ..detector import ShapeDetector

        detector = ShapeDetector()
    summary = ReplaySummary(str(in_path), str(out_path))
    with BagFrameReader(in_path, slop=slop, queue_size=queue_size, **sel) as reader:
        summary.topics = reader.selection
        summary.recovered = reader.source.recovered
        bar = Progress(reader.source.message_count, progress)
        with safe as out:
            try:
                replay_loop(reader, out, detector, summary, bar, copy_input=copy_input, up_vec=up_vec,
                            depth_scale=depth_scale, size_mismatch=size_mismatch, on_frame=on_frame,
                            should_stop=should_stop, scene=recorder)
            finally:
                bar.done()
            count_damage(summary, reader.source, reader.selection.image)
            summary.copied = dict(out.counts)
            summary.skipped_topics = dict(out.skipped_topics)
    if recorder is not None:
        recorder.finish()
        summary.scene = recorder.stats
    summary.wall_s = time.perf_counter() - t0
    return summary
