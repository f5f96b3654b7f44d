"""Message synchronisation and the node's latest-only hand-off, in plain Python (no rclpy).

:class:`ApproximateTimeSynchronizer` reproduces the Python ``message_filters``
``ApproximateTimeSynchronizer`` (ROS 2 Jazzy) algorithm, so the live node and the offline
replay pair messages identically:

* every input keeps a queue ``{stamp: message}`` of at most ``queue_size`` entries (a
  message with a stamp already queued replaces it; on overflow the oldest stamp goes);
* when a message arrives, the other queues' stamps within ``slop`` of its stamp are
  sorted by distance, and the first combination (in ``itertools.product`` order of
  those sorted lists, the new message fixed) whose spread ``max - min`` is within
  ``slop`` is emitted and removed from the queues; older unmatched messages stay until
  they fall out of their queue.

The one deliberate deviation: the spread test is ``<= slop`` (message_filters uses
``<``), so exactly equal stamps synchronise with ``slop = 0``. Stamps are integer
nanoseconds; ``slop`` is given in seconds like message_filters'.

:class:`LatestMailbox` is a one-slot, thread-safe hand-off between the callbacks that
produce synchronised sets and the worker that processes them: a newer set replaces an
unprocessed older one (which is counted as dropped), so the consumer never falls behind.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable, Sequence
from typing import Any, Generic, TypeVar

from msg_conversion.stamps import stamp_to_ns

T = TypeVar("T")

_NS = 1_000_000_000


def header_stamp_ns(msg: Any) -> int | None:
    """``msg.header.stamp`` in integer nanoseconds, or None when the message has no header.

    Works for rclpy and rosbags messages (``sec``/``nanosec``) and ROS 1 style stamps
    (``secs``/``nsecs``).
    """
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None or isinstance(stamp, (bool, int)):
        return None
    try:
        return stamp_to_ns(stamp)
    except TypeError:
        return None


class ApproximateTimeSynchronizer:
    """Pairs messages of ``num_inputs`` streams whose stamps lie within ``slop`` seconds.

    ``add(i, msg)`` feeds input ``i``; when it completes a set, the set (a tuple of
    messages in input order) is returned and passed to every registered callback.
    Messages without ``header.stamp`` are ignored (counted in ``headerless``) unless a
    ``stamp_ns`` is passed explicitly. Thread-safe.
    """

    def __init__(
        self,
        num_inputs: int,
        queue_size: int = 10,
        slop: float = 0.05,
        *,
        stamp_getter: Callable[[Any], int | None] = header_stamp_ns,
    ) -> None:
        if int(num_inputs) < 1:
            raise ValueError(f"num_inputs must be >= 1, got {num_inputs}")
        self.num_inputs = int(num_inputs)
        self._stamp_getter = stamp_getter
        self._lock = threading.Lock()
        self._queues: list[dict[int, Any]] = [{} for _ in range(self.num_inputs)]
        self._callbacks: list[Callable[..., Any]] = []
        self.queue_size = 1
        self.slop_ns = 0
        self.configure(queue_size=queue_size, slop=slop)
        #: counters: messages added per input, sets emitted, messages evicted by overflow,
        #: headerless messages ignored.
        self.added = [0] * self.num_inputs
        self.emitted = 0
        self.evicted = 0
        self.headerless = 0

    # --- configuration ---------------------------------------------------------------
    def configure(self, queue_size: int | None = None, slop: float | None = None) -> None:
        """Change queue size and/or slop (seconds); queued messages are kept (trimmed)."""
        with self._lock:
            if queue_size is not None:
                if int(queue_size) < 1:
                    raise ValueError(f"queue_size must be >= 1, got {queue_size}")
                self.queue_size = int(queue_size)
                for q in self._queues:
                    self._trim(q)
            if slop is not None:
                slop = float(slop)
                if not slop >= 0.0 or slop == float("inf"):
                    raise ValueError(f"slop must be a finite number of seconds >= 0, got {slop}")
                self.slop_ns = int(round(slop * _NS))

    @property
    def slop(self) -> float:
        """The slop, seconds."""
        return self.slop_ns / _NS

    def register_callback(self, callback: Callable[..., Any]) -> None:
        """``callback(*msgs)`` is called with every synchronised set (inside the lock-free
        part of :meth:`add`, in the adding thread)."""
        self._callbacks.append(callback)

    def clear(self) -> None:
        """Drop every queued message."""
        with self._lock:
            for q in self._queues:
                q.clear()

    def queued(self) -> list[int]:
        """Number of queued messages per input."""
        with self._lock:
            return [len(q) for q in self._queues]

    # --- the algorithm ---------------------------------------------------------------
    def _trim(self, q: dict[int, Any]) -> None:
        while len(q) > self.queue_size:
            del q[min(q)]
            self.evicted += 1

    def add(self, index: int, msg: Any, stamp_ns: int | None = None) -> tuple[Any, ...] | None:
        """Feed ``msg`` to input ``index``; returns the completed set or None."""
        if not 0 <= index < self.num_inputs:
            raise IndexError(f"input index {index} out of range 0..{self.num_inputs - 1}")
        stamp = self._stamp_getter(msg) if stamp_ns is None else int(stamp_ns)
        if stamp is None:
            self.headerless += 1
            return None
        result: tuple[Any, ...] | None = None
        with self._lock:
            self.added[index] += 1
            my_queue = self._queues[index]
            my_queue[stamp] = msg
            self._trim(my_queue)
            if stamp not in my_queue:  # evicted at once: older than a full queue
                return None
            others = [i for i in range(self.num_inputs) if i != index]
            candidates: list[list[int]] = []
            for i in others:
                near = [(s, abs(s - stamp)) for s in self._queues[i] if abs(s - stamp) <= self.slop_ns]
                if not near:
                    return None
                near.sort(key=lambda x: x[1])
                candidates.append([s for s, _ in near])
            for combo in itertools.product(*candidates):
                stamps = list(combo)
                stamps.insert(index, stamp)
                if max(stamps) - min(stamps) <= self.slop_ns:
                    result = tuple(self._queues[i][s] for i, s in enumerate(stamps))
                    for i, s in enumerate(stamps):
                        del self._queues[i][s]
                    self.emitted += 1
                    break
        if result is not None:
            for cb in list(self._callbacks):
                cb(*result)
        return result


class TimeSynchronizer(ApproximateTimeSynchronizer):
    """Exact-stamp synchroniser (message_filters' ``TimeSynchronizer``)."""

    def __init__(self, num_inputs: int, queue_size: int = 10, **kwargs: Any) -> None:
        super().__init__(num_inputs, queue_size, 0.0, **kwargs)


class LatestMailbox(Generic[T]):
    """A one-slot, thread-safe hand-off that keeps only the newest item.

    ``put`` never blocks: it replaces an item the consumer has not taken yet (returned,
    and counted in :attr:`dropped`). ``get`` blocks until an item is there, the timeout
    passes (None) or the mailbox is closed (None).
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._has_item = False
        self._closed = False
        self.put_count = 0
        self.taken = 0
        self.dropped = 0

    def put(self, item: T) -> T | None:
        """Store ``item``; returns the unprocessed item it replaced (or None)."""
        with self._cond:
            if self._closed:
                return None
            old = self._item if self._has_item else None
            if self._has_item:
                self.dropped += 1
            self._item, self._has_item = item, True
            self.put_count += 1
            self._cond.notify()
            return old

    def get(self, timeout: float | None = None) -> T | None:
        """Take the newest item (blocking up to ``timeout`` seconds; None = forever)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._has_item or self._closed, timeout=timeout):
                return None
            if not self._has_item:
                return None
            item, self._item, self._has_item = self._item, None, False
            self.taken += 1
            self._cond.notify_all()  # wake wait_empty()
            return item

    def wait_empty(self, timeout: float | None = None) -> bool:
        """Block until the slot is empty (its item taken) or the mailbox is closed; False
        when ``timeout`` seconds pass first. A producer that calls this before taking new
        work hands over one item at a time and never replaces one (a pipeline stage)."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._has_item or self._closed, timeout=timeout)

    def pending(self) -> bool:
        """True while an item waits to be taken."""
        with self._cond:
            return self._has_item

    def close(self) -> None:
        """Wake every waiting ``get`` (which then returns None); later puts are ignored."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called."""
        return self._closed


def synchronize_offline(
    stream: Sequence[tuple[int, Any]] | Any,
    num_inputs: int,
    queue_size: int = 10,
    slop: float = 0.05,
) -> list[tuple[Any, ...]]:
    """Convenience: feed ``(input_index, msg)`` pairs in order, return all sets."""
    sync = ApproximateTimeSynchronizer(num_inputs, queue_size, slop)
    out = []
    for index, msg in stream:
        s = sync.add(index, msg)
        if s is not None:
            out.append(s)
    return out
