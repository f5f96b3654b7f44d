"""The live node's bookkeeping without ROS: rate-limited warnings per distinct problem,
latency statistics robust to clocks that jump, and the periodic statistics line.

Times: ``now`` arguments are ``time.monotonic()`` seconds; latencies are milliseconds.
"""

from __future__ import annotations

import re
import threading
from collections import Counter, OrderedDict, deque
from typing import Any

import numpy as np

#: a stamp->publish latency outside [0, this] ms comes from a clock that jumped, a
#: restamped or replayed source, or simulated time: counted, not averaged in
MAX_PLAUSIBLE_LATENCY_MS = 60_000.0

_NUMBER = re.compile(r"0x[0-9a-fA-F]+|[-+]?\d+(\.\d+)?(e[-+]?\d+)?")


def problem_key(kind: str, text: str) -> str:
    """The identity of a warning: its kind plus its text with numbers (and hex addresses)
    blanked, so that the same problem on another frame (other stamp, count, size or object)
    is one key and a different topic or reason is another."""
    return kind + "|" + _NUMBER.sub("#", text)


class WarningLimiter:
    """Decides which warnings to print: each distinct problem at once the first time, then
    at most once per ``period`` seconds with the count of repeats held back. Remembers at
    most ``max_keys`` problems (the least recently seen are forgotten)."""

    def __init__(self, max_keys: int = 512) -> None:
        self._seen: OrderedDict[str, tuple[float, int]] = OrderedDict()
        self._max_keys = max_keys
        self._lock = threading.Lock()

    def admit(self, key: str, now: float, period: float) -> int | None:
        """None: hold this one back; else the number of repeats held back since the last
        report of ``key`` (``now``, ``period``: seconds)."""
        with self._lock:
            last, held = self._seen.get(key, (float("-inf"), 0))
            self._seen[key] = (last, held)
            self._seen.move_to_end(key)
            if now - last < period:
                self._seen[key] = (last, held + 1)
                return None
            self._seen[key] = (now, 0)
            while len(self._seen) > self._max_keys:
                self._seen.popitem(last=False)
            return held


def percentiles(values: list[float] | deque) -> tuple[float, float] | None:
    """(p50, p95) of ``values``; None when empty."""
    if not values:
        return None
    a = np.asarray(values, dtype=np.float64)
    return float(np.percentile(a, 50)), float(np.percentile(a, 95))


class NodeStats:
    """Counters and latency windows of the live node (thread safe).

    ``stamp_ms``: header stamp -> publish on the node's clock, kept only when plausible
    (``0 <= ms <= MAX_PLAUSIBLE_LATENCY_MS``; others counted as ``implausible_stamps``);
    ``pipeline_ms``: synchronisation -> publish on the monotonic clock (always valid);
    ``detect_ms``: detector time."""

    def __init__(self, window: int = 2000) -> None:
        self.lock = threading.Lock()
        self.counters: Counter = Counter()
        self.stamp_ms: deque[float] = deque(maxlen=window)
        self.pipeline_ms: deque[float] = deque(maxlen=window)
        self.detect_ms: deque[float] = deque(maxlen=window)
        self.period_processed = 0

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to counter ``name``."""
        with self.lock:
            self.counters[name] += n

    def frame_done(self, n_objects: int, stamp_latency_ms: float | None, pipeline_ms: float,
                   detect_ms: float | None) -> None:
        """Record one processed frame (latencies in ms; None: unknown)."""
        with self.lock:
            self.counters["processed"] += 1
            self.counters["objects"] += n_objects
            self.period_processed += 1
            if stamp_latency_ms is not None:
                if 0.0 <= stamp_latency_ms <= MAX_PLAUSIBLE_LATENCY_MS:
                    self.stamp_ms.append(stamp_latency_ms)
                else:
                    self.counters["implausible_stamps"] += 1
            if 0.0 <= pipeline_ms <= MAX_PLAUSIBLE_LATENCY_MS:
                self.pipeline_ms.append(pipeline_ms)
            if detect_ms is not None:
                self.detect_ms.append(detect_ms)

    def take_period(self) -> int:
        """Frames processed since the last call."""
        with self.lock:
            n, self.period_processed = self.period_processed, 0
        return n

    def snapshot(self) -> dict[str, Any]:
        """Counters plus ``latency_*`` (stamp), ``pipeline_*``, ``detect_*`` p50/p95 in ms."""
        with self.lock:
            out: dict[str, Any] = dict(self.counters)
            series = {"latency": list(self.stamp_ms), "pipeline": list(self.pipeline_ms),
                      "detect": list(self.detect_ms)}
        for key, vals in series.items():
            p = percentiles(vals)
            if p is not None:
                out[f"{key}_p50_ms"], out[f"{key}_p95_ms"] = p
        return out


def stats_line(s: dict[str, Any], frames_per_s: float) -> str:
    """The periodic log line from a :meth:`NodeStats.snapshot` (plus ``dropped``)."""
    skipped = sum(v for k, v in s.items() if k.startswith("skipped_"))
    line = (
        f"{frames_per_s:.1f} frames/s; totals: {s.get('synced', 0)} synced, {s.get('processed', 0)} processed, "
        f"{s.get('dropped', 0)} dropped (busy), {skipped} skipped (bad input), "
        f"{s.get('detector_errors', 0)} detector errors"
    )
    if "latency_p50_ms" in s:
        line += f"; latency stamp->publish p50 {s['latency_p50_ms']:.0f} ms, p95 {s['latency_p95_ms']:.0f} ms"
    elif "pipeline_p50_ms" in s:
        line += f"; latency sync->publish p50 {s['pipeline_p50_ms']:.0f} ms, p95 {s['pipeline_p95_ms']:.0f} ms"
    if s.get("implausible_stamps"):
        line += (f" ({s['implausible_stamps']} frames with stamps in the future or over "
                 f"{MAX_PLAUSIBLE_LATENCY_MS / 1000:.0f} s old not counted)")
    if "detect_p50_ms" in s:
        line += f"; detector p50 {s['detect_p50_ms']:.0f} ms"
    return line
