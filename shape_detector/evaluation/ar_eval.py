"""AR query evaluation on generated walk-throughs (world frame z up, metres).

The queries of :mod:`shape_detector.ar` run on a map (the detector-built ``SceneMap`` or,
as a check of this code, the true scene) and are scored against the room's true geometry:

* ``ray_within_5cm`` -- rays from the true camera poses through random pixels: share whose
  hit distance on the map is within ``ray_tol`` of the true first hit, over the rays whose
  true first hit is a labelled object's part (the issue's "true geometry"); rays first
  hitting a wall, door, window, unlabelled clutter or the floor are left out of it.
  ``ray_floor_within_5cm`` is the same share over the rays first hitting the floor inside
  the room (the room's floor slab), reported beside it, and ``ray_within_5cm_primitives`` the
  object rays' share without the observed surfaces (the primitives alone);
* ``collide_precision`` / ``collide_recall`` -- ``collides`` (sphere of ``radius``) at random
  points within ``band`` of the parts of objects seen during the walk, against all true parts;
  ``_primitives`` the same without the observed surfaces (the primitives alone);
* ``plan_found`` -- pairs of random floor points free for the agent in the true footprint
  grid, both on floor the map saw, joined in the true grid: share the map's ``plan`` joins;
  ``plan_clear`` -- share of found paths keeping ``agent_radius - margin`` from every true
  footprint (the whole polyline, sampled every 2 cm). Both for the default (enclosed unknown
  cells walkable) and, suffixed ``_blocked``, for unknown cells blocked;
* ``surface_height_err_cm`` -- the map's usable surfaces (``surfaces()``): median height error
  against the true part top under each surface's centre (the one nearest in height, within
  ``max_err``); ``surface_within_2cm`` the share of those within 2 cm, ``surface_matched`` the
  share of surfaces with such a true top.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..ar.affordances import surfaces
from ..ar.collision import collides_many, distance_to_scene
from ..ar.planning import traversable
from ..ar.queries import SceneQueries
from ..ar.rays import raycast_many
from ..ar.scene_data import ArScene
from ..scene.grid import NavGrid
from ..scene.types import SceneObject, ScenePrimitive

#: object ids of non-furniture boxes in the full true scene
STRUCTURE_ID0 = 100_000
CLUTTER_ID0 = 200_000


@dataclass
class Truth:
    """The true room: ``objects`` (labelled furniture, ids = instance ids, with parts),
    ``full`` (furniture + walls/doors/windows + clutter, for first hits), the room rectangle
    ``[0, rx] x [0, ry]``, ``grid`` (free floor inside the room minus the footprints of
    parts that block an agent), ``footprints`` (those parts as tall boxes: 2D distances)."""

    objects: ArScene
    full: ArScene
    rx: float
    ry: float
    grid: NavGrid
    footprints: ArScene


def _obj(oid: int, name: str, centers: np.ndarray, sizes: np.ndarray, rots: np.ndarray) -> SceneObject:
    prims = [ScenePrimitive(np.asarray(c, float), np.asarray(s, float), np.asarray(R, float))
             for c, s, R in zip(centers, sizes, rots)]
    lo = np.min([p.center - 0.5 * np.abs(p.rotation) @ p.size for p in prims], axis=0)
    hi = np.max([p.center + 0.5 * np.abs(p.rotation) @ p.size for p in prims], axis=0)
    return SceneObject(oid, name, 1.0, 0.5 * (lo + hi), hi - lo, np.eye(3), primitives=prims)


def truth_from_layout(scene: Any, resolution: float = 0.05, agent_height: float = 1.8,
                      min_height: float = 0.05) -> Truth:
    """:class:`Truth` of a generated room (``shape_detector.synth.layout.Scene``)."""
    objects, others = [], []
    for i, p in enumerate(scene.objects):
        c, s, R, _ = p.cuboids()
        objects.append(_obj(i + 1, p.model.name, c, s, np.broadcast_to(R, (len(c), 3, 3))))
    for k, st in enumerate(scene.structure):
        others.append(_obj(STRUCTURE_ID0 + k, "structure", st.center[None], st.size[None], st.R[None]))
    for k, p in enumerate(scene.clutter):
        c, s, R, _ = p.cuboids()
        others.append(_obj(CLUTTER_ID0 + k, "clutter", c, s, np.broadcast_to(R, (len(c), 3, 3))))
    rx, ry = float(scene.rx), float(scene.ry)
    blocking = []
    for o in objects:
        for p in o.primitives:
            hz = 0.5 * float(np.abs(p.rotation[2]) @ p.size)
            if p.center[2] - hz < agent_height and p.center[2] + hz > min_height:
                blocking.append(ScenePrimitive(np.array([*p.center[:2], 0.0]), np.array([*p.size[:2], 1e3]), p.rotation))
    footprints = ArScene([SceneObject(1, "footprint", 1.0, np.zeros(3), np.ones(3), np.eye(3), primitives=blocking)] if blocking else [])
    margin = 0.3
    nx, ny = int(np.ceil((rx + 2 * margin) / resolution)), int(np.ceil((ry + 2 * margin) / resolution))
    origin = np.array([-margin, -margin])
    xs = origin[0] + (np.arange(nx) + 0.5) * resolution
    ys = origin[1] + (np.arange(ny) + 0.5) * resolution
    X, Y = np.meshgrid(xs, ys)
    pts = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    inside = (pts[:, 0] > 0) & (pts[:, 0] < rx) & (pts[:, 1] > 0) & (pts[:, 1] < ry)
    occupied = collides_many(footprints, pts, 0.0) if blocking else np.zeros(len(pts), bool)
    data = np.where(inside & ~occupied, 0, 100).astype(np.int8).reshape(ny, nx)
    return Truth(ArScene(objects), ArScene(objects + others), rx, ry, NavGrid(resolution, origin, data), footprints)


def ray_metric(truth: Truth, m: ArScene, cameras: list[tuple[np.ndarray, np.ndarray, int, int]], n_rays: int,
               rng: np.random.Generator, tol: float = 0.05) -> dict[str, float]:
    """Ray casts through random pixels of random frames (``cameras``: T_world_camera (4,4), K,
    width, height); see the module doc."""
    cam = rng.integers(0, len(cameras), n_rays)
    o, d = np.zeros((n_rays, 3)), np.zeros((n_rays, 3))
    for i, k in enumerate(cam):
        T, K, W, H = cameras[k]
        uv1 = np.array([rng.uniform(0, W) - 0.5, rng.uniform(0, H) - 0.5, 1.0])
        o[i], d[i] = T[:3, 3], T[:3, :3] @ (np.linalg.inv(K) @ uv1)
    true = raycast_many(truth.full, o, d)
    hit_pt = o + d / np.linalg.norm(d, axis=1, keepdims=True) * np.where(true.hit, true.distance, 0.0)[:, None]
    in_room = (hit_pt[:, 0] >= 0) & (hit_pt[:, 0] <= truth.rx) & (hit_pt[:, 1] >= 0) & (hit_pt[:, 1] <= truth.ry)
    on_obj = true.hit & (true.object_id > 0) & (true.object_id < STRUCTURE_ID0)
    # the generated room's floor is its first structure box, a slab whose top is z = 0
    on_floor = true.hit & (true.object_id == STRUCTURE_ID0) & in_room & (np.abs(hit_pt[:, 2]) < 1e-6)
    used = on_obj | on_floor
    got = raycast_many(m, o[used], d[used])
    err = np.abs(got.distance - true.distance[used])
    ok = err <= tol  # a miss (inf) never counts
    obj = on_obj[used]
    bare = np.abs(raycast_many(m, o[used], d[used], surfaces=False).distance - true.distance[used]) <= tol
    return {"ray_within_5cm": float(ok[obj].mean()) if obj.any() else float("nan"),
            "ray_within_5cm_primitives": float(bare[obj].mean()) if obj.any() else float("nan"),
            "ray_floor_within_5cm": float(ok[~obj].mean()) if (~obj).any() else float("nan"),
            "ray_median_err_cm": 100 * float(np.median(np.where(np.isfinite(err[obj]), err[obj], 1e3)))
            if obj.any() else 0.0,
            "rays_used": float(obj.sum()), "rays_floor": float((~obj).sum()), "rays_excluded": float((~used).sum())}


def collide_metric(truth: Truth, m: ArScene, seen_ids: set[int], n_points: int, rng: np.random.Generator,
                   radius: float = 0.1, band: float = 0.3) -> dict[str, float]:
    """``collides`` precision / recall near the seen objects (see the module doc)."""
    seen = ArScene([o for o in truth.objects.objects if o.id in seen_ids])
    if not seen.objects:
        return {"collide_precision": float("nan"), "collide_recall": float("nan"), "collide_points": 0.0,
                "collide_precision_primitives": float("nan"), "collide_recall_primitives": float("nan")}
    floor = truth.objects.floor_z
    k = rng.integers(0, len(seen.objects), 4 * n_points)
    c = np.array([seen.objects[i].center for i in k])
    ext = np.array([seen.objects[i].size for i in k]) / 2 + band
    pts = c + rng.uniform(-1, 1, (len(k), 3)) * ext
    keep = (pts[:, 2] >= floor) & (distance_to_scene(seen, pts, 2 * band) <= band)
    pts = pts[keep][:n_points]
    want = collides_many(truth.objects, pts, radius)
    out = {"collide_points": float(len(pts)), "collide_positive_share": float(want.mean()) if len(pts) else 0.0}
    for suffix, observed in (("", True), ("_primitives", False)):
        got = collides_many(m, pts, radius, surfaces=observed)
        tp = float(np.sum(want & got))
        out[f"collide_precision{suffix}"] = tp / max(float(got.sum()), 1.0)
        out[f"collide_recall{suffix}"] = tp / max(float(want.sum()), 1.0)
    return out


def _free_points(mask: np.ndarray, grid: NavGrid, n: int, rng: np.random.Generator) -> np.ndarray:
    cells = np.argwhere(mask)
    if len(cells) == 0:
        return np.zeros((0, 2))
    pick = cells[rng.integers(0, len(cells), n)]
    return grid.origin + (pick[:, ::-1] + rng.uniform(0.1, 0.9, (n, 2))) * grid.resolution


def _cell_values(grid: NavGrid | None, xy: np.ndarray) -> np.ndarray:
    if grid is None or grid.data.size == 0:
        return np.full(len(xy), -1)
    rc = np.floor((xy - grid.origin) / grid.resolution).astype(np.int64)[:, ::-1]
    ok = (rc[:, 0] >= 0) & (rc[:, 1] >= 0) & (rc[:, 0] < grid.height) & (rc[:, 1] < grid.width)
    out = np.full(len(xy), -1)
    out[ok] = grid.data[rc[ok, 0], rc[ok, 1]]
    return out


def plan_metric(truth: Truth, m: ArScene, n_pairs: int, rng: np.random.Generator, agent_radius: float = 0.2,
                margin: float = 0.02, policies: tuple[str, ...] = ("interior", "blocked")) -> dict[str, float]:
    """``plan`` on the map against the true footprint grid (see the module doc), once per
    policy for the map's unknown cells (keys suffixed ``_<policy>`` after the first)."""
    tq, mq = SceneQueries(ArScene([], truth.grid)), SceneQueries(m)
    free = traversable(truth.grid, agent_radius, "blocked")  # the true grid has no unknown cells
    a, b = _free_points(free, truth.grid, 6 * n_pairs, rng), _free_points(free, truth.grid, 6 * n_pairs, rng)
    seen = (_cell_values(m.grid, a) == 0) & (_cell_values(m.grid, b) == 0)
    pairs = [(s, g) for s, g in zip(a[seen], b[seen]) if tq.plan(s, g, agent_radius, snap_distance=0.0, squeeze=0.0) is not None]
    pairs = pairs[:n_pairs]
    out = {"plan_pairs": float(len(pairs))}
    for k, policy in enumerate(policies):
        found = clear = 0
        min_clear = np.inf
        for s, g in pairs:
            path = mq.plan(s, g, agent_radius, unknown=policy) if m.grid is not None else None
            if path is None:
                continue
            found += 1
            p = np.array(path)
            dense = np.concatenate([np.linspace(u, v, max(2, int(np.ceil(np.linalg.norm(v - u) / 0.02)) + 1))
                                    for u, v in zip(p[:-1], p[1:])])
            d = distance_to_scene(truth.footprints, np.column_stack([dense, np.zeros(len(dense))]), 1.0) \
                if truth.footprints.objects else np.ones(len(dense))
            min_clear = min(min_clear, float(d.min()))
            clear += int(d.min() >= agent_radius - margin)
        sfx = "" if k == 0 else f"_{policy}"
        out[f"plan_found{sfx}"] = found / len(pairs) if pairs else float("nan")
        out[f"plan_clear{sfx}"] = clear / found if found else float("nan")
        out[f"plan_min_clearance_cm{sfx}"] = 100 * min_clear if found else float("nan")
    return out


