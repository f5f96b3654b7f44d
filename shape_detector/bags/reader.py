"""Synchronised RGB-D frames of a bag: :class:`BagFrameReader`.

Frames are paired with the same :class:`~shape_detector.sync.ApproximateTimeSynchronizer` as the
live node; each frame gets the ``camera_info`` nearest its stamp. On damage the frame generator
first yields every frame completed before it, then raises :class:`~.source.BagReadError`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..frame_prep import PreparedFrame, prepare_frame
from ..sync import ApproximateTimeSynchronizer, header_stamp_ns
from .source import BagReadError, RawMessage, open_bag
from .topics import select_topics


@dataclass
class SyncedFrame:
    """One synchronised set read from a bag (messages deserialised, not yet decoded).

    ``index``: 0-based count of synchronised sets; ``stamp_ns``/``frame_id``: the colour
    image's header; ``log_time_ns``: bag time of the message that completed the set;
    ``up``: low-passed IMU gravity-up (camera optical frame) when an IMU topic is used.
    """

    index: int
    stamp_ns: int
    frame_id: str
    image: Any
    depth: Any
    camera_info: Any | None
    detections2d: Any | None = None
    up: np.ndarray | None = None
    log_time_ns: int = 0

    def prepare(self, depth_scale: float | None = None, size_mismatch: str = "rescale") -> PreparedFrame:
        """The decoded frame (:func:`~shape_detector.frame_prep.prepare_frame`); raises ``FrameError``."""
        return prepare_frame(
            self.image,
            self.depth,
            self.camera_info,
            depth_scale=depth_scale,
            size_mismatch=size_mismatch,
            detections2d=self.detections2d,
        )


@dataclass
class ReadStats:
    """Counters of a frame read: messages per role, sets synchronised, frames yielded."""

    messages: int = 0
    per_role: dict[str, int] = field(default_factory=dict)
    synced: int = 0
    yielded: int = 0
    no_camera_info: int = 0


class BagFrameReader:
    """Synchronised frames of one bag.

    >>> with BagFrameReader("bags/sample") as reader:
    ...     for frame in reader.frames():
    ...         pf = frame.prepare()

    ``frames(on_message=cb)`` also calls ``cb(raw_message)`` for every message of the bag
    in bag order (``all_topics=True``, the default when a callback is given) so a writer
    can copy the input. ``slop`` (s) / ``queue_size``: synchroniser settings. The
    camera_info of a frame is the one nearest its stamp (a frame waits at most
    ``max_pending`` frames for a camera_info at or after its stamp).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        image: str | None = None,
        depth: str | None = None,
        camera_info: str | None = None,
        imu: str | None = None,
        detections2d: str | None = None,
        slop: float = 0.02,
        queue_size: int = 30,
        max_pending: int = 3,
        imu_time_constant: float = 0.5,
        imu_to_camera: Any = None,
    ) -> None:
        self.source = open_bag(path)
        try:
            self.selection = select_topics(self.source, image, depth, camera_info, imu, detections2d)
        except Exception:
            self.source.close()
            raise
        self.slop = float(slop)
        self.queue_size = int(queue_size)
        self.max_pending = max(0, int(max_pending))
        self.imu_time_constant = imu_time_constant
        self.imu_to_camera = imu_to_camera
        self.stats = ReadStats()

    @property
    def path(self) -> Path:
        """The bag's path."""
        return self.source.path

    def close(self) -> None:
        """Close the bag."""
        self.source.close()

    def __enter__(self) -> BagFrameReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _release(self, pending: deque[SyncedFrame], infos: deque[tuple[int, Any]], flush: bool) -> Iterator[SyncedFrame]:
        """Frames whose camera_info is decided (one at or after their stamp arrived, too many
        waiting, or ``flush`` at the end of the bag), each with the camera_info nearest its stamp."""
        stats = self.stats
        while pending:
            head = pending[0]
            newest = infos[-1][0] if infos else None
            if not (flush or (newest is not None and newest >= head.stamp_ns) or len(pending) > self.max_pending):
                return
            pending.popleft()
            head.camera_info = min(infos, key=lambda si: abs(si[0] - head.stamp_ns))[1] if infos else None
            if head.camera_info is None:
                stats.no_camera_info += 1
            stats.yielded += 1
            yield head

    def frames(
        self,
        on_message: Callable[[RawMessage], None] | None = None,
        all_topics: bool | None = None,
    ) -> Iterator[SyncedFrame]:
        """Yield :class:`SyncedFrame` s in order; raises :class:`BagReadError` after the
        last frame completed before damage."""
        from ..imu_gravity import ImuGravityFilter

        sel = self.selection
        roles = sel.roles()
        sync_roles = ["image", "depth"] + (["detections2d"] if sel.detections2d else [])
        index_of = {getattr(sel, r): i for i, r in enumerate(sync_roles)}
        sync = ApproximateTimeSynchronizer(len(sync_roles), self.queue_size, self.slop)
        imu = ImuGravityFilter(self.imu_time_constant, self.imu_to_camera) if sel.imu else None
        infos: deque[tuple[int, Any]] = deque(maxlen=64)
        pending: deque[SyncedFrame] = deque()
        stats = self.stats = ReadStats()
        if all_topics is None:
            all_topics = on_message is not None
        error: BaseException | None = None
        try:
            for m in self.source.messages(None if all_topics else list(roles)):
                stats.messages += 1
                if on_message is not None:
                    on_message(m)
                role = roles.get(m.topic)
                if role is None:
                    continue
                stats.per_role[role] = stats.per_role.get(role, 0) + 1
                msg = self.source.deserialize(m.raw, m.msgtype)
                if role == "camera_info":
                    stamp = header_stamp_ns(msg)
                    infos.append((m.log_time_ns if stamp is None else stamp, msg))
                elif role == "imu":
                    acc = getattr(msg, "linear_acceleration", None)
                    if acc is not None and imu is not None:
                        imu.update((acc.x, acc.y, acc.z), header_stamp_ns(msg))
                    continue
                elif (out := sync.add(index_of[m.topic], msg)) is not None:
                    stats.synced += 1
                    pending.append(_synced_frame(stats.synced - 1, out, None if imu is None else imu.up, m.log_time_ns))
                else:
                    continue
                yield from self._release(pending, infos, flush=False)
        except BagReadError as e:
            error = e
        # end of bag (or damage): every completed frame goes out
        yield from self._release(pending, infos, flush=True)
        if error is not None:
            raise error


def _synced_frame(index: int, out: tuple, up: np.ndarray | None, log_time_ns: int) -> SyncedFrame:
    img = out[0]
    return SyncedFrame(
        index=index,
        stamp_ns=int(header_stamp_ns(img) or 0),
        frame_id=str(getattr(img.header, "frame_id", "") or ""),
        image=img,
        depth=out[1],
        camera_info=None,
        detections2d=out[2] if len(out) > 2 else None,
        up=up,
        log_time_ns=log_time_ns,
    )


def iter_frames(path: str | Path, **kwargs: Any) -> Iterator[SyncedFrame]:
    """Shorthand: the synchronised frames of a bag (see :class:`BagFrameReader`)."""
    with BagFrameReader(path, **kwargs) as reader:
        yield from reader.frames()
