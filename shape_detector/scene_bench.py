"""``python -m shape_detector.scene_bench``: milliseconds per SceneMap.update with 20 tracks.

A generated room with 20 pieces of furniture in two rows before two walls, seen from a
camera walking past them at VGA;
each frame gives the map the boxes in view with noise (no network runs). Prints the mean
and 95th percentile of: the update without depth (association, fusion, merging), the full
update with depth (plus negative evidence, the floor and the observed surfaces), the floor
integration alone (the grid's depth part) without and with the observed surfaces, building
the grid and listing the objects with their observed surfaces (for JSON and ray casts) when
asked. The listing runs on a second map fed the same frames: it merges the surface memory's
pending points, whose cost belongs to the update.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from .scene import SceneConfig, SceneMap
from .synth.render import rasterize
from .types import Object3D

W, H = 640, 480
K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def _rotz(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _pose(x: float, heading: float) -> np.ndarray:
    f = np.array([np.cos(heading), np.sin(heading), 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([[np.sin(heading), -np.cos(heading), 0.0], [0.0, 0.0, -1.0], f], axis=1)
    T[:3, 3] = [x, 0.0, 1.3]
    return T


def scene(n: int = 20, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """``n`` boxes (centre, size, yaw) on the floor in two rows along x."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        size = np.array([rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.0), rng.uniform(0.5, 1.2)])
        c = np.array([1.5 * (i // 2 + 1), 2.0 if i % 2 else -2.0, 0.5 * size[2]])
        out.append((c, size, float(rng.uniform(-0.3, 0.3))))
    return out


def frames(boxes, n: int, seed: int = 1):
    """Per frame: (T_world_camera, depth, detections in the camera frame)."""
    rng = np.random.default_rng(seed)
    floor = (np.array([10.0, 0.0, -0.05]), np.array([40.0, 10.0, 0.1]), 0.0)
    # the room's walls behind the two rows: their depth points are kept as observed surfaces too
    walls = [(np.array([10.0, y, 1.3]), np.array([40.0, 0.1, 2.6]), 0.0) for y in (-3.5, 3.5)]
    for i in range(n):
        T = _pose(0.28 * i, np.pi / 2 if i % 2 else -np.pi / 2 + 0.3)
        R, t = T[:3, :3], T[:3, 3]
        allb = boxes + [floor] + walls
        depth, _, _ = rasterize(np.array([(c - t) @ R for c, _, _ in allb]), np.array([s for _, s, _ in allb]),
                                np.array([R.T @ _rotz(y) for _, _, y in allb]), K, W, H)
        depth = depth.astype(np.float32)
        depth[~np.isfinite(depth)] = np.nan
        dets = []
        for c, s, y in boxes:
            cc = R.T @ (c - t)
            if cc[2] < 0.5 or abs(cc[0]) > cc[2]:
                continue
            noisy = c + rng.normal(0, 0.03, 3)
            dets.append(Object3D("chair", float(rng.uniform(0.8, 1.0)), R.T @ (noisy - t), s * rng.uniform(0.95, 1.05, 3),
                                 R.T @ _rotz(y + rng.normal(0, 0.05))))
        yield T, depth, dets


def run(n_frames: int = 60, tracks: int = 20) -> dict[str, list[float]]:
    """Per-frame milliseconds of each measured step (and the final track count)."""
    boxes = scene(tracks)
    data = list(frames(boxes, n_frames))
    times: dict[str, list[float]] = {"update_no_depth": [], "update_with_depth": [], "floor_integration": [],
                                     "floor_and_surfaces": [], "grid_build": [], "objects_with_surfaces": []}
    a, b, c, e = SceneMap(), SceneMap(), SceneMap(SceneConfig(surface_voxel=0.0)), SceneMap()
    f = SceneMap()  # asked for its objects' surfaces every frame, which merges its pending points; b never is
    for i, (T, depth, dets) in enumerate(data):
        t0 = time.perf_counter()
        a.update(dets, T, None, None, i)
        t1 = time.perf_counter()
        b.update(dets, T, depth, K, i)
        t2 = time.perf_counter()
        c.integrate_floor(T, depth, K)
        t3 = time.perf_counter()
        e.integrate_floor(T, depth, K)
        t4 = time.perf_counter()
        b.grid()
        t5 = time.perf_counter()
        f.update(dets, T, depth, K, i)
        t6 = time.perf_counter()
        f.objects(surfaces=True)
        t7 = time.perf_counter()
        for k, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t7 - t6)):
            times[k].append(1000.0 * dt)
    times["tracks"] = [float(len(b.tracks))]
    return times


def main(argv: list[str] | None = None) -> int:
    """Print the benchmark table."""
    p = argparse.ArgumentParser(prog="python -m shape_detector.scene_bench", description=__doc__)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--tracks", type=int, default=20)
    args = p.parse_args(argv)
    t = run(args.frames, args.tracks)
    skip = min(5, args.frames - 1)  # the first frames start the tracks
    print(f"SceneMap.update, {int(t.pop('tracks')[0])} tracks at the end, {args.frames} frames at {W}x{H}:")
    for k, ms in t.items():
        v = np.asarray(ms[skip:])
        print(f"  {k:20s} mean {v.mean():6.2f} ms   p95 {np.percentile(v, 95):6.2f} ms")
    print(f"  target: update_with_depth <= 5 ms per frame (mean {np.mean(t['update_with_depth'][skip:]):.2f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