def surface_metric(truth: Truth, m: ArScene, max_err: float = 0.3) -> dict[str, float]:
    """Height errors of the map's usable surfaces (module doc)."""
    found = surfaces(m)
    tops = [(p.center, 0.5 * p.size, p.rotation) for o in truth.objects.objects for p in o.primitives
            if np.max(np.abs(p.rotation[2])) > 0.98]  # parts with a vertical axis: a horizontal top
    errs = []
    for f in found:
        c = f.polygon.mean(axis=0)
        best = np.inf
        for pc, ph, R in tops:
            local = (np.array([*c, pc[2]]) - pc) @ R
            k = int(np.argmax(np.abs(R[2])))
            if all(abs(local[j]) <= ph[j] for j in range(3) if j != k):
                err = abs(pc[2] + abs(R[2, k]) * ph[k] - f.height)
                best = min(best, err)
        if best <= max_err:
            errs.append(best)
    e = np.array(errs)
    return {"surface_height_err_cm": 100 * float(np.median(e)) if len(e) else float("nan"),
            "surface_within_2cm": float(np.mean(e <= 0.02)) if len(e) else float("nan"),
            "surface_matched": len(e) / len(found) if found else float("nan"), "surfaces": float(len(found))}


def evaluate_map(truth: Truth, m: ArScene, cameras: list[tuple[np.ndarray, np.ndarray, int, int]], seen_ids: set[int],
                 rng: np.random.Generator, n_rays: int = 2000, n_points: int = 2000, n_pairs: int = 40,
                 radius: float = 0.1, agent_radius: float = 0.2) -> dict[str, float]:
    """All the metrics of one map."""
    out = ray_metric(truth, m, cameras, n_rays, rng)
    out.update(collide_metric(truth, m, seen_ids, n_points, rng, radius))
    out.update(plan_metric(truth, m, n_pairs, rng, agent_radius))
    out.update(surface_metric(truth, m))
    return out


