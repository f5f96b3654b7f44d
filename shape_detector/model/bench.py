"""Network benchmark: ms per frame for a batched forward of 1, 5, 10 frustums.

``bench_network`` times :meth:`FrustumPredictor.predict` (one batched forward + decoding
+ primitive pruning) on synthetic frustums, then the network work of built-in proposals
(first pass, proposal classifier, class-given second pass); the network's cost does not
depend on the point values, so random points are fine. ``shape-detector bench network`` (the bench
module) calls it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..frustum import Frustum
from ..geometry import upright_rotation


def random_frustums(n: int, num_points: int, rng: np.random.Generator) -> list[Frustum]:
    """``n`` frustums of ``num_points`` random points shaped like a room ahead (frustum frame F,
    metres; colour in [0, 1]): inputs for timing and for comparing runtimes."""
    out = []
    for _ in range(n):
        pts = np.zeros((num_points, 6), np.float32)
        pts[:, 0] = rng.normal(0, 0.4, num_points)
        pts[:, 1] = rng.uniform(1.5, 4.0, num_points)
        pts[:, 2] = rng.normal(-0.5, 0.4, num_points)
        pts[:, 3:] = rng.random((num_points, 3))
        out.append(Frustum(pts, np.arange(num_points), num_points, 0.1, upright_rotation(None)))
    return out


def bench_network(
    counts: Sequence[int] = (1, 5, 10),
    weights: str | Path | None = None,
    device: str = "cpu",
    num_threads: int | None = 1,
    repeats: int = 20,
    warmup: int = 3,
    num_points: int | None = None,
    verbose: bool = True,
    threads: int | None = None,
    workers: int = 1,
    precision: str = "fp32",
    trace: bool = True,
    backend: str = "auto",
) -> dict:
    """Median / mean ms per frame (one batched ``predict`` of ``count`` frustums).

    ``workers``: threads the batch is split over (:class:`FrustumPredictor`); ``precision``
    'fp32' or 'bf16'; ``trace``: TorchScript graphs (default) or the eager forward;
    ``backend``: the predictor's (``auto``, ``onnxruntime``, ``torch``).
    Then the largest count once more beside a busy pure-Python thread, onnxruntime, traced and
    eager, one worker (``beside_python``): the node's other pipeline stage is such a thread for part of
    its time.

    ``threads`` is an alias of ``num_threads`` (used when not None).

    Returns ``{"device", "num_threads", "num_points", "results": {count: {"median_ms",
    "mean_ms", "fps", "cpu_ms"}}}`` and prints one line per count. ``cpu_ms`` is the
    process CPU time per frame: with one thread it stays meaningful on a busy machine,
    where wall-clock times are not.
    """
    import warnings

    from .predictor import FrustumPredictor

    if threads is not None:
        num_threads = threads
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pred = FrustumPredictor(
            weights, device=device, num_threads=num_threads, workers=workers, precision=precision, trace=trace,
            backend=backend,
        )
    dev = getattr(pred.device, "type", str(pred.device))
    n_pts = int(num_points or pred.num_points)
    rng = np.random.default_rng(0)
    results = {}
    for c in counts:
        fr = random_frustums(int(c), n_pts, rng)
        cls = [i % pred.config.num_classes for i in range(int(c))]
        times, cpu = _timed(lambda fr=fr, cls=cls: pred.predict(fr, cls), warmup, repeats,
                            dev == "cuda" and pred.backend == "torch")
        med = float(np.median(times))
        results[int(c)] = {"median_ms": med, "mean_ms": float(np.mean(times)), "fps": 1000.0 / med,
                           "cpu_ms": float(np.median(cpu))}
        if verbose:
            print(
                f"network: {c:3d} objects/frame  {med:7.2f} ms/frame (median of {repeats})  "
                f"{1000.0 / med:6.1f} frames/s  cpu {results[int(c)]['cpu_ms']:.1f} ms  "
                f"[{pred.backend}, {dev}, {num_threads} threads, {pred.workers} workers, {n_pts} pts, {pred.precision}, "
                f"{'traced' if trace else 'eager'}]"
            )
    builtin = _bench_builtin_path(pred, counts, n_pts, rng, repeats, warmup, verbose, trace)
    beside = {}
    if dev == "cpu":
        beside = _bench_beside_python(pred, counts, n_pts, rng, weights, device, precision, verbose)
    return {
        "builtin_path": builtin,
        "beside_python": beside,
        "device": dev,
        "backend": pred.backend,
        "num_threads": num_threads,
        "workers": pred.workers,
        "precision": pred.precision,
        "num_points": n_pts,
        "results": results,
    }


def _bench_beside_python(pred, counts: Sequence[int], n_pts: int, rng: np.random.Generator,
                         weights: str | Path | None, device: str, precision: str, verbose: bool) -> dict[str, float]:
    """Median ms per frame of the largest count beside a busy pure-Python thread, for a one-worker
    predictor per runtime (``onnxruntime``, ``traced``, ``eager``), as in the node's pipeline."""
    import warnings

    from .predictor import FrustumPredictor

    beside = {}
    c = int(max(counts))
    fr = random_frustums(c, n_pts, rng)
    cls = [i % pred.config.num_classes for i in range(c)]
    for name in ("onnxruntime", "traced", "eager"):  # one worker, as in the node's pipeline
        torch_precision = "fp32" if precision == "int8" else precision  # int8 graphs are onnxruntime's
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            p = FrustumPredictor(weights, device=device, workers=1, trace=name != "eager",
                                 precision=precision if name == "onnxruntime" else torch_precision,
                                 backend="onnxruntime" if name == "onnxruntime" else "torch")
        beside[name] = float(np.median(_beside_busy_python(lambda p=p: p.predict(fr, cls), warmup=2, repeats=3)))
    if verbose:
        print(f"network beside a busy pure-Python thread, {c} objects/frame, 1 worker: onnxruntime "
              f"{beside['onnxruntime']:.1f} ms, traced {beside['traced']:.1f} ms, "
              f"eager {beside['eager']:.1f} ms (the eager forward waits for the GIL at every op)")
    return beside


