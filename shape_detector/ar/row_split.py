"""Row-split calls of compiled (numba ``nogil``) kernels over the cores this process may use.

A batch of rays is independent row by row, so a kernel that releases the GIL and writes only
its own rows runs on two halves at once, one per core: about half the time for a large batch.
Small batches run in the calling thread (the hand-over costs about as much as they do).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from ..model.devices import usable_cores

#: rows below which a batch runs in the calling thread
MIN_ROWS = 128

_pool: ThreadPoolExecutor | None = None
_pool_pid = 0


def run_rows(fn: Callable[[int, int], None], n: int, min_rows: int | None = None) -> None:
    """Call ``fn(start, stop)`` so that the calls cover rows ``[0, n)``: in the calling thread
    and one pool thread, half each, when ``n >= min_rows`` (default :data:`MIN_ROWS`) and two or
    more cores are usable; else once. ``fn`` must release the GIL to gain, and must write only its rows."""
    global _pool, _pool_pid
    if n < max(2, MIN_ROWS if min_rows is None else min_rows) or usable_cores() < 2:
        fn(0, n)
        return
    if _pool is None or _pool_pid != os.getpid():  # a forked child has no pool thread
        _pool, _pool_pid = ThreadPoolExecutor(1, thread_name_prefix="ar-rows"), os.getpid()
    half = n // 2
    other = _pool.submit(fn, half, n)
    try:
        fn(0, half)
    finally:
        other.result()
