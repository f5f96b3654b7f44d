"""Detection in worker processes, so that frames in flight run in parallel for real.

Python threads share one interpreter lock: the numpy steps of two frames (gravity,
proposals, frustums, post-processing) take turns even on two cores, and only ONNX Runtime's
kernels overlap. :class:`ProcessDetector` keeps one detector per worker process (spawned,
never forked: the node's process holds ROS and ONNX Runtime threads) and offers the node's
scheduler the detector's two-step interface: :meth:`~ProcessDetector.prepare` hands a frame
to a free worker and returns at once, :meth:`~ProcessDetector.finish` waits for its objects.
With the node's ``pipeline`` the next frame is handed over while the current one finishes,
so two workers are busy and output stays in input order.

Frames travel to the workers through shared memory (one segment per frame, removed once its
objects are back): a 2 MB VGA colour + depth pair sent down the executor's pipe costs several
milliseconds, the copy a fraction of one. The objects come back pickled. A worker that dies is
replaced and the frames it held fail with an error; workers ignore Ctrl-C (the parent stops
them) and exit when the parent is killed outright.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from multiprocessing import get_context
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from .detector_config import DetectorConfig

log = logging.getLogger(__name__)

#: the detector of this worker process (None in the parent)
_DETECTOR: Any = None
#: seconds between two restarts of dead workers (frames in between fail)
RESTART_BACKOFF_S = 5.0
#: the dynamic settings this worker has applied (name -> value)
_APPLIED: dict[str, Any] = {}


def _start(config: DetectorConfig, factory: str, parent: int) -> None:
    """Worker initialiser: build and warm up this process's detector. Ctrl-C reaches the
    whole terminal's process group: the parent finishes the frames in flight and stops the
    workers, so they ignore it; a worker whose parent ``parent`` is gone (killed outright)
    exits."""
    global _DETECTOR
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # not SIGTERM: the executor stops broken pools with it
    threading.Thread(target=_exit_with_parent, args=(parent,), name="parent_watch", daemon=True).start()
    from .bags.detector_factory import make_detector
    from .node_params import DETECTOR_ATTRS

    _DETECTOR = make_detector(config, factory or None)
    if factory:  # as the node builds a custom detector: dynamic settings follow as attributes
        _apply(tuple((name, getattr(config, name)) for name in DETECTOR_ATTRS))
    if hasattr(_DETECTOR, "warm_up"):
        _DETECTOR.warm_up()


def _exit_with_parent(parent: int, period: float = 0.5) -> None:
    """Worker thread: end this process once ``parent`` is no longer its parent."""
    while os.getppid() == parent:
        time.sleep(period)
    os._exit(0)  # nothing to flush: the detector holds no state worth keeping


def _apply(changes: tuple[tuple[str, Any], ...]) -> None:
    from .node_params import apply_to_detector

    for name, value in changes:
        if _APPLIED.get(name, object()) != value:
            apply_to_detector(_DETECTOR, name, value)
            _APPLIED[name] = value


def _detect(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, boxes2d: Any, up: np.ndarray | None,
            changes: tuple[tuple[str, Any], ...]) -> tuple[list, np.ndarray | None, dict, float]:
    """Worker task: (objects, gravity up used, stage timing, detect ms) of one frame."""
    _apply(changes)
    t0 = time.perf_counter()
    objects = list(_DETECTOR.detect(rgb, depth, K, boxes2d=boxes2d, up=up))
    ms = 1e3 * (time.perf_counter() - t0)
    return objects, getattr(_DETECTOR, "last_up", None), dict(getattr(_DETECTOR, "last_timing", None) or {}), ms


def _detect_shared(name: str, rgb_spec: tuple, depth_spec: tuple, K: np.ndarray, boxes2d: Any,
                   up: np.ndarray | None, changes: tuple[tuple[str, Any], ...]) -> tuple[list, np.ndarray | None, dict, float]:
    """Worker task: :func:`_detect` of the colour and depth images in shared memory ``name``
    (``*_spec``: shape, dtype string; depth right after colour)."""
    shm = SharedMemory(name=name)
    try:
        rgb = np.ndarray(rgb_spec[0], np.dtype(rgb_spec[1]), buffer=shm.buf).copy()
        depth = np.ndarray(depth_spec[0], np.dtype(depth_spec[1]), buffer=shm.buf, offset=rgb.nbytes).copy()
    finally:
        shm.close()
    return _detect(rgb, depth, K, boxes2d, up, changes)


class _Segment:
    """One frame's shared memory (``rgb`` then ``depth``, C order), released once (the
    executor's callback thread and the waiting thread may both try)."""

    def __init__(self, rgb: np.ndarray, depth: np.ndarray) -> None:
        self.shm = SharedMemory(create=True, size=max(rgb.nbytes + depth.nbytes, 1))
        np.ndarray(rgb.shape, rgb.dtype, buffer=self.shm.buf)[...] = rgb
        np.ndarray(depth.shape, depth.dtype, buffer=self.shm.buf, offset=rgb.nbytes)[...] = depth
        self._lock = threading.Lock()
        self._released = False

    @property
    def name(self) -> str:
        return self.shm.name

    def release(self) -> None:
        with self._lock:  # held throughout: whoever comes second returns once it is gone
            if self._released:
                return
            self._released = True
            try:
                self.shm.unlink()  # the name first: it goes even while a view keeps the mapping
            except FileNotFoundError:
                pass
            try:
                self.shm.close()
            except BufferError:  # a view still open: the mapping goes with it
                pass


