"""Spin nodes of an in-process ROS test on a background executor (shared by the ROS tests)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterable, Iterator
from typing import Any


@contextlib.contextmanager
def spinning(context: Any, nodes: Iterable[Any], publishers: Iterable[Any] = (), timeout: float = 10.0) -> Iterator[None]:
    """Spin ``nodes`` on one executor thread of ``context``; first wait (up to ``timeout`` s)
    until each of ``publishers`` has a subscriber. On exit: stop the executor, join its thread
    and destroy the nodes."""
    from rclpy.executors import SingleThreadedExecutor

    nodes = list(nodes)
    executor = SingleThreadedExecutor(context=context)
    for n in nodes:
        executor.add_node(n)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    pubs = list(publishers)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not all(p.get_subscription_count() for p in pubs):
        time.sleep(0.05)
    try:
        yield
    finally:
        executor.shutdown(timeout_sec=2.0)
        thread.join(timeout=5)
        for n in nodes:
            n.destroy_node()
