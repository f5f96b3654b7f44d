"""Generator throughput: frames/s at 640x480 with and without the depth noise model."""

from __future__ import annotations

import time

import numpy as np


def bench_synth(frames: int = 20, width: int = 640, height: int = 480, seed0: int = 50_000,
                workers: int = 2) -> dict:
    """Time ``generate_frame`` (and shard encoding) on ``frames`` frames; prints and returns frames/s.

    ``est_10k_minutes`` extrapolates generating + encoding 10k frames with ``workers`` processes
    (assumes one free core per worker, from the CPU-time rate). OpenCV runs single-threaded here, as
    in the dataset workers; wall-clock rates drop when other processes share the cores.
    """
    import cv2

    from .dataset import encode_frame
    from .generate import SynthConfig, generate_frame

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one core per generator process, as in write_shards' workers
    generate_frame(seed0 - 1, SynthConfig(width=width, height=height))  # warm caches (noise textures)
    out: dict = {"width": width, "height": height, "frames": frames}
    for noise in (True, False):
        cfg = SynthConfig(width=width, height=height, noise=noise)
        times, cpu = [], []
        for i in range(frames):
            t0, c0 = time.perf_counter(), time.process_time()
            generate_frame(seed0 + i, cfg)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        key = "noise" if noise else "clean"
        out[f"fps_{key}"] = float(frames / np.sum(times))
        out[f"fps_cpu_{key}"] = float(frames / np.sum(cpu))
        out[f"ms_p50_{key}"] = float(1e3 * np.median(times))
        out[f"ms_p95_{key}"] = float(1e3 * np.percentile(times, 95))
        print(f"synth[{key}] {width}x{height}: {out[f'fps_{key}']:.2f} frames/s wall "
              f"(p50 {out[f'ms_p50_{key}']:.0f} ms, p95 {out[f'ms_p95_{key}']:.0f} ms); "
              f"{out[f'fps_cpu_{key}']:.2f} frames/s of process CPU time (= an idle core)", flush=True)
    f = generate_frame(seed0, SynthConfig(width=width, height=height))
    t0 = time.perf_counter()
    for _ in range(5):
        encode_frame(f)
    enc = (time.perf_counter() - t0) / 5
    out["encode_ms"] = 1e3 * enc
    per = 1.0 / out["fps_cpu_noise"] + enc
    cv2.setNumThreads(threads)
    out["est_10k_minutes"] = float(10_000 * per / workers / 60.0)
    print(f"shard encoding {1e3 * enc:.0f} ms/frame; 10k frames with {workers} workers ~ "
          f"{out['est_10k_minutes']:.0f} min", flush=True)
    return out
