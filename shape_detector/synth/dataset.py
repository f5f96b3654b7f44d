"""Training data shards: generated frames stored compactly, read back as :class:`Frame`.

Layout of ``out_dir``::

    index.json                 # seed, frame count, frames per shard, generator config, shard list
    shard_00000.npz ...        # one uncompressed zip per shard; per frame i (0-based within shard):
        {i}_rgb    uint8 bytes   PNG (lossless, default) or JPEG of the RGB image
        {i}_depth  uint8 bytes   16-bit PNG, depth in millimetres, 0 = invalid (NaN)
        {i}_mask   uint8 bytes   8-bit PNG instance mask (0 = none, else GTObject.instance_id)
        {i}_gt     uint8 bytes   UTF-8 JSON: K, up, stamp_ns, frame_id, seed, objects
                                 (GTObject.to_dict), clutter_boxes

Frame ``k`` of a set made with seed ``S`` is ``generate_frame(frame_seed(S, k), config)``, so any
frame can be regenerated exactly. Depth reads back within 1 mm (it is quantised to 1 mm by the
noise model already, so noisy depth is exact).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from ..types import Frame, GTObject
from .generate import GENERATOR_VERSION, SynthConfig, generate_frame

INDEX = "index.json"


def frame_seed(seed: int, index: int) -> int:
    """Seed of frame ``index`` of a data set generated with ``seed`` (disjoint across seeds)."""
    return (int(seed) << 32) + int(index)


# ----------------------------------------------------------------------------- encoding

def encode_frame(frame: Frame, rgb_format: str = "png", seed: int | None = None) -> dict[str, np.ndarray]:
    """Compressed arrays of one frame: RGB (PNG or JPEG), depth (uint16 mm PNG, 0 = invalid), instance mask (uint8
    PNG), GT as JSON bytes."""
    if rgb_format == "png":
        ok, rgb = cv2.imencode(".png", np.ascontiguousarray(frame.rgb[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        ok, rgb = cv2.imencode(".jpg", np.ascontiguousarray(frame.rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    d = frame.depth
    mm = np.where(np.isfinite(d), np.clip(np.round(d * 1000.0), 0, 65535), 0).astype(np.uint16)
    ok, dep = cv2.imencode(".png", mm, [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
                                        cv2.IMWRITE_PNG_STRATEGY_RLE])
    assert ok
    mask = frame.instance_mask if frame.instance_mask is not None else np.zeros(d.shape, np.int32)
    if mask.max(initial=0) > 255:
        raise ValueError("instance ids above 255 do not fit the uint8 mask")
    ok, msk = cv2.imencode(".png", mask.astype(np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    assert ok
    gt = {
        "K": np.asarray(frame.K).tolist(),
        "up": None if frame.up is None else np.asarray(frame.up).tolist(),
        "stamp_ns": int(frame.stamp_ns),
        "frame_id": frame.frame_id,
        "seed": seed,
        "width": int(d.shape[1]),
        "height": int(d.shape[0]),
        "objects": [o.to_dict() for o in frame.objects],
        "clutter_boxes": [list(map(float, b)) for b in frame.clutter_boxes],
    }
    js = np.frombuffer(json.dumps(gt, separators=(",", ":")).encode(), np.uint8)
    return {"rgb": rgb.ravel(), "depth": dep.ravel(), "mask": msk.ravel(), "gt": js}


def decode_frame(parts: dict[str, np.ndarray]) -> Frame:
    """The frame stored by :func:`encode_frame` (depth float32 metres, NaN where invalid)."""
    rgb = cv2.imdecode(parts["rgb"], cv2.IMREAD_COLOR)[:, :, ::-1]
    mm = cv2.imdecode(parts["depth"], cv2.IMREAD_UNCHANGED)
    depth = mm.astype(np.float32) / 1000.0
    depth[mm == 0] = np.nan
    mask = cv2.imdecode(parts["mask"], cv2.IMREAD_UNCHANGED).astype(np.int32)
    gt = json.loads(bytes(parts["gt"]).decode())
    return Frame(
        rgb=np.ascontiguousarray(rgb), depth=depth, K=np.array(gt["K"], dtype=np.float64),
        up=None if gt["up"] is None else np.array(gt["up"], dtype=np.float64), stamp_ns=int(gt["stamp_ns"]),
        frame_id=gt["frame_id"], objects=[GTObject.from_dict(o) for o in gt["objects"]], instance_mask=mask,
        clutter_boxes=[tuple(b) for b in gt["clutter_boxes"]],
    )


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- writing

def _shard_job(args: tuple) -> tuple[int, int, float]:
    out_dir, shard, start, count, seed, config, rgb_format = args
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    arrays: dict[str, np.ndarray] = {}
    for j in range(count):
        s = frame_seed(seed, start + j)
        fr = generate_frame(s, config)
        for k, v in encode_frame(fr, rgb_format, s).items():
            arrays[f"{j}_{k}"] = v
    _write_npz(Path(out_dir) / f"shard_{shard:05d}.npz", arrays)
    return shard, count, time.perf_counter() - t0


def write_shards(out_dir: str | Path, num_frames: int, seed: int = 0, frames_per_shard: int = 256,
                 workers: int = 2, config: SynthConfig | None = None, rgb_format: str = "png",
                 quiet: bool = False) -> dict:
    """Generate ``num_frames`` frames into shards under ``out_dir`` with ``workers`` processes
    (spawned: from a script, call it under ``if __name__ == "__main__":``).

    Prints one progress line per finished shard and the overall frames/s; returns the index dict.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config or SynthConfig()
    n_shards = (num_frames + frames_per_shard - 1) // frames_per_shard
    jobs = [(str(out), k, k * frames_per_shard, min(frames_per_shard, num_frames - k * frames_per_shard), seed, cfg,
             rgb_format) for k in range(n_shards)]
    t0 = time.perf_counter()
    done = 0
    log = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    if workers <= 1 or n_shards == 1:
        results = map(_shard_job, jobs)
        pool = None
    else:
        # spawn, not fork: a process that already ran OpenCV's (or torch's) thread pool, as
        # the training runner has when it generates a missing data set after cutting frustums,
        # forks children that hang in cv2.setNumThreads on the pool's copied condition variable
        ctx = mp.get_context("spawn")
        pool = ctx.Pool(min(workers, n_shards))
        results = pool.imap_unordered(_shard_job, jobs)
    try:
        for shard, count, dt in results:
            done += count
            el = time.perf_counter() - t0
            log(f"shard {shard + 1}/{n_shards}: {count} frames in {dt:.1f} s ({count / dt:.2f} frames/s/worker); "
                f"total {done}/{num_frames} frames, {done / el:.2f} frames/s")
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    el = time.perf_counter() - t0
    cdict = asdict(cfg)
    cdict["noise_params"] = None if cfg.noise_params is None else asdict(cfg.noise_params)
    index = {
        "format": "shape_detector.synth shards v1", "generator_version": GENERATOR_VERSION,
        "seed": seed, "num_frames": num_frames,
        "frames_per_shard": frames_per_shard, "rgb_format": rgb_format,
        "shards": [f"shard_{k:05d}.npz" for k in range(n_shards)], "config": cdict,
        "seconds": el, "frames_per_second": num_frames / max(el, 1e-9),
    }
    (out / INDEX).write_text(json.dumps(index, indent=1))
    log(f"wrote {num_frames} frames in {n_shards} shards to {out} in {el:.1f} s: {num_frames / max(el, 1e-9):.2f} frames/s")
    return index


