"""``shape-detector bench proposals``: gravity + geometric proposals, ms per VGA frame.

Times, on generated VGA frames (``shape_detector.synth.generate``), the stages of
:class:`GeometricProposer` as the detector runs them: ``grid`` (strided back-projection + normals), ``gravity``
(:func:`~shape_detector.gravity.estimate_up` on that grid), ``proposals`` (structure
removal, segmentation, hypotheses) and ``total`` (the whole call); then, when the
``realtime`` preset's ``proposal_source`` is another one (``hybrid``: the learned network in
a thread beside the geometric proposer), that proposer's whole call as the detector makes
it (``proposer``; its name in ``res["proposer"]``) and the learned network alone (``learned``). Prints and returns median / p95
wall-clock ms and the median thread CPU ms (less sensitive to other processes on a shared
machine; for ``proposer`` only the calling thread's), plus the 1-minute load average.
"""

from __future__ import annotations

import os
import time

import numpy as np


def _frames(n: int, seed0: int):
    """``n`` generated VGA frames (seeds ``seed0``...) and the source's name."""
    from ..synth.generate import generate_frame

    return [generate_frame(seed0 + i) for i in range(n)], "synth"


def _time_default_proposer(data: list, timed, wall: dict, cpu: dict, res: dict, repeats: int) -> tuple[str, ...]:
    """Time the ``realtime`` preset's built-in proposer when it is not the geometric one
    (see the module docstring); the stage names it added."""
    from ..detector_config import preset
    from ..proposal_source import make_proposer

    cfg = preset("realtime")
    if cfg.proposal_source == "geometric":
        return ()
    proposer = make_proposer(cfg)
    res["proposer"] = cfg.proposal_source
    added: tuple[str, ...] = ("proposer",)
    learned = getattr(proposer, "learned", None)
    if learned is not None:
        added += ("learned",)
    for k in added:
        wall[k], cpu[k] = [], []
    for f in data[:2]:  # warm-up
        proposer(f.depth, f.K, rgb=f.rgb)
    for _ in range(max(1, repeats)):
        for f in data:
            timed("proposer", lambda f=f: proposer(f.depth, f.K, rgb=f.rgb))
            if learned is not None:
                timed("learned", lambda f=f: learned.detect(f.rgb, f.depth))
    return added


def bench_proposals(frames: int = 20, seed0: int = 20_000, repeats: int = 2, verbose: bool = True) -> dict:
    """Median / p95 ms per VGA frame of grid, gravity, proposals and total (see module doc)."""
    from ..gravity import estimate_up, make_grid
    from .geometric import GeometricProposer

    data, source = _frames(max(1, int(frames)), seed0)
    prop = GeometricProposer()
    cfg = prop.config
    for f in data[:2]:  # warm-up
        prop(f.depth, f.K, rgb=f.rgb)
    stride = prop.stride_for(data[0].depth.shape)
    stages = ("grid", "gravity", "proposals", "total")
    wall: dict[str, list[float]] = {k: [] for k in stages}
    cpu: dict[str, list[float]] = {k: [] for k in stages}
    nprops = []

    def timed(key, fn):
        t0, c0 = time.perf_counter(), time.thread_time()
        out = fn()
        wall[key].append(1e3 * (time.perf_counter() - t0))
        cpu[key].append(1e3 * (time.thread_time() - c0))
        return out

    for _ in range(max(1, repeats)):
        for f in data:
            grid = timed("grid", lambda f=f: make_grid(f.depth, f.K, stride=stride, max_depth=cfg.max_depth))
            grav = timed("gravity", lambda f=f, grid=grid: estimate_up(None, f.K, grid=grid, config=cfg.gravity))
            timed("proposals", lambda f=f, grid=grid, grav=grav: prop.propose(grid, grav, f.rgb))
            _, props = timed("total", lambda f=f: prop(f.depth, f.K, rgb=f.rgb))
            nprops.append(len(props))
    h, w = data[0].depth.shape
    res: dict = {"frames": len(data), "source": source, "image": f"{w}x{h}", "stride": stride}
    stages = stages + _time_default_proposer(data, timed, wall, cpu, res, repeats)
    for k in stages:
        res[f"{k}_ms_p50"] = float(np.median(wall[k]))
        res[f"{k}_ms_p95"] = float(np.percentile(wall[k], 95))
        res[f"{k}_cpu_ms_p50"] = float(np.median(cpu[k]))
    res["total_fps_p50"] = 1e3 / res["total_ms_p50"]
    res["proposals_per_frame"] = float(np.mean(nprops))
    try:
        res["load_avg_1min"] = float(os.getloadavg()[0])
    except OSError:  # pragma: no cover
        res["load_avg_1min"] = float("nan")
    if verbose:
        print(
            f"proposals bench ({len(data)} {source} frames {w}x{h}, stride {stride}, "
            f"load avg {res['load_avg_1min']:.1f}): ms/frame p50 (p95) [thread cpu p50]",
            flush=True,
        )
        for k in stages:
            label = res["proposer"] if k == "proposer" else k
            print(
                f"  {label:<10} {res[f'{k}_ms_p50']:6.1f} ({res[f'{k}_ms_p95']:6.1f}) [{res[f'{k}_cpu_ms_p50']:5.1f}]",
                flush=True,
            )
        print(f"  -> {res['total_fps_p50']:.0f} fps, {res['proposals_per_frame']:.1f} proposals/frame", flush=True)
    return res


if __name__ == "__main__":  # pragma: no cover
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    a = ap.parse_args()
    bench_proposals(a.frames)