def _timed(run, warmup: int, repeats: int, cuda: bool) -> tuple[list[float], list[float]]:
    """Wall-clock and process-CPU milliseconds of ``repeats`` calls of ``run`` after
    ``warmup`` untimed ones (CUDA synchronised around each timed call when ``cuda``)."""
    for _ in range(warmup):
        run()
    wall, cpu = [], []
    sync = None
    if cuda:
        import torch

        sync = torch.cuda.synchronize
    for _ in range(repeats):
        if sync:
            sync()
        t0, c0 = time.perf_counter(), time.process_time()
        run()
        if sync:
            sync()
        wall.append((time.perf_counter() - t0) * 1000.0)
        cpu.append((time.process_time() - c0) * 1000.0)
    return wall, cpu


def _beside_busy_python(run, warmup: int, repeats: int) -> list[float]:
    """Wall-clock ms of ``repeats`` calls of ``run`` while another thread runs pure Python."""
    import threading

    stop = threading.Event()

    def spin() -> None:
        x = 0
        while not stop.is_set():
            for _ in range(1000):
                x += 1

    t = threading.Thread(target=spin, daemon=True)
    t.start()
    try:
        return _timed(run, warmup, repeats, False)[0]
    finally:
        stop.set()
        t.join()


def _bench_builtin_path(
    pred, counts, n_pts: int, rng, repeats: int, warmup: int, verbose: bool, trace: bool = True
) -> dict:
    """ms per frame of the network work on built-in proposals: the class-agnostic first pass,
    the packaged proposal classifier and the class-given second pass of every frustum (the
    detector's worst case: ``refine_min_score`` 0). Empty when no classifier is packaged."""
    from ..detector import DEFAULT_CLASSIFIER
    from .classifier_inputs import frame_inputs
    from .classifier_runtime import ClassifierPredictor

    if not DEFAULT_CLASSIFIER.is_file():
        return {}
    clf = ClassifierPredictor.from_file(DEFAULT_CLASSIFIER, pred.precision, trace, pred.backend)
    out = {}
    for c in counts:
        fr = random_frustums(int(c), n_pts, rng)

        def run(fr: list[Frustum] = fr) -> None:
            # as the detector: features reused below, shapes left to the second pass
            first = pred.predict(fr, [None] * len(fr), keep_features=True, shapes=False)
            clf.probabilities(*frame_inputs(fr, first, [(0, 0, 100, 100)] * len(fr), [1.0] * len(fr), (640, 480), 1.3,
                                            clf.config))
            pred.refine(fr, first)

        times, _ = _timed(run, warmup, repeats, False)
        med = float(np.median(times))
        out[int(c)] = {"median_ms": med, "fps": 1000.0 / med}
        if verbose:
            print(f"network, built-in path (first pass + classifier + class-given pass): {c:3d} objects/frame  "
                  f"{med:7.2f} ms/frame  {1000.0 / med:6.1f} frames/s")
    return out


if __name__ == "__main__":  # pragma: no cover
    bench_network()