# ----------------------------------------------------------------------------- reading

def shard_paths(shard_dir: str | Path) -> list[Path]:
    """Shard files of ``shard_dir`` in generation order (its index file's order when there is one); a file is its own
    shard."""
    p = Path(shard_dir)
    if p.is_file():
        return [p]
    idx = p / INDEX
    if idx.is_file():
        return [p / s for s in json.loads(idx.read_text())["shards"] if (p / s).is_file()]
    return sorted(p.glob("shard_*.npz"))


def iter_frames(shard_dir: str | Path) -> Iterator[Frame]:
    """Frames of a shard directory (or a single shard file), in generation order."""
    for path in shard_paths(shard_dir):
        with np.load(path) as z:
            n = sum(1 for k in z.files if k.endswith("_gt"))
            for j in range(n):
                yield decode_frame({k: z[f"{j}_{k}"] for k in ("rgb", "depth", "mask", "gt")})


def read_frame(shard_dir: str | Path, index: int) -> Frame:
    """Random access to frame ``index`` of a shard directory."""
    paths = shard_paths(shard_dir)
    for path in paths:
        with np.load(path) as z:
            n = sum(1 for k in z.files if k.endswith("_gt"))
            if index < n:
                return decode_frame({k: z[f"{index}_{k}"] for k in ("rgb", "depth", "mask", "gt")})
            index -= n
    raise IndexError(index)


def count_frames(shard_dir: str | Path) -> int:
    """Number of frames stored in the shards of ``shard_dir``."""
    total = 0
    for path in shard_paths(shard_dir):
        with np.load(path) as z:
            total += sum(1 for k in z.files if k.endswith("_gt"))
    return total


__all__ = ["write_shards", "iter_frames", "read_frame", "count_frames", "frame_seed", "encode_frame", "decode_frame",
           "shard_paths"]