def _describe(hold_s: float) -> tuple[int, str, str | None, str | None]:
    """Worker task: (pid, detector type, backend, precision), after holding the worker
    ``hold_s`` seconds so that concurrent calls land on different workers."""
    time.sleep(hold_s)
    pred = getattr(_DETECTOR, "predictor", None)
    return os.getpid(), type(_DETECTOR).__name__, getattr(pred, "backend", None), getattr(pred, "precision", None)


def close_detector(det: Any) -> None:
    """Release a detector's resources (a ProcessDetector's workers) if it has any to release;
    never raises (shutting down must not fail on it)."""
    close = getattr(det, "close", None)
    if callable(close):
        try:
            close()
        except Exception as e:  # noqa: BLE001
            log.error("closing the detector: %s: %s", type(e).__name__, e)


@dataclass
class WorkerRuntime:
    """What the workers run (for the node's start-up log line)."""

    backend: str | None = None
    precision: str | None = None
    workers: int = 1


class ProcessDetector:
    """``processes`` detector processes behind a detector's interface (see the module doc).

    ``config``: the detector settings (each process runs one frame at a time, so its
    predictor uses one frustum worker thread); ``factory``: a ``'package.module:callable'``
    detector factory the workers build instead of ShapeDetector (empty: ShapeDetector).
    """

    def __init__(self, config: DetectorConfig, processes: int = 2, factory: str = "") -> None:
        if processes < 1:
            raise ValueError(f"processes must be >= 1, got {processes}")
        self.config = replace(config, workers=1)
        self.processes = int(processes)
        self.factory = factory
        self.last_up: np.ndarray | None = None
        self.last_timing: dict[str, Any] = {}
        self.last_detect_ms: float | None = None
        self.predictor = WorkerRuntime()
        self.worker_pids: list[int] = []
        self._changes: dict[str, Any] = {}
        self._restarted_at = -float("inf")
        self._pool = self._new_pool()

    @classmethod
    def started(cls, config: DetectorConfig, processes: int = 2, factory: str = "") -> ProcessDetector:
        """A ProcessDetector whose workers are up and warmed up (closed again if they fail)."""
        det = cls(config, processes, factory)
        try:
            det.warm_up()
        except BaseException:
            det.close()
            raise
        return det

    def _new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(self.processes, mp_context=get_context("spawn"), initializer=_start,
                                   initargs=(self.config, self.factory, os.getpid()))

    def warm_up(self) -> None:
        """Start every worker (each builds and warms up its detector) and wait for them;
        RuntimeError naming the cause when they cannot start (the workers print its traceback)."""
        try:
            futures = [self._pool.submit(_describe, 0.3) for _ in range(self.processes)]
            described = [f.result() for f in futures]
        except BrokenProcessPool as e:
            raise RuntimeError(f"the detector worker processes could not start ({e}); their error output "
                               "above says why") from None
        self.worker_pids = sorted({d[0] for d in described})
        _, _, backend, precision = described[0]
        self.predictor = WorkerRuntime(backend, precision)

    def configure(self, **changes: Any) -> None:
        """Change dynamic detector settings; each worker applies them before its next frame."""
        self.config = replace(self.config, **changes)  # unknown names raise TypeError here
        self._changes.update(changes)

    def prepare(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, boxes2d: Any = None,
                up: np.ndarray | None = None) -> Future:
        """Hand one frame to a worker (returns at once); :meth:`finish` waits for it."""
        rgb, depth = np.ascontiguousarray(rgb), np.ascontiguousarray(depth)
        changes = tuple(sorted(self._changes.items()))
        segment = _Segment(rgb, depth)
        try:
            job = self._pool.submit(_detect_shared, segment.name, (rgb.shape, rgb.dtype.str),
                                    (depth.shape, depth.dtype.str), K, boxes2d, up, changes)
        except BrokenProcessPool:
            segment.release()
            raise RuntimeError(f"a detector process had died; {self._restart()}") from None
        job.add_done_callback(lambda _: segment.release())  # also for frames never waited for
        setattr(job, "shared_memory", segment)  # noqa: B010 - finish() releases it before returning
        return job

    #: the offline replay's name for :meth:`prepare` (frames handed over, waited for in order)
    submit = prepare

    def finish(self, job: Future) -> list:
        """The objects of a frame handed over by :meth:`prepare` (camera optical frame)."""
        try:
            try:
                objects, up, timing, ms = job.result()
            finally:  # the done-callback may run only after this thread has woken
                if (segment := getattr(job, "shared_memory", None)) is not None:
                    segment.release()
        except BrokenProcessPool:
            raise RuntimeError(f"a detector process died; {self._restart()}") from None
        self.last_up, self.last_timing, self.last_detect_ms = up, timing, ms
        return objects

    def detect(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, boxes2d: Any = None,
               up: np.ndarray | None = None) -> list:
        """One frame, waited for."""
        return self.finish(self.prepare(rgb, depth, K, boxes2d=boxes2d, up=up))

    def _restart(self) -> str:
        """Replace the broken pool (at most every ``RESTART_BACKOFF_S``); what was done."""
        # a worker that dies at once again (a bad build, no memory) must not respawn every frame
        now = time.monotonic()
        if now - self._restarted_at < RESTART_BACKOFF_S:
            return "new workers were started moments ago"
        self._restarted_at = now
        log.error("a detector process died; starting new ones")
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = self._new_pool()
        self.worker_pids = []  # known again after the next warm_up()
        return "new workers are starting"

    def close(self, timeout: float = 5.0) -> None:
        """Stop the workers: frames not started are cancelled, a worker still busy after
        ``timeout`` s is killed (idempotent)."""
        processes = list((getattr(self._pool, "_processes", None) or {}).values())  # no public list; None once shut down
        self._pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + timeout
        for proc in processes:
            proc.join(max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                proc.kill()

    def __enter__(self) -> ProcessDetector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
