"""``shape-detector bench``: benchmarks that print numbers (never run by the unit tests).

Targets: ``synth`` (scene generator frames/s), ``network`` (batched forward ms/frame for 1,
5, 10 objects), ``proposals`` (gravity + geometric proposals ms per VGA frame),
``pipeline`` (whole ``ShapeDetector.detect`` on generated VGA frames, serial and as the
node's two-thread pipeline), ``node`` (ROS node
frames/s and stamp-to-publish latency on the sample bag), ``all``; and ``soak`` (the node
under ``--rate-factor`` times overload for ``--minutes``: RSS, counts, output order; not
part of ``all``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from .model.config import PRECISIONS

TARGETS = ("synth", "network", "proposals", "pipeline", "node")


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", choices=TARGETS + ("all", "soak"), help="what to time")
    p.add_argument("--minutes", type=float, default=10.0, help="soak: minutes under overload")
    p.add_argument("--rate-factor", type=float, default=2.0,
                   help="soak: frames offered per second as a multiple of what the node processes")
    p.add_argument("--frames", type=int, default=20, help="frames to time (synth, proposals, pipeline)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1, as the detector)")
    p.add_argument("--workers", type=int, default=2, help="threads the network splits a frame's frustums over (default 2, as the detector)")
    p.add_argument("--max-objects", type=int, default=25, help="pipeline: frustums per frame cap (default 25, as the detector)")
    p.add_argument("--precision", default="fp32", choices=PRECISIONS,
                   help="network arithmetic (bf16: faster on CPUs with AMX / AVX512-BF16; auto: bf16 for 4 or "
                        "more frustums where the CPU has AMX)")
    p.add_argument("--backend", default="auto", choices=("auto", "onnxruntime", "torch"),
                   help="network, pipeline: inference runtime (auto: onnxruntime when installed)")
    p.add_argument("--weights", default=None, help="weights for network/pipeline/node (default: packaged)")
    p.add_argument("--no-classifier", action="store_true", help="pipeline: without the proposal classifier")
    p.add_argument("--no-refine", action="store_true", help="pipeline: without the class-given second pass")
    p.add_argument("--no-free-space", action="store_true", help="pipeline: without free-space carving")
    p.add_argument("--no-trace", action="store_true",
                   help="network, pipeline: the eager forward instead of the TorchScript graphs")
    p.add_argument("--pipeline-split", default="auto", choices=("auto", "prepare", "network"),
                   help="pipeline: where the node's pipeline runs the network's first pass (its pipeline_split)")
    p.add_argument("--bag", default=str(Path(__file__).resolve().parents[1] / "bags" / "sample"))
    p.add_argument("--json", default=None, help="also write the results here")


def bench_pipeline(
    frames: int = 20,
    weights: str | None = None,
    threads: int | None = None,
    workers: int = 2,
    precision: str = "fp32",
    max_objects: int = 25,
    classifier: bool = True,
    refine: bool = True,
    pipeline_split: str = "auto",
    trace: bool = True,
    free_space: bool = True,
    backend: str = "auto",
) -> dict:
    """Median / p95 ms per VGA frame of ``ShapeDetector.detect`` with GT boxes and with built-in
    proposals, then the built-in throughput with the node's two-thread pipeline."""
    from .detector import ShapeDetector
    from .synth.generate import generate_frame

    det = ShapeDetector(
        weights=weights, score_threshold=0.0, num_threads=threads, workers=workers, precision=precision,
        max_objects=max_objects, classifier=classifier, refine=refine, trace=trace, free_space=free_space,
        backend=backend,
    )
    scenes = [generate_frame(10_000 + i) for i in range(frames)]
    det.warm_up()  # as the node does at start: the network's graphs are traced
    out: dict[str, dict] = {}
    for mode in ("gt_boxes", "builtin"):
        times, parts, nobj = [], [], []
        det.detect(scenes[0].rgb, scenes[0].depth, scenes[0].K)  # warm-up
        for f in scenes:
            boxes = [(*o.box2d, o.class_name) for o in f.objects] if mode == "gt_boxes" else None
            t0 = time.perf_counter()
            det.detect(f.rgb, f.depth, f.K, boxes2d=boxes)
            times.append(1e3 * (time.perf_counter() - t0))
            parts.append(det.last_timing)
            nobj.append(det.last_timing.get("num_frustums", 0))
        res = {
            "ms_p50": float(np.median(times)),
            "ms_p95": float(np.percentile(times, 95)),
            "fps_p50": float(1e3 / np.median(times)),
            "frustums_per_frame": float(np.mean(nobj)),
        }
        for key in ("proposals_ms", "frustums_ms", "network_ms", "classifier_ms", "refine_ms", "post_ms"):
            res[key + "_p50"] = float(np.median([p.get(key, 0.0) for p in parts]))
        out[mode] = res
        print(
            f"pipeline[{mode}]: {res['ms_p50']:.1f} ms/frame p50 ({res['fps_p50']:.1f} fps), p95 {res['ms_p95']:.1f} ms, "
            f"{res['frustums_per_frame']:.1f} frustums/frame; proposals {res['proposals_ms_p50']:.1f} ms, "
            f"frustums {res['frustums_ms_p50']:.1f} ms, network {res['network_ms_p50']:.1f} ms, "
            f"classifier {res['classifier_ms_p50']:.1f} ms, second pass {res['refine_ms_p50']:.1f} ms, "
            f"post {res['post_ms_p50']:.1f} ms",
            flush=True,
        )
    # as the node runs it: two stages, each single-threaded (workers=1: the stages keep both
    # cores busy; a third thread only contends for them)
    det.predictor.workers = 1
    res = _bench_pipelined(det, scenes, pipeline_split)
    det.predictor.workers = workers
    out["builtin_pipelined"] = res
    print(
        f"pipeline[builtin, node's 2-stage pipeline, workers=1]: {res['ms_per_frame']:.1f} ms/frame throughput "
        f"({res['fps']:.1f} fps); latency p50 {res['latency_ms_p50']:.1f} ms, p95 {res['latency_ms_p95']:.1f} ms; "
        f"first pass in the first stage for {100 * res['first_pass_early_share']:.0f}% of the frames "
        f"(pipeline_split {pipeline_split})",
        flush=True,
    )
    return out


