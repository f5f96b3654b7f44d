"""Benchmark of the AR queries: ``python -m shape_detector.ar.bench``.

Prints the median time of 10,000 ``collides`` queries (one batch, points within 30 cm of
furniture) and of 1,000 ray casts (one batch) against a 20-object scene whose objects carry
observed surface points on every face and whose four 2.5 m walls were seen whole (structure
points; and on the primitives alone), and of a plan across a 10 m x 10 m grid at 5 cm (graph
build included, and on a cached graph); single queries too.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from collections.abc import Callable

import numpy as np

from . import collision, planning
from .queries import SceneQueries
from .rays import raycast_many
from ..scene.grid import NavGrid
from ..scene.surface import SurfaceMemory
from ..scene.types import SceneObject, ScenePrimitive
from .scene_data import ArScene


def _rotz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def face_points(prims: list[ScenePrimitive], voxel: float = 0.02) -> np.ndarray:
    """Surface points as the scene map keeps them: the faces of ``prims`` sampled at half a
    voxel, then one mean point per ``voxel`` cube (world frame)."""
    pts = []
    for p in prims:
        axes = [np.linspace(-0.5, 0.5, max(2, int(np.ceil(s / (0.5 * voxel))) + 1)) * s for s in p.size]
        for k in range(3):
            for side in (-0.5, 0.5):
                a, b = [axes[j] for j in range(3) if j != k]
                g = np.stack(np.meshgrid(a, b, indexing="ij"), -1).reshape(-1, 2)
                q = np.zeros((len(g), 3))
                q[:, [j for j in range(3) if j != k]] = g
                q[:, k] = side * p.size[k]
                pts.append(q @ p.rotation.T + p.center)
    mem = SurfaceMemory(voxel)
    mem.add(np.concatenate(pts))
    return mem.points()


def bench_scene(n_objects: int = 20, room: float = 10.0, seed: int = 0, surfaces: bool = True) -> ArScene:
    """``n_objects`` tables (top + four legs, turned about z) on a ``room`` x ``room`` m floor, with
    the 5 cm grid of their footprints; ``surfaces``: each with surface points on all its faces."""
    rng = np.random.default_rng(seed)
    objects = []
    for i in range(n_objects):
        c = np.array([*rng.uniform(0.8, room - 0.8, 2), 0.0])
        R = _rotz(float(rng.uniform(-np.pi, np.pi)))
        ln, w, h = rng.uniform(0.5, 1.2), rng.uniform(0.5, 1.6), rng.uniform(0.45, 0.8)
        prims = [ScenePrimitive(c + R @ np.array([0, 0, h - 0.02]), np.array([ln, w, 0.04]), R)]
        for sx in (-1, 1):
            for sy in (-1, 1):
                off = np.array([sx * (ln / 2 - 0.03), sy * (w / 2 - 0.03), (h - 0.04) / 2])
                prims.append(ScenePrimitive(c + R @ off, np.array([0.06, 0.06, h - 0.04]), R))
        objects.append(SceneObject(i + 1, "table", 1.0, c + np.array([0, 0, h / 2]), np.array([ln, w, h]), R,
                                   primitives=prims, surface=face_points(prims) if surfaces else None))
    res = 0.05
    n = int(round(room / res))
    data = np.zeros((n, n), np.int8)
    centers = (np.stack(np.meshgrid(np.arange(n), np.arange(n)), axis=-1) + 0.5) * res  # (row, col) -> (x, y)
    for o in objects:
        local = (centers.reshape(-1, 2) - o.center[:2]) @ o.rotation[:2, :2]
        inside = np.all(np.abs(local) <= o.size[:2] / 2, axis=1).reshape(n, n)
        data[inside] = 100
    walls = [ScenePrimitive(c, np.array(sz), np.eye(3)) for c, sz in (
        (np.array([room / 2, -0.05, 1.25]), (room, 0.1, 2.5)), (np.array([room / 2, room + 0.05, 1.25]), (room, 0.1, 2.5)),
        (np.array([-0.05, room / 2, 1.25]), (0.1, room, 2.5)), (np.array([room + 0.05, room / 2, 1.25]), (0.1, room, 2.5)))]
    inner = face_points(walls) if surfaces else None
    if inner is not None:  # the faces towards the room
        inner = inner[(inner[:, 0] > -0.01) & (inner[:, 0] < room + 0.01) & (inner[:, 1] > -0.01) & (inner[:, 1] < room + 0.01)]
    return ArScene(objects, NavGrid(res, np.zeros(2), data), structure=inner)


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def run(repeats: int = 20, seed: int = 0) -> dict[str, float]:
    """Median milliseconds of each benchmark (see module doc)."""
    scene = bench_scene(seed=seed)
    bare = ArScene([replace(o, surface=None) for o in scene.objects], scene.grid)  # no structure either
    rng = np.random.default_rng(seed + 1)
    owners = rng.integers(0, len(scene.objects), 10_000)
    centers = np.array([scene.objects[k].center for k in owners])
    ext = np.array([scene.objects[k].size for k in owners]) / 2 + 0.3
    pts = centers + rng.uniform(-1, 1, (10_000, 3)) * ext
    origins = np.column_stack([rng.uniform(0, 10, (1000, 2)), rng.uniform(1.2, 1.8, 1000)])
    targets = np.array([scene.objects[k].center for k in rng.integers(0, len(scene.objects), 1000)])
    dirs = targets + rng.normal(0, 0.3, (1000, 3)) - origins
    q = SceneQueries(scene)
    start, goal = (0.15, 0.15), (9.85, 9.85)
    path = np.array(q.plan(start, goal, 0.2) or [start, start])
    return {
        "plan_length_m": float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))),
        "boxes": float(len(scene.boxes)),
        "collides_10k_ms": _median_ms(lambda: collision.collides_many(scene, pts, 0.1), repeats),
        "collides_single_us": 1e3 * _median_ms(lambda: collision.collides(scene, pts[0], 0.1), repeats * 10),
        "surface_points": float(len(scene.surface_index)),
        "structure_points": float(len(scene.structure_points) if scene.structure_points is not None else 0),
        "raycast_1k_ms": _median_ms(lambda: raycast_many(scene, origins, dirs), repeats),
        "raycast_1k_primitives_ms": _median_ms(lambda: raycast_many(bare, origins, dirs), repeats),
        "raycast_single_us": 1e3 * _median_ms(lambda: q.raycast(origins[0], dirs[0]), repeats * 10),
        "plan_10m_cold_ms": _median_ms(lambda: planning.plan(scene, start, goal, 0.2), max(3, repeats // 4)),
        "plan_10m_cached_ms": _median_ms(lambda: q.plan(start, goal, 0.2), repeats),
    }


def main(argv: list[str] | None = None) -> int:
    """Print the benchmark numbers."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=20)
    args = p.parse_args(argv)
    for k, v in run(args.repeats).items():
        print(f"{k:>22}: {v:9.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
