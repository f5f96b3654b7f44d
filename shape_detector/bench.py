"""``shape-detector bench``: benchmarks that print numbers (whose timings no unit test asserts).

Targets: ``synth`` (scene generator frames/s), ``network`` (batched forward ms/frame for 1,
5, 10 objects), ``proposals`` (gravity + geometric proposals ms per VGA frame, and the default
built-in proposer's whole call),
``pipeline`` (whole ``ShapeDetector.detect`` on generated VGA frames, serial and as the
node's two-thread pipeline and its detector processes), ``node`` (ROS node
frames/s and stamp-to-publish latency on the sample bag), ``all``; and ``soak`` (the node
under ``--rate-factor`` times overload for ``--minutes``: RSS, counts, output order; not
part of ``all``).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from .model.config import PRECISIONS
from .detector_config import BUILTIN_PROPOSAL_SOURCES

TARGETS = ("synth", "network", "proposals", "pipeline", "node")
#: frames the node's pipeline is timed over (the serial frames repeated): enough for a steady state
PIPELINE_FRAMES = 60


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Options of ``shape-detector bench``."""
    p.add_argument("target", choices=TARGETS + ("all", "soak"), help="what to time")
    p.add_argument("--minutes", type=float, default=10.0, help="soak: minutes under overload")
    p.add_argument("--rate-factor", type=float, default=2.0,
                   help="soak: frames offered per second as a multiple of what the node processes")
    p.add_argument("--frames", type=int, default=20, help="frames to time (synth, proposals, pipeline)")
    p.add_argument("--data", default=None,
                   help="pipeline: a synthetic shard directory to take the frames from (default: generated)")
    p.add_argument("--threads", type=int, default=None,
                   help="network intra-op threads (default: the realtime preset's num_threads)")
    p.add_argument("--workers", type=int, default=None,
                   help="threads the network splits a frame's frustums over (default: the realtime preset's)")
    p.add_argument("--max-objects", type=int, default=None,
                   help="pipeline: frustums per frame cap (default: the realtime preset's)")
    p.add_argument("--score-threshold", type=float, default=None,
                   help="pipeline: published score threshold (default: the realtime preset's)")
    p.add_argument("--precision", default=None, choices=PRECISIONS,
                   help="network arithmetic (default: the realtime preset's; bf16: faster on CPUs with AMX / "
                        "AVX512-BF16)")
    p.add_argument("--backend", default="auto", choices=("auto", "onnxruntime", "torch"),
                   help="network, pipeline: inference runtime (auto: onnxruntime when installed)")
    p.add_argument("--weights", default=None, help="weights for network/pipeline/node (default: packaged)")
    p.add_argument("--device", default=None,
                   help="network, pipeline: compute device (cpu, cuda, cuda:N, auto; default: the realtime preset's)")
    p.add_argument("--no-classifier", action="store_true", help="pipeline: without the proposal classifier")
    p.add_argument("--no-refine", action="store_true", help="pipeline: without the class-given second pass")
    p.add_argument("--no-free-space", action="store_true", help="pipeline: without free-space carving")
    p.add_argument("--no-peer", action="store_true",
                   help="pipeline: skip the F-PointNet v1 reference forward (it imports torch)")
    p.add_argument("--no-trace", action="store_true",
                   help="network, pipeline: the eager forward instead of the TorchScript graphs")
    p.add_argument("--pipeline-split", default="auto", choices=("auto", "prepare", "network"),
                   help="pipeline: where the node's pipeline runs the network's first pass (its pipeline_split)")
    p.add_argument("--against", default=None, choices=PRECISIONS,
                   help="pipeline: also time detect() in this precision, alternating frames with --precision "
                        "in one process (a paired comparison that the VM's drift does not bias)")
    p.add_argument("--gravity", default="estimate", choices=("estimate", "given"),
                   help="pipeline: estimate gravity per frame (default) or give each frame's true up, as a node "
                        "with a camera pose does (up_source auto)")
    p.add_argument("--proposal-source", default=None, choices=BUILTIN_PROPOSAL_SOURCES,
                   help="pipeline: built-in 2D proposals (default: the realtime preset's)")
    p.add_argument("--frustum-points", type=int, default=None,
                   help="pipeline: points per frustum (default: the realtime preset's, 0 = the network's count)")
    p.add_argument("--processes", type=int, default=2,
                   help="pipeline: also time the node's pipeline with this many detector processes (0: not)")
    p.add_argument("--bag", default=str(Path(__file__).resolve().parents[1] / "bags" / "sample"))
    p.add_argument("--json", default=None, help="also write the results here")