def _bench_pipelined(det, scenes: list, split: str = "auto") -> dict:
    """Throughput and latency of built-in-proposal detection run as the node runs it with
    ``pipeline``: one thread runs ``prepare`` on frame N+1 while another runs ``finish`` on
    frame N; the first takes a frame once the second has taken the previous one, and a
    frame is always waiting (a camera faster than the detector, without the drops).
    ``split``: the node's ``pipeline_split``."""
    import threading

    from .detector import first_pass_early
    from .sync import LatestMailbox

    handoff: LatestMailbox = LatestMailbox()
    early: list[bool] = []
    latency: list[float] = []
    errors: list[BaseException] = []

    def first() -> None:
        try:
            for f in scenes:
                handoff.wait_empty()
                if handoff.closed:  # the second stage failed
                    return
                t0 = time.perf_counter()
                prepared = det.prepare(f.rgb, f.depth, f.K)
                early.append(first_pass_early(det.last_timing) if split == "auto" else split == "network")
                if early[-1]:  # as the node's pipeline_split
                    det.first_pass(prepared)
                handoff.put((t0, prepared))
            handoff.wait_empty()
        except BaseException as e:  # noqa: BLE001 - re-raised by the caller's thread
            errors.append(e)
        finally:
            handoff.close()

    def second() -> None:
        try:
            while (item := handoff.get()) is not None:
                det.finish(item[1])
                latency.append(1e3 * (time.perf_counter() - item[0]))
        except BaseException as e:  # noqa: BLE001
            errors.append(e)
            handoff.close()

    det.finish(det.prepare(scenes[0].rgb, scenes[0].depth, scenes[0].K))  # warm-up
    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    ms = 1e3 * (time.perf_counter() - t0) / len(scenes)
    return {
        "ms_per_frame": float(ms),
        "fps": float(1e3 / ms),
        "latency_ms_p50": float(np.median(latency)),
        "latency_ms_p95": float(np.percentile(latency, 95)),
        "first_pass_early_share": float(np.mean(early)),
    }


def run_target(target: str, args: argparse.Namespace) -> dict:
    """Run one benchmark and return its numbers."""
    if target == "synth":
        from .synth.bench import bench_synth

        return bench_synth(frames=args.frames)
    if target == "network":
        from .model.bench import bench_network

        return bench_network(
            weights=args.weights, threads=args.threads, workers=args.workers, precision=args.precision,
            trace=not args.no_trace, backend=args.backend,
        )
    if target == "proposals":
        from .proposals.bench import bench_proposals

        return bench_proposals(frames=args.frames)
    if target == "pipeline":
        return bench_pipeline(
            frames=args.frames, weights=args.weights, threads=args.threads, workers=args.workers,
            precision=args.precision, max_objects=args.max_objects, classifier=not args.no_classifier,
            refine=not args.no_refine, pipeline_split=args.pipeline_split, trace=not args.no_trace,
            free_space=not args.no_free_space, backend=args.backend,
        )
    if target == "node":
        from .node_bench import bench_node

        return bench_node(args.bag, weights=args.weights)
    if target == "soak":
        from .soak import print_soak, soak

        res = soak(args.minutes, args.rate_factor, args.bag, node_params={"weights": args.weights} if args.weights else None)
        print_soak(res)
        return res
    raise ValueError(target)


def main(args: argparse.Namespace) -> int:
    targets = TARGETS if args.target == "all" else (args.target,)
    results = {}
    for t in targets:
        print(f"== bench {t}", flush=True)
        results[t] = run_target(t, args)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0 if results.get("soak", {}).get("ok", True) else 1
