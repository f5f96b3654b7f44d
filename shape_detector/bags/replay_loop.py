"""The offline replay loop: read synchronised frames, detect, write; stop on request.

``summary`` here is a :class:`~shape_detector.bags.summary.ReplaySummary`; ``scene`` an optional
:class:`~shape_detector.bags.scene_record.SceneRecorder` updated after every frame.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
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


@dataclass
class _InFlight:
    """A frame between reading and writing: its input copies, checked input and detection."""

    frame: Any
    copies: list[RawMessage] = field(default_factory=list)
    prepared: Any = None
    up: Any = None
    job: Any = None  # a Future from the detector's submit(); None: nothing to wait for
    objects: list = field(default_factory=list)
    detected: bool = False


def _start_frame(entry: _InFlight, detector: Any, summary: Any, up_vec: Any, depth_scale: float | None,
                 size_mismatch: str, submit: bool, pose_up: Any = None) -> None:
    """Check one synchronised frame and start (``submit``: hand to the detector's workers) or
    run its detection; failures are counted in ``summary``. Gravity: ``up_vec`` (fixed), else
    the frame's IMU gravity, else ``pose_up(frame)`` (the camera pose's), else estimated."""
    frame = entry.frame
    try:
        prepared = entry.prepared = frame.prepare(depth_scale=depth_scale, size_mismatch=size_mismatch)
        for note in prepared.notes:
            summary.notes[note] += 1
        if prepared.valid_depth_fraction == 0.0:
            summary.skipped["no valid depth"] += 1
            return
        entry.up = up_vec if up_vec is not None else frame.up
        if entry.up is None and pose_up is not None:
            entry.up = pose_up(frame)
        args = (prepared.rgb, prepared.depth, prepared.K)
        if submit:
            entry.job = detector.submit(*args, boxes2d=prepared.boxes2d, up=entry.up)
            return
        td = time.perf_counter()
        entry.objects = list(detector.detect(*args, boxes2d=prepared.boxes2d, up=entry.up))
        summary.detect_ms.append((time.perf_counter() - td) * 1e3)
        summary.detected += 1
        entry.detected = True
    except FrameError as e:
        summary.skipped[e.kind] += 1
        summary.notes[f"frame skipped: {e}"] += 1
    except Exception as e:  # noqa: BLE001 - a detector failure must not end the replay
        _detector_error(summary, e)


def _wait_frame(entry: _InFlight, detector: Any, summary: Any) -> None:
    """The objects of a frame handed to the detector's workers (failures counted)."""
    if entry.job is None:
        return
    try:
        entry.objects = list(detector.finish(entry.job))
        summary.detect_ms.append(float(detector.last_detect_ms))
        summary.detected += 1
        entry.detected = True
    except Exception as e:  # noqa: BLE001
        _detector_error(summary, e)


def _detector_error(summary: Any, e: Exception) -> None:
    summary.skipped["detector error"] += 1
    summary.notes[f"detector error: {type(e).__name__}: {e}"] += 1


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
    """Read, detect, write; returns normally after input damage or a stop request.

    A detector with ``submit`` / ``finish`` and ``processes`` (detector worker processes)
    gets that many frames at once plus one queued while this loop reads and writes; frames are still
    written in input order, each after the input messages read before it (as without
    workers), and the frames in flight at a stop or a read error are finished and written."""
    source = reader.source
    roles = reader.selection.roles()
    window = int(getattr(detector, "processes", 0)) if hasattr(detector, "submit") else 0
    copies: list[RawMessage] = []  # input messages read since the last frame (with a window)
    in_flight: deque[_InFlight] = deque()

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
            if window:
                copies.append(m)
            else:
                out.copy(m, source)
        bar.update(summary.messages_in, summary.frames_out)

    def write(entry: _InFlight) -> None:
        for m in entry.copies:
            out.copy(m, source)
        _wait_frame(entry, detector, summary)
        frame, objects = entry.frame, entry.objects
        out.write_objects(objects, frame.stamp_ns, frame.frame_id)
        if scene is not None:  # one scene and map per frame; a skipped frame repeats the current state
            used = entry.prepared if entry.detected else None  # learn only from detected frames
            scene.update(frame, used, objects, entry.up)
            scene.write(out, frame.stamp_ns)
        summary.frames_out += 1
        summary.objects += len(objects)
        summary.objects_per_class.update(o.class_name for o in objects)
        if on_frame is not None:
            on_frame(frame, entry.prepared, objects)
        bar.update(summary.messages_in, summary.frames_out)

    try:
        check_stop()
        for frame in reader.frames(on_message=on_message, all_topics=copy_input):
            summary.synced += 1
            entry = _InFlight(frame, copies[:])
            copies.clear()
            _start_frame(entry, detector, summary, up_vec, depth_scale, size_mismatch, submit=window > 0,
                         pose_up=scene.up_at if scene is not None else None)
            in_flight.append(entry)
            while len(in_flight) > window:  # the workers busy, one frame queued behind them
                write(in_flight.popleft())
            check_stop()
    except BagReadError as e:
        summary.error = str(e)
    except _Stopped as e:
        summary.interrupted = str(e)
    finally:
        while in_flight:  # frames already handed over are finished and written, never lost
            write(in_flight.popleft())
        for m in copies:
            out.copy(m, source)