def seen_objects(frames: list[Any], min_pixels: int = 300, min_frames: int = 3) -> set[int]:
    """Instance ids with at least ``min_pixels`` pixels in at least ``min_frames`` frames."""
    counts: dict[int, int] = {}
    for f in frames:
        if f.instance_mask is None:
            continue
        n = np.bincount(f.instance_mask.ravel().clip(0))
        for i in np.nonzero(n >= min_pixels)[0]:
            if i > 0:
                counts[int(i)] = counts.get(int(i), 0) + 1
    return {i for i, c in counts.items() if c >= min_frames}


def gt_map(truth: Truth) -> ArScene:
    """The true scene as a map (objects with their parts and the true footprint grid)."""
    return ArScene(list(truth.objects.objects), truth.grid)


def evaluate_walkthrough(seed: int, frames: int = 40, width: int = 640, height: int = 480, detector: Any = None,
                         use_gt_map: bool = False, n_rays: int = 2000, n_points: int = 2000, n_pairs: int = 40,
                         radius: float = 0.1, agent_radius: float = 0.2, save_map: str | None = None,
                         gt_2d: str | None = None, track_classifier: str | None = None) -> dict[str, float]:
    """Render walk-through ``seed``, build its map (the detector on every frame fed to a
    ``SceneMap`` with the true poses; or the true scene with ``use_gt_map``) and score the
    queries on it. ``detector``: a ``ShapeDetector`` (the default one when None);
    ``save_map``: write the detector's map as scene JSON there; ``gt_2d``: the frames' true 2D
    boxes instead of the detector's proposals (:func:`~.runner.detect_walkthrough_frame`);
    ``track_classifier``: ``SceneConfig.track_classifier`` (None: the default)."""
    from ..synth.generate import SynthConfig
    from ..synth.walkthrough import walkthrough

    wt = walkthrough(int(seed), frames, config=SynthConfig(width=width, height=height))
    truth = truth_from_layout(wt.scene)
    cameras = [(T, f.K, f.depth.shape[1], f.depth.shape[0]) for T, f in zip(wt.poses, wt.frames)]
    if use_gt_map:
        m = gt_map(truth)
    else:
        from ..ar.scene_data import load_scene
        from ..poses import camera_up
        from ..scene import SceneConfig, SceneMap
        from .runner import detect_walkthrough_frame

        if detector is None:
            from ..detector import ShapeDetector

            detector = ShapeDetector()
        smap = SceneMap(SceneConfig() if track_classifier is None else SceneConfig(track_classifier=track_classifier))
        for f, T in zip(wt.frames, wt.poses):
            objs = detect_walkthrough_frame(detector, f, camera_up(T), gt_2d)
            smap.update(objs, T, f.depth, f.K, int(f.stamp_ns))
        if save_map:
            smap.save_json(save_map)
        m = load_scene(smap)
    rng = np.random.default_rng([int(seed), 27])
    out = evaluate_map(truth, m, cameras, seen_objects(wt.frames), rng, n_rays, n_points, n_pairs, radius,
                       agent_radius)
    out["objects_true"] = float(len(truth.objects.objects))
    out["objects_map"] = float(len(m.objects))
    return out
