"""The offline replay loop: read synchronised frames, detect, write; stop on request.

``summary`` here is a :class:`~shape_detector.bags.summary.ReplaySummary`; ``scene`` an optional
:class:`~shape_detector.bags.scene_record.SceneRecorder` updated after every frame.
"""

from __future__ import annotations

import math
import time
from typing import Any

from ..frame_prep import FrameError
from .reader import BagFrameReader
from .source import BagReadError, RawMessage


class _Stopped(Exception):
    """Raised between messages when ``should_stop`` reports a signal."""


def check_replay_args(depth_scale: float | None, slop: float, queue_size: int) -> None:
    """ValueError for a depth scale that is not finite and > 0 (m per unit), a negative
    or non-finite slop (s), a queue size < 1."""
    if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be a finite number > 0 (metres per raw unit), got {depth_scale!r}")
    if not (math.isfinite(slop) and slop >= 0):
        raise ValueError(f"slop must be a finite number >= 0 (seconds), got {slop!r}")
    if int(queue_size) < 1:
        raise ValueError(f"queue_size must be >= 1, got {queue_size!r}")


def _detect_frame(frame: Any, detector: Any, summary: Any, up_vec: Any,
                  depth_scale: float | None, size_mismatch: str) -> tuple[Any, list]:
    """Prepare and detect one synchronised frame; failures are counted in ``summary``."""
    objects: list = []
    prepared = None
    try:
        prepared = frame.prepare(depth_scale=depth_scale, size_mismatch=size_mismatch)
        for note in prepared.notes:
            summary.notes[note] += 1
        if prepared.valid_depth_fraction == 0.0:
            summary.skipped["no valid depth"] += 1
        else:
            frame_up = up_vec if up_vec is not None else frame.up
            td = time.perf_counter()
            objects = list(detector.detect(prepared.rgb, prepared.depth, prepared.K,
                                           boxes2d=prepared.boxes2d, up=frame_up))
            summary.detect_ms.append((time.perf_counter() - td) * 1e3)
            summary.detected += 1
    except FrameError as e:
        summary.skipped[e.kind] += 1
        summary.notes[f"frame skipped: {e}"] += 1
    except Exception as e:  # noqa: BLE001 - a detector failure must not end the replay
        summary.skipped["detector error"] += 1
        summary.notes[f"detector error: {type(e).__name__}: {e}"] += 1
    return prepared, objects


def count_damage(summary: Any, source: Any, image_topic: str) -> None:
    """Damaged input chunks: named in ``summary.damage``, their colour images skipped."""
    for d in getattr(source, "damage", ()):
        summary.damage.append(str(d))
        lost = d.lost(image_topic)
        if lost:
            summary.skipped["corrupt_chunk"] += lost


def replay_loop(reader: BagFrameReader, out: Any, detector: Any, summary: Any, bar: Any, *,
                copy_input: bool, up_vec: Any, depth_scale: float | None, size_mismatch: str,
                on_frame: Any, should_stop: Any, scene: Any = None) -> None:
    """Read, detect, write; returns normally after input damage or a stop request."""
    source = reader.source
    roles = reader.selection.roles()

    def check_stop() -> None:
        if should_stop is not None and (why := should_stop()):
            raise _Stopped(str(why))

    def on_message(m: RawMessage) -> None:
        check_stop()
        summary.messages_in += 1
        role = roles.get(m.topic)
        if role == "image":
            summary.frames_in += 1
        elif role == "depth":
            summary.depth_in += 1
        if copy_input:
            out.copy(m, source)
        bar.update(summary.messages_in, summary.frames_out)

    try:
        check_stop()
        for frame in reader.frames(on_message=on_message, all_topics=copy_input):
            summary.synced += 1
            detected = summary.detected
            prepared, objects = _detect_frame(frame, detector, summary, up_vec, depth_scale, size_mismatch)
            out.write_objects(objects, frame.stamp_ns, frame.frame_id)
            if scene is not None:  # one scene and map per frame; a skipped frame repeats the current state
                used = prepared if summary.detected > detected else None  # learn only from detected frames
                scene.update(frame, used, objects, up_vec if up_vec is not None else frame.up)
                scene.write(out, frame.stamp_ns)
            summary.frames_out += 1
            summary.objects += len(objects)
            summary.objects_per_class.update(o.class_name for o in objects)
            if on_frame is not None:
                on_frame(frame, prepared, objects)
            bar.update(summary.messages_in, summary.frames_out)
            check_stop()
    except BagReadError as e:
        summary.error = str(e)
    except _Stopped as e:
        summary.interrupted = str(e)
