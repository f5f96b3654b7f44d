"""The live node's frame scheduling without ROS: one-slot mailboxes and the worker threads.

Sets go through a one-slot :class:`~shape_detector.sync.LatestMailbox` to the worker, so the
node never falls behind: a newer set replaces one not yet processed (counted as dropped).
With ``pipeline`` the worker is two threads: the first checks the input and runs the
detector's ``prepare`` on frame N+1 while the second runs ``finish`` on frame N and
publishes. The first takes a new frame only when the second has taken the last one, so
output stays in input order and a frame waits for at most one other.

The host (the node) provides: ``p`` (parameter values), ``detector``, ``stats``
(:class:`~shape_detector.node_stats.NodeStats`), ``warn(kind, text, period=, level=)``,
``publish(objects, stamp_ns, frame_id, frame, up)`` (``frame``: the checked input frame, None
when it was skipped; ``up``: gravity up in the camera frame or None), ``now_ns()`` (its clock),
``camera_info()`` (latest or None), ``info_event`` (set once one arrived),
``frame_up(frame_set, stamp_ns, frame_id)`` (gravity up for a frame about to be detected, None:
estimated), ``build_detector()`` and ``topic(name)`` (resolved topic name).
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .frame_prep import FrameError, prepare_frame
from .process_detector import close_detector
from .sync import LatestMailbox, header_stamp_ns

#: longest a thread is waited for at shutdown, seconds: a detector stuck in a frame must
#: not keep the process from exiting (the threads are daemons)
JOIN_TIMEOUT_S = 5.0


@dataclass
class FrameSet:
    """One synchronised input set waiting for the worker (``synced_at``: monotonic s; ``up``:
    gravity taken at synchronisation, filled from the camera pose when the worker takes the
    frame, None: estimated)."""

    image: Any
    depth: Any
    camera_info: Any
    detections2d: Any
    up: np.ndarray | None
    synced_at: float


@dataclass
class Job:
    """A frame between the worker's two stages: what is left to run and to publish."""

    fs: FrameSet
    stamp: int
    frame_id: str
    detector: Any = None  # the detector that prepared the frame finishes it
    prepared: Any = None  # its prepare() output; None: nothing left to run
    objects: list = field(default_factory=list)
    frame: Any = None  # the checked input (PreparedFrame); None: skipped
    detect_ms: float | None = None  # detector time so far; None: the detector did not succeed