def given_boxes(frame, count: int = 10, seed: int = 0) -> list[tuple]:
    """``count`` given 2D boxes with classes for ``frame``: its GT boxes, then copies of them
    with each edge moved by up to 8 px (a detector's boxes around the same objects)."""
    base = [(*o.box2d, o.class_name) for o in frame.objects]
    if not base:
        return []
    rng = np.random.default_rng(seed)
    out = list(base[:count])
    while len(out) < count:
        x1, y1, x2, y2, c = base[len(out) % len(base)]
        d = rng.uniform(-8.0, 8.0, 4)
        out.append((x1 + d[0], y1 + d[1], x2 + d[2], y2 + d[3], c))
    return out


def _pipeline_frames(frames: int, data: str | None) -> list:
    """``frames`` VGA frames: the first of a shard directory, else generated (seeds 10000+)."""
    if data:
        import itertools

        from .synth.dataset import iter_frames

        return list(itertools.islice(iter_frames(data), max(1, frames)))
    from .synth.generate import generate_frame

    return [generate_frame(10_000 + i) for i in range(max(1, frames))]


def bench_pipeline(
    frames: int = 20,
    weights: str | None = None,
    threads: int | None = None,
    workers: int | None = None,
    precision: str | None = None,
    max_objects: int | None = None,
    classifier: bool = True,
    refine: bool = True,
    pipeline_split: str = "auto",
    trace: bool = True,
    free_space: bool = True,
    backend: str = "auto",
    score_threshold: float | None = None,
    data: str | None = None,
    peer: bool = True,
    against: str | None = None,
    processes: int = 2,
    device: str | None = None,
    gravity: str = "estimate",
    proposal_source: str | None = None,
    frustum_points: int | None = None,
) -> dict:
    """Median / p95 ms per VGA frame of serial ``ShapeDetector.detect`` (the realtime preset;
    arguments that are not None change its settings) with GT boxes (``gt_boxes``), with 10
    given boxes (``given10``, :func:`given_boxes`) and with built-in proposals
    (``builtin``), the F-PointNet v1 forward of 10 x 1024 points in PyTorch beside it
    (``peer``: :mod:`.model.fpointnet_v1`), then the built-in throughput with the node's
    two-thread pipeline, and in ``processes`` worker processes (0: not timed). ``against``:
    another precision, timed alternately with this one on the same frames
    (:func:`_bench_paired`). ``gravity``: ``estimate`` per frame or ``given`` (each frame's
    true up, as the node gets it from a camera pose)."""
    from .detector import ShapeDetector
    from .detector_config import resolved_workers

    overrides = dict(
        precision=precision, weights=weights, score_threshold=score_threshold, num_threads=threads, workers=workers,
        max_objects=max_objects, classifier=None if classifier else False, refine=refine, trace=trace,
        free_space=free_space, backend=backend, device=device, proposal_source=proposal_source,
        frustum_points=frustum_points,
    )
    det = ShapeDetector(**{k: v for k, v in overrides.items() if v is not None})
    scenes = _pipeline_frames(frames, data)
    det.warm_up()  # as the node does at start: the network's graphs are traced
    cfg = det.config
    print(f"pipeline: {len(scenes)} VGA frames, backend {det.predictor.backend} on {det.predictor.device}, precision {det.predictor.precision}, "
          f"max_objects {cfg.max_objects}, {det.num_points} points a frustum, workers {det.predictor.workers} ({cfg.workers or 'auto'}), threads {cfg.num_threads}, "
          f"score_threshold {cfg.score_threshold}, gravity {gravity}, proposals {cfg.proposal_source}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs",
          flush=True)
    out: dict[str, dict] = {}
    given_up = gravity == "given"
    for mode in ("gt_boxes", "given10", "builtin"):
        out[mode] = _bench_mode(det, scenes, mode, given_up)
    if against is not None:
        other = ShapeDetector(**{**{k: v for k, v in overrides.items() if v is not None}, "precision": against})
        other.warm_up()
        for mode in ("given10", "builtin"):
            out[f"paired_{mode}"] = _bench_paired(det, other, scenes, mode)
    if peer:
        from .model.fpointnet_v1 import time_fpointnet_v1

        v1 = time_fpointnet_v1(batch=10, num_points=1024, threads=max(1, cfg.num_threads))
        g10 = out["given10"]
        v1["ratio_to_given10"] = v1["ms_p50"] / g10["ms_p50"]
        v1["cpu_ratio_to_given10"] = v1["cpu_ms_p50"] / g10["cpu_ms_p50"]
        out["fpointnet_v1"] = v1
        print(f"peer: F-PointNet v1 forward, 10 x 1024 points, PyTorch, {v1['threads']} thread(s): "
              f"{v1['ms_p50']:.1f} ms (cpu {v1['cpu_ms_p50']:.1f} ms) = {v1['ratio_to_given10']:.1f}x "
              f"(cpu {v1['cpu_ratio_to_given10']:.1f}x) our detect() with 10 given boxes", flush=True)
    # as the node runs it: two stages, the network split over the workers the node resolves
    node_workers = resolved_workers(cfg.workers, pipelined=True)
    if node_workers != det.predictor.workers:
        det = ShapeDetector(**{k: v for k, v in overrides.items() if v is not None and k != "workers"},
                            workers=node_workers)
        det.warm_up()
    # a node runs for hours: its throughput is the steady state over more frames than the serial rows time
    stream = (scenes * -(-PIPELINE_FRAMES // len(scenes)))[:max(PIPELINE_FRAMES, len(scenes))]
    res = _bench_pipelined(det, stream, pipeline_split, given_up)
    out["builtin_pipelined"] = res
    print(
        f"pipeline[builtin, node's 2-stage pipeline, workers={node_workers}, {len(stream)} frames]: "
        f"{res['ms_per_frame']:.1f} ms/frame steady throughput "
        f"({res['fps']:.1f} fps); latency p50 {res['latency_ms_p50']:.1f} ms, p95 {res['latency_ms_p95']:.1f} ms; "
        f"the first stage ran {100 * res['first_pass_share']:.0f}% of the first pass "
        f"(pipeline_split {pipeline_split})",
        flush=True,
    )
    if processes > 0:
        from .process_detector import ProcessDetector

        with ProcessDetector.started(det.config, processes) as pool:
            res = _bench_pipelined(pool, stream, given_up=given_up)
        out["builtin_processes"] = res
        print(f"pipeline[builtin, node's pipeline, detector_processes={processes}]: {res['ms_per_frame']:.1f} ms/frame "
              f"steady throughput ({res['fps']:.1f} fps); latency p50 {res['latency_ms_p50']:.1f} ms, "
              f"p95 {res['latency_ms_p95']:.1f} ms", flush=True)
    return out


def _bench_mode(det, scenes: list, mode: str, given_up: bool = False) -> dict:
    """Median / p95 wall and CPU ms per frame of serial ``det.detect`` on ``scenes`` with the
    boxes of ``mode`` (``gt_boxes``, ``given10`` or ``builtin``: none) and the frames' true up
    when ``given_up`` (else estimated), and the median ms of each stage; prints one line."""
    times, cpu, parts, nobj = [], [], [], []
    det.detect(scenes[0].rgb, scenes[0].depth, scenes[0].K)  # warm-up
    for f in scenes:
        boxes = {"gt_boxes": [(*o.box2d, o.class_name) for o in f.objects], "given10": given_boxes(f),
                 "builtin": None}[mode]
        t0, c0 = time.perf_counter(), time.process_time()
        det.detect(f.rgb, f.depth, f.K, boxes2d=boxes, up=f.up if given_up else None)
        times.append(1e3 * (time.perf_counter() - t0))
        cpu.append(1e3 * (time.process_time() - c0))
        parts.append(det.last_timing)
        nobj.append(det.last_timing.get("num_frustums", 0))
    res = {
        "ms_p50": float(np.median(times)),
        "ms_p95": float(np.percentile(times, 95)),
        "fps_p50": float(1e3 / np.median(times)),
        "cpu_ms_p50": float(np.median(cpu)),
        "frustums_per_frame": float(np.mean(nobj)),
    }
    for key in ("proposals_ms", "frustums_ms", "network_ms", "classifier_ms", "refine_ms", "post_ms"):
        res[key + "_p50"] = float(np.median([p.get(key, 0.0) for p in parts]))
    print(
        f"pipeline[{mode}]: {res['ms_p50']:.1f} ms/frame p50 ({res['fps_p50']:.1f} fps), p95 {res['ms_p95']:.1f} ms, "
        f"cpu {res['cpu_ms_p50']:.1f} ms, "
        f"{res['frustums_per_frame']:.1f} frustums/frame; proposals {res['proposals_ms_p50']:.1f} ms, "
        f"frustums {res['frustums_ms_p50']:.1f} ms, network {res['network_ms_p50']:.1f} ms, "
        f"classifier {res['classifier_ms_p50']:.1f} ms, second pass {res['refine_ms_p50']:.1f} ms, "
        f"post {res['post_ms_p50']:.1f} ms",
        flush=True,
    )
    return res


def _bench_paired(det, other, scenes: list, mode: str) -> dict:
    """``det`` and ``other`` timed on each of ``scenes`` in turn (boxes of ``mode``: ``given10``
    or ``builtin``): medians and the median per-frame ratio ``det / other``; prints one line."""
    times: dict[str, list[float]] = {"a": [], "b": []}
    net: dict[str, list[float]] = {"a": [], "b": []}
    for f in scenes:
        boxes = given_boxes(f) if mode == "given10" else None
        for key, d in (("a", det), ("b", other)):
            t0 = time.perf_counter()
            d.detect(f.rgb, f.depth, f.K, boxes2d=boxes)
            times[key].append(1e3 * (time.perf_counter() - t0))
            net[key].append(d.last_timing.get("network_ms", 0.0) + d.last_timing.get("refine_ms", 0.0))
    ratio = float(np.median(np.asarray(times["a"]) / np.asarray(times["b"])))
    res = {"ms_p50": float(np.median(times["a"])), "other_ms_p50": float(np.median(times["b"])),
           "network_ms_p50": float(np.median(net["a"])), "other_network_ms_p50": float(np.median(net["b"])),
           "ratio": ratio}
    print(f"paired[{mode}]: precision {det.predictor.precision} {res['ms_p50']:.1f} ms (network "
          f"{res['network_ms_p50']:.1f} ms) against {other.predictor.precision} {res['other_ms_p50']:.1f} ms "
          f"(network {res['other_network_ms_p50']:.1f} ms): {ratio:.3f}x, median of per-frame ratios", flush=True)
    return res


def _bench_pipelined(det, scenes: list, split: str = "auto", given_up: bool = False) -> dict:
    """Throughput and latency of built-in-proposal detection run as the node runs it with
    ``pipeline``: one thread runs ``prepare`` on frame N+1 while another runs ``finish`` on
    frame N; the first takes a frame once the second has taken the previous one, and a
    frame is always waiting (a camera faster than the detector, without the drops).
    ``split``: the node's ``pipeline_split``. The throughput is the steady state a running
    node delivers: the time from the first frame's output to the last's over the frames
    between (the pipeline's one-off fill left out). ``given_up``: the frames' true up, else estimated."""
    import threading

    from .detector import first_pass_share
    from .sync import LatestMailbox

    handoff: LatestMailbox = LatestMailbox()
    early: list[float] = []
    latency: list[float] = []
    done: list[float] = []
    errors: list[BaseException] = []

    def first() -> None:
        try:
            for f in scenes:
                handoff.wait_empty()
                if handoff.closed:  # the second stage failed
                    return
                t0 = time.perf_counter()
                prepared = det.prepare(f.rgb, f.depth, f.K, up=f.up if given_up else None)
                share = first_pass_share(det.last_timing) if split == "auto" else float(split == "network")
                share *= hasattr(det, "first_pass")  # worker processes run whole frames
                early.append(share)  # as the node's pipeline_split
                if share > 0.0:
                    det.first_pass(prepared, share)
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
                done.append(time.perf_counter())
                latency.append(1e3 * (done[-1] - item[0]))
        except BaseException as e:  # noqa: BLE001
            errors.append(e)
            handoff.close()

    det.finish(det.prepare(scenes[0].rgb, scenes[0].depth, scenes[0].K))  # warm-up
    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    if len(done) < 2:
        raise ValueError("the pipelined benchmark needs at least 2 frames")
    ms = 1e3 * (done[-1] - done[0]) / (len(done) - 1)
    return {
        "ms_per_frame": float(ms),
        "fps": float(1e3 / ms),
        "latency_ms_p50": float(np.median(latency)),
        "latency_ms_p95": float(np.percentile(latency, 95)),
        "first_pass_share": float(np.mean(early)),
    }


def run_target(target: str, args: argparse.Namespace) -> dict:
    """Run one benchmark and return its numbers."""
    if target == "synth":
        from .synth.bench import bench_synth

        return bench_synth(frames=args.frames)
    if target == "network":
        from .model.bench import bench_network

        return bench_network(
            weights=args.weights, threads=1 if args.threads is None else args.threads, workers=args.workers or 1,
            precision=args.precision or "fp32", trace=not args.no_trace, backend=args.backend,
            device=args.device or "cpu",
        )
    if target == "proposals":
        from .proposals.bench import bench_proposals

        return bench_proposals(frames=args.frames)
    if target == "pipeline":
        return bench_pipeline(
            frames=args.frames, weights=args.weights, threads=args.threads, workers=args.workers,
            precision=args.precision, max_objects=args.max_objects, classifier=not args.no_classifier,
            refine=not args.no_refine, pipeline_split=args.pipeline_split, trace=not args.no_trace,
            free_space=not args.no_free_space, backend=args.backend, score_threshold=args.score_threshold,
            data=args.data, peer=not args.no_peer, against=args.against, processes=args.processes,
            device=args.device, gravity=args.gravity, proposal_source=args.proposal_source,
            frustum_points=args.frustum_points,
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
    """Run the chosen benchmarks; 1 when a soak run failed, else 0."""
    targets = TARGETS if args.target == "all" else (args.target,)
    results = {}
    for t in targets:
        print(f"== bench {t}", flush=True)
        results[t] = run_target(t, args)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0 if results.get("soak", {}).get("ok", True) else 1
