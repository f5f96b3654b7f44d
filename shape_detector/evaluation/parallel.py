"""Evaluation over walk-through seeds, in this process or in worker processes.

Each walk-through is rendered, detected and scored on its own, so the seeds of
``evaluate-scene`` and ``evaluate-ar`` can run in parallel: :func:`map_seeds` hands them to
``processes`` spawned workers (spawned, not forked: the parent may hold ONNX Runtime and
PyTorch thread pools), each building its own detector from the same configuration once.
Results come back in seed order.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

#: the detector of a worker process (built once by :func:`_init_worker`)
_DETECTOR: Any = None


def _init_worker(config: Any) -> None:
    global _DETECTOR
    if config is not None:
        from ..detector import ShapeDetector

        _DETECTOR = ShapeDetector(config)


def _call(fn: Callable[..., Any], seed: int, kwargs: dict[str, Any]) -> Any:
    return fn(seed, detector=_DETECTOR, **kwargs)


def map_seeds(fn: Callable[..., Any], seeds: Sequence[int], config: Any, processes: int = 1,
              local_detector: Any = None, **kwargs: Any) -> Iterator[Any]:
    """``fn(seed, detector=..., **kwargs)`` for each of ``seeds``, yielded in seed order.

    ``fn`` must be a module-level function (it is pickled to the workers). ``config``: the
    detector's :class:`~shape_detector.detector_config.DetectorConfig` (None: ``detector=None``,
    e.g. for the true map). ``processes`` <= 1: here, with ``local_detector`` or one built from
    ``config``; more: that many worker processes, each with its own detector (set the
    detector's ``workers`` / ``num_threads`` to fit the cores). A worker's failure is raised here.
    The workers are spawned, so a script that calls this with ``processes`` > 1 needs the
    ``if __name__ == "__main__":`` guard.
    """
    seeds = [int(s) for s in seeds]
    if processes <= 1 or len(seeds) <= 1:
        if local_detector is None and config is not None:
            from ..detector import ShapeDetector

            local_detector = ShapeDetector(config)
        for s in seeds:
            yield fn(s, detector=local_detector, **kwargs)
        return
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(min(processes, len(seeds)), mp_context=ctx, initializer=_init_worker,
                             initargs=(config,)) as pool:
        futures = [pool.submit(_call, fn, s, kwargs) for s in seeds]
        for f in futures:
            yield f.result()