class FrameScheduler:
    """The worker thread(s) of the node; see the module docstring."""

    def __init__(self, host: Any, pipeline: bool) -> None:
        self.host = host
        self.mailbox: LatestMailbox[FrameSet] = LatestMailbox()
        self.handoff: LatestMailbox[Job] | None = LatestMailbox() if pipeline else None
        self.rebuild = False
        self._running = True
        self.finisher: threading.Thread | None = None
        if self.handoff is not None:
            self.finisher = threading.Thread(target=self._finish_loop, name="shape_detector_finisher", daemon=True)
            self.finisher.start()
        self.worker = threading.Thread(target=self._work, name="shape_detector_worker", daemon=True)
        self.worker.start()

    def offer(self, fs: FrameSet) -> None:
        """Hand a set to the worker, replacing (and counting as dropped) one not yet taken."""
        self.host.stats.count("synced")
        self.mailbox.put(fs)  # a replaced set is counted in mailbox.dropped

    def _work(self) -> None:
        """First stage: input checks and the detector's pre-network work."""
        while self._running:
            try:
                # take a new frame only once the second stage has taken the last one, so
                # the frame prepared is the newest and waits for at most one other
                if self.handoff is not None and not self.handoff.wait_empty(timeout=0.2):
                    self.host.maybe_report()
                    continue
                fs = self.mailbox.get(timeout=0.2)
                if fs is not None and self._running:
                    try:
                        job = self.prepare(fs)
                        if self.handoff is None:
                            self.complete(job)
                        else:
                            self.handoff.put(job)
                    except Exception as e:  # noqa: BLE001 - the worker must survive anything
                        self._count_error(e)
                self.host.maybe_report()
            except Exception as e:  # noqa: BLE001
                print(f"[shape_detector] worker: {type(e).__name__}: {e}", file=sys.stderr)
                time.sleep(0.1)

    def _finish_loop(self) -> None:
        """Second stage: network, post-processing, publishing."""
        assert self.handoff is not None
        while self._running:
            job = self.handoff.get(timeout=0.2)
            if job is None or not self._running:
                continue
            try:
                self.complete(job)
            except Exception as e:  # noqa: BLE001 - the worker must survive anything
                self._count_error(e)

    def _count_error(self, e: Exception) -> None:
        self.host.stats.count("errors")
        self.host.warn("worker", f"frame processing failed: {type(e).__name__}: {e}", level="error")

    def _detector_failed(self, stamp: int, e: Exception) -> None:
        self.host.stats.count("detector_errors")
        self.host.warn("detector", f"detector failed on frame {stamp / 1e9:.3f}: {type(e).__name__}: {e}",
                       level="error")

    def _maybe_rebuild(self) -> None:
        if not self.rebuild:
            return
        self.rebuild = False
        try:
            old, self.host.detector = self.host.detector, self.host.build_detector()
        except Exception as e:  # noqa: BLE001
            self.host.warn("rebuild", f"cannot rebuild the detector, keeping the old one: {type(e).__name__}: {e}",
                           level="error", period=0.0)
        else:
            close_detector(old)

    def _frame(self, fs: FrameSet) -> Any:
        """The checked frame (PreparedFrame) or None when it is skipped (counted, warned)."""
        host = self.host
        info = fs.camera_info
        if info is None:
            # the executor may hand over image + depth before a camera_info that arrived
            # with them: give the first one a moment
            if not host.info_event.is_set():
                host.info_event.wait(0.1)
            info = host.camera_info()
        try:
            pf = prepare_frame(fs.image, fs.depth, info, depth_scale=float(host.p["depth_scale"]) or None,
                               size_mismatch=host.p["size_mismatch"], detections2d=fs.detections2d)
        except FrameError as e:
            host.stats.count(f"skipped_{e.kind}")
            if e.kind == "camera_info" and info is None:
                text = f"no camera_info received on {host.topic('camera_info')} yet: frame skipped"
            else:
                text = f"frame skipped: {e}"
            host.warn("skip:" + e.kind, text)
            return None
        for note in pf.notes:
            host.warn("note", note, period=30.0)
        if pf.valid_depth_fraction == 0.0:
            host.stats.count("skipped_no_depth")
            return None
        return pf

    def prepare(self, fs: FrameSet) -> Job:
        """Input checks and, for a usable frame, the detector's work up to the network (all
        of it without ``pipeline`` or when the detector has no ``prepare``/``finish``)."""
        self._maybe_rebuild()
        job = Job(fs, int(header_stamp_ns(fs.image) or 0), str(getattr(fs.image.header, "frame_id", "") or ""))
        if not job.frame_id:
            self.host.warn("frame_id", "colour image has an empty header.frame_id: markers will have no frame", 60.0)
        pf = job.frame = self._frame(fs)
        if pf is None:
            return job
        fs.up = self.host.frame_up(fs, job.stamp, job.frame_id)
        det = self.host.detector
        td = time.perf_counter()
        try:
            if self.handoff is not None and hasattr(det, "prepare") and hasattr(det, "finish"):
                job.prepared = det.prepare(pf.rgb, pf.depth, pf.K, boxes2d=pf.boxes2d, up=fs.up)
                job.detector = det
                share = self._first_pass_share(det) if hasattr(det, "first_pass") else 0.0
                if share > 0.0:
                    det.first_pass(job.prepared, share)
                    self.host.stats.count("first_pass_early")
            else:
                job.objects = list(det.detect(pf.rgb, pf.depth, pf.K, boxes2d=pf.boxes2d, up=fs.up))
        except Exception as e:  # noqa: BLE001
            self._detector_failed(job.stamp, e)
        else:
            job.detect_ms = (time.perf_counter() - td) * 1e3
        return job

    def _first_pass_share(self, det: Any) -> float:
        """The share of the frame's frustums whose first pass the first stage runs."""
        split = self.host.p["pipeline_split"]
        if split != "auto":
            return 1.0 if split == "network" else 0.0
        from .detector import first_pass_share

        return first_pass_share(getattr(det, "last_timing", None))

    def complete(self, job: Job) -> None:
        """The rest of the detector's work on ``job`` (if any), then publish and count."""
        if job.prepared is not None:
            td = time.perf_counter()
            try:
                job.objects = list(job.detector.finish(job.prepared))
            except Exception as e:  # noqa: BLE001
                job.objects, job.detect_ms = [], None
                self._detector_failed(job.stamp, e)
            else:
                job.detect_ms = (job.detect_ms or 0.0) + (time.perf_counter() - td) * 1e3
            job.prepared = None
        if not self._running:  # stopping: the publishers may be gone already
            return
        up = job.fs.up if job.fs.up is not None else getattr(job.detector or self.host.detector, "last_up", None)
        self.host.publish(job.objects, job.stamp, job.frame_id, job.frame, up)
        stamp_ms = (self.host.now_ns() - job.stamp) / 1e6 if job.stamp > 0 else None
        self.host.stats.frame_done(len(job.objects), stamp_ms, (time.monotonic() - job.fs.synced_at) * 1e3,
                                   job.detect_ms)

    def stop(self, timeout: float = JOIN_TIMEOUT_S) -> bool:
        """Stop the threads (idempotent); False if one is still running after ``timeout`` s."""
        self._running = False
        self.mailbox.close()
        if self.handoff is not None:
            self.handoff.close()
        deadline = time.monotonic() + timeout
        for t in (self.worker, self.finisher):
            if t is not None and t.is_alive() and threading.current_thread() is not t:
                t.join(timeout=max(0.0, deadline - time.monotonic()))
        return not any(t is not None and t.is_alive() for t in (self.worker, self.finisher))
