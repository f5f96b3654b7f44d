"""Ray casts onto observed surface points (``SceneObject.surface``), and the memory that keeps them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ar_scenes import box_object, rotz
from shape_detector.ar import SceneQueries, load_scene, raycast, raycast_many
from shape_detector.ar.bench import face_points
from shape_detector.ar.scene_data import ArScene
from shape_detector.ar.surface_rays import build_index, cast
from shape_detector.scene import SceneConfig, SceneMap
from shape_detector.scene.surface import SurfaceMemory, points_in_boxes
from shape_detector.scene.types import SceneObject, ScenePrimitive
from test_scene_support import K, detection, pose, render, room


def _plane_x(x: float, y0: float, y1: float, z0: float, z1: float, step: float = 0.01, noise: float = 0.0,
             seed: int = 0) -> np.ndarray:
    """Voxel means of a plane x = const, as the scene map keeps observed points."""
    ys, zs = np.meshgrid(np.arange(y0, y1, step), np.arange(z0, z1, step))
    p = np.stack([np.full(ys.size, x), ys.ravel(), zs.ravel()], axis=1)
    p[:, 0] += np.random.default_rng(seed).normal(0.0, noise, len(p))
    mem = SurfaceMemory(0.02)
    mem.add(p)
    return mem.points()


def _dresser(surface: np.ndarray | None) -> SceneObject:
    """A 1 m box standing at x in [-0.5, 0.5] whose front face the camera saw at x = 0.40."""
    return replace(box_object(7, "dresser", (0.0, 0.0, 0.5), (1.0, 1.0, 1.0)), surface=surface)


def test_memory_keeps_voxel_means_and_counts() -> None:
    mem = SurfaceMemory(0.1)
    mem.add(np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.07], [np.nan, 0.0, 0.0]]))
    mem.add(np.array([[0.05, 0.03, 0.02], [0.55, 0.0, 0.0]]))
    pts, counts = mem.points(), mem.counts()
    assert len(mem) == 2
    first = np.argmin(pts[:, 0])
    np.testing.assert_allclose(pts[first], [0.03, 0.03, 0.1 / 3], atol=1e-9)
    assert sorted(counts.tolist()) == [1, 3]


def test_memory_merged_in_batches_keeps_every_voxel_mean(monkeypatch: pytest.MonkeyPatch) -> None:
    import shape_detector.scene.surface as surface

    monkeypatch.setattr(surface, "PENDING_MIN", 500)  # many merges into a growing memory
    rng = np.random.default_rng(3)
    frames = [rng.uniform(-1.0, 1.0, (400, 3)) + rng.uniform(-2.0, 2.0, 3) for _ in range(30)]
    mem = SurfaceMemory(0.1)
    for i, p in enumerate(frames):
        mem.add(p, weight=1 + i % 2)
    allp = np.concatenate(frames)
    w = np.repeat([1 + i % 2 for i in range(len(frames))], 400)
    keys, inv = np.unique(np.floor(allp / 0.1).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    counts = np.bincount(inv, w)
    means = np.stack([np.bincount(inv, allp[:, k] * w) for k in range(3)], axis=1) / counts[:, None]
    assert len(mem) == len(keys)
    order = np.lexsort(mem.points().T[::-1])
    want = np.lexsort(means.T[::-1])
    np.testing.assert_allclose(mem.points()[order], means[want], atol=1e-9)
    np.testing.assert_array_equal(mem.counts()[order], counts[want])
    assert len(mem.points(min_count=3)) == int(np.sum(counts >= 3))


def test_memory_sorted_runs_merge_like_one_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    """Frames of negative and positive coordinates, empty and all-NaN frames and reads between
    merges: the memory holds what one pass over every finite point gives."""
    import shape_detector.scene.surface as surface

    monkeypatch.setattr(surface, "PENDING_MIN", 300)
    rng = np.random.default_rng(11)
    mem = SurfaceMemory(0.05)
    kept = []
    for i in range(40):
        p = rng.normal(0.0, 0.4, (rng.integers(0, 250), 3)) + rng.uniform(-3.0, 3.0, 3)
        if i % 7 == 3:
            p[::3] = np.nan
        if i % 11 == 5:
            p = np.full((10, 3), np.inf)
        mem.add(p)
        kept.append(p[np.isfinite(p).all(axis=1)])
        if i % 13 == 0:
            assert len(mem.points()) == len(np.unique(np.floor(np.concatenate(kept) / 0.05), axis=0))
    allp = np.concatenate(kept)
    keys, inv, counts = np.unique(np.floor(allp / 0.05).astype(np.int64), axis=0, return_inverse=True,
                                  return_counts=True)
    means = np.stack([np.bincount(inv.ravel(), allp[:, k]) for k in range(3)], axis=1) / counts[:, None]
    got = mem.points()
    np.testing.assert_allclose(got[np.lexsort(got.T[::-1])], means[np.lexsort(means.T[::-1])], atol=1e-9)
    assert sorted(mem.counts().tolist()) == sorted(counts.tolist())


def test_memory_bound_drops_the_least_seen_voxels() -> None:
    mem = SurfaceMemory(0.1, max_voxels=2)
    for _ in range(3):
        mem.add(np.array([[0.05, 0.05, 0.05], [1.05, 0.05, 0.05]]))
    mem.add(np.array([[2.05, 0.05, 0.05]]))
    assert len(mem) == 2
    assert np.all(mem.points()[:, 0] < 1.5)
    with pytest.raises(ValueError):
        SurfaceMemory(0.0)


def test_points_in_boxes_uses_the_box_axes_and_the_pad() -> None:
    box = box_object(1, "table", (0.0, 0.0, 0.5), (2.0, 0.2, 1.0), yaw=np.pi / 4)
    along = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0])
    pts = np.array([0.9 * along + [0, 0, 0.5], [0.0, 0.9, 0.5], 0.0 * along + [0, 0, 1.04]])
    inside, = points_in_boxes(pts, [box], pad=0.05)
    assert len(inside) == 2  # along the long axis and just above the top; not beside it
    assert len(points_in_boxes(pts, [box], pad=0.0)[0]) == 1


def test_ray_lands_on_the_observed_face_not_the_box() -> None:
    scene = ArScene([_dresser(_plane_x(0.40, -0.45, 0.45, 0.05, 0.95))])
    hit = raycast(scene, (3.0, 0.1, 0.6), (-1.0, 0.0, 0.0))
    assert hit is not None and hit.object_id == 7
    assert hit.distance == pytest.approx(2.60, abs=0.01)
    np.testing.assert_allclose(hit.normal, [1.0, 0.0, 0.0], atol=0.05)
    assert hit.primitive_index == -1
    box_only = raycast(scene, (3.0, 0.1, 0.6), (-1.0, 0.0, 0.0), surfaces=False)
    assert box_only.distance == pytest.approx(2.50, abs=1e-6)
    q = SceneQueries(scene)
    assert q.raycast((3.0, 0.1, 0.6), (-1.0, 0.0, 0.0)).distance == pytest.approx(2.60, abs=0.01)
    assert q.raycast_many(np.array([[3.0, 0.1, 0.6]]), (-1.0, 0.0, 0.0), surfaces=False).distance[0] == \
        pytest.approx(2.50, abs=1e-6)


def test_noise_along_the_ray_averages_out() -> None:
    scene = ArScene([_dresser(_plane_x(0.40, -0.45, 0.45, 0.05, 0.95, noise=0.01, seed=3))])
    o = np.column_stack([np.full(50, 3.0), np.linspace(-0.3, 0.3, 50), np.full(50, 0.5)])
    hits = raycast_many(scene, o, (-1.0, 0.0, 0.0))
    assert np.all(np.abs(hits.distance - 2.60) < 0.02)


def test_where_nothing_was_observed_the_box_answers() -> None:
    scene = ArScene([_dresser(_plane_x(0.40, -0.45, 0.0, 0.05, 0.95))])  # only half the face was seen
    hits = raycast_many(scene, np.array([[3.0, -0.2, 0.5], [3.0, 0.3, 0.5]]), (-1.0, 0.0, 0.0))
    np.testing.assert_allclose(hits.distance, [2.60, 2.50], atol=0.01)
    assert hits.box_index[0] == -1 and hits.box_index[1] >= 0
    assert raycast(scene, (3.0, 3.0, 0.5), (-1.0, 0.0, 0.0)) is None


def test_the_floor_hides_what_lies_below_it_and_rays_pass_beside_points() -> None:
    below = _dresser(_plane_x(0.40, -0.45, 0.45, -0.9, -0.1))  # points under the floor (z = 0)
    scene = ArScene([below], floor_z=0.0)
    hit = raycast(scene, (3.0, 0.0, 1.0), (-1.0, 0.0, -0.5))
    assert hit is not None and hit.object_id == 0
    beside = raycast(ArScene([_dresser(_plane_x(0.40, -0.45, 0.45, 0.05, 0.95))], floor_z=0.0),
                     (3.0, 0.48, 0.5), (-1.0, 0.0, 0.0))
    assert beside is not None and beside.distance == pytest.approx(2.50, abs=1e-6)  # beside the face: its box


@pytest.mark.parametrize("cluster", [0.03, 0.12])
def test_index_matches_a_brute_force_tube(cluster: float) -> None:
    rng = np.random.default_rng(5)
    parts = [ScenePrimitive(rng.uniform(-0.4, 0.4, 3) + [0, 0, 0.5], rng.uniform(0.05, 0.6, 3), rotz(rng.uniform(-3, 3)))
             for _ in range(6)]
    pts = face_points(parts)
    index = build_index([(1, pts, np.eye(3))], cluster=cluster)
    o = rng.uniform([2.0, -1.0, 0.2], [3.0, 1.0, 1.5], (300, 3))
    d = pts[rng.integers(0, len(pts), 300)] + rng.normal(0.0, 0.03, (300, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got, oid, _ = cast(index, o, d, np.full(300, np.inf))
    want = np.full(300, np.inf)
    for i in range(300):
        v = pts - o[i]
        t = v @ d[i]
        inside = (np.einsum("ij,ij->i", v, v) - t * t <= index.tube ** 2) & (t > 0.05)
        if inside.any():
            tc = np.sort(t[inside])
            want[i] = np.median(tc[tc <= tc[0] + index.cluster])
    assert np.isfinite(want).sum() > 200
    assert not np.any(np.isfinite(got) & ~np.isfinite(want))  # the index never invents a hit
    same = np.isclose(got, want, atol=1e-3) | ~np.isfinite(want)
    assert same.mean() >= 0.97  # and rarely gives up early on a grazed edge
    assert set(oid[np.isfinite(got)].tolist()) == {1}


def test_surface_json_round_trip_to_the_millimetre(tmp_path) -> None:
    obj = _dresser(_plane_x(0.40, -0.45, 0.45, 0.05, 0.95))
    back = SceneObject.from_dict(obj.to_dict())
    np.testing.assert_allclose(back.surface, obj.surface, atol=6e-4)
    assert "surface" not in _dresser(None).to_dict()
    bad = obj.to_dict()
    bad["surface"]["encoding"] = "png"
    with pytest.raises(ValueError):
        SceneObject.from_dict(bad)


def test_scene_map_keeps_what_the_depth_saw_and_saves_it(tmp_path) -> None:
    T = pose(0.0, 0.0, 1.2, 0.0)
    chest = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)
    m = SceneMap(SceneConfig(floor_z=0.0, depth_stride=2))  # the test frames are 160 x 120
    depth = render(room([chest]), T)
    for i in range(4):
        m.update([detection(*chest, T)], T, depth, K, stamp_ns=i)
    (obj,) = m.objects(surfaces=True)
    assert obj.surface is not None and len(obj.surface) > 20
    front = obj.surface[obj.surface[:, 0] < 2.8]
    assert len(front) > 10 and np.all(np.abs(front[:, 0] - 2.75) < 0.02)  # the face the camera sees
    assert m.objects()[0].surface is None  # only when asked: it costs a pass over the points
    path = tmp_path / "scene.json"
    m.save_json(path)
    scene = load_scene(path)
    hit = raycast(scene, (0.0, 0.0, 0.5), (1.0, 0.0, 0.0))
    assert hit is not None and hit.distance == pytest.approx(2.75, abs=0.02)
    again = SceneMap.from_json(path)
    assert len(again.objects(surfaces=True)[0].surface) == len(obj.surface)
    off = SceneMap(SceneConfig(floor_z=0.0, surface_voxel=0.0))
    off.update([detection(*chest, T)], T, depth, K, stamp_ns=0)
    assert off.surface is None


def test_rays_stop_at_observed_surfaces_no_object_claims() -> None:
    """A wall the camera saw (no object's box holds it) stops rays, as STRUCTURE_ID; the
    dresser's own points stay the dresser's."""
    from shape_detector.ar import STRUCTURE_ID
    from shape_detector.scene.surface import split_points

    wall = _plane_x(3.0, -2.0, 2.0, 0.1, 2.4)
    front = _plane_x(0.40, -0.45, 0.45, 0.05, 0.95)
    (claimed,), rest = split_points(np.concatenate([front, wall]), [_dresser(None)], pad=0.1)
    assert len(claimed) == len(front) and len(rest) == len(wall)
    sc = ArScene([_dresser(None)], observed=(np.concatenate([front, wall]), 0.1))
    assert len(sc.structure_points) == len(wall)
    hits = raycast_many(sc, np.array([[-2.0, 0.0, 0.5], [-2.0, 1.0, 0.5]]), np.array([[1.0, 0.0, 0.0]] * 2))
    np.testing.assert_allclose(hits.distance, [2.40, 5.0], atol=0.02)  # the dresser's front; the wall beside it
    assert hits.object_id.tolist() == [7, STRUCTURE_ID]
    assert raycast_many(ArScene([_dresser(None)]), [-2.0, 1.0, 0.5], [1.0, 0.0, 0.0]).hit.tolist() == [False]
    none = ArScene([], observed=(wall, 0.1))  # no objects at all: all of it is structure
    assert raycast(none, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]).object_id == STRUCTURE_ID


def test_structure_survives_the_json_round_trip(tmp_path) -> None:
    from shape_detector.ar import STRUCTURE_ID

    m = SceneMap(SceneConfig(floor_z=0.0))
    m.surface.add(_plane_x(3.0, -2.0, 2.0, 0.1, 2.4), weight=2)
    doc = m.to_json()
    assert doc["structure"]["count"] > 1000
    sc = load_scene(doc)
    assert raycast(sc, [0.0, 0.5, 1.0], [1.0, 0.0, 0.0]).object_id == STRUCTURE_ID
    np.testing.assert_allclose(raycast(sc, [0.0, 0.5, 1.0], [1.0, 0.0, 0.0]).distance, 3.0, atol=0.01)
    back = SceneMap.from_json(doc)
    assert len(back.surface_points()) == len(m.surface_points())
    bad = dict(doc, structure={"center": [0, 0, 0], "encoding": "base64-int16-mm-from-center", "count": 5,
                               "data": "AAAA"})
    with pytest.raises(ValueError):
        load_scene(bad)
    old = {k: v for k, v in doc.items() if k != "structure"}  # a map written before structure
    assert load_scene(old).structure_points is None


def test_split_points_gives_each_point_to_the_first_box_holding_it() -> None:
    from shape_detector.geometry import points_in_box
    from shape_detector.scene.surface import split_points

    rng = np.random.default_rng(5)
    boxes = [box_object(i + 1, "table", rng.uniform(-2, 2, 3), rng.uniform(0.3, 1.5, 3), yaw=rng.uniform(0, np.pi))
             for i in range(12)]
    pts = rng.uniform(-3, 3, (5000, 3))
    per_box, rest = split_points(pts, boxes, pad=0.05)
    owner = np.full(len(pts), -1)
    for k, b in reversed(list(enumerate(boxes))):  # the first box that holds a point wins
        owner[points_in_box(pts, b.center, b.size, b.rotation, 0.05)] = k
    for k, got in enumerate(per_box):
        np.testing.assert_array_equal(got, pts[owner == k])  # in the input's order
    np.testing.assert_array_equal(rest, pts[owner < 0])
    assert (owner >= 0).sum() > 200
