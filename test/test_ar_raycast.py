"""Ray casts against hand-made scenes: distances, object ids, normals, floor, batches."""

from __future__ import annotations

import numpy as np
from ar_scenes import box_object, table

from shape_detector.ar import FLOOR_ID, ArScene, raycast, raycast_many


def _scene() -> ArScene:
    return ArScene([table(2, (0.0, 0.0)), box_object(5, "dresser", (3.0, 0.0, 0.6), (0.5, 1.0, 1.2), yaw=np.pi / 4)])


def test_down_onto_table_top() -> None:
    hit = raycast(_scene(), [0.1, 0.1, 2.0], [0.0, 0.0, -3.0])
    assert hit is not None and hit.object_id == 2 and hit.primitive_index == 0
    assert abs(hit.distance - 1.25) < 1e-5
    np.testing.assert_allclose(hit.normal, [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(hit.point, [0.1, 0.1, 0.75], atol=1e-5)


def test_under_the_table_hits_the_floor() -> None:
    hit = raycast(_scene(), [0.0, 0.0, 0.5], [0.0, 0.0, -1.0])
    assert hit is not None and hit.object_id == FLOOR_ID
    assert abs(hit.distance - 0.5) < 1e-9
    assert raycast(_scene(), [0.0, 0.0, 0.5], [0.0, 0.0, -1.0], max_distance=0.4) is None


def test_side_of_rotated_box_normal() -> None:
    # the dresser turned 45 degrees: aim at the middle of its back face (normal = -its x axis),
    # 0.25 m (half its depth) behind its centre, from 2 m out along that normal
    n = -np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0])
    face_center = np.array([3.0, 0.0, 0.6]) + 0.25 * n
    origin = face_center + 2.0 * n
    hit = raycast(_scene(), origin, face_center - origin)
    assert hit is not None and hit.object_id == 5 and hit.primitive_index == -1
    assert abs(hit.distance - 2.0) < 1e-5
    np.testing.assert_allclose(hit.normal, n, atol=1e-6)


def test_misses_and_origin_inside() -> None:
    sc = _scene()
    assert raycast(sc, [0.0, 0.0, 2.0], [0.0, 0.0, 1.0]) is None  # up, nothing above
    assert raycast(sc, [0.0, 0.0, 2.0], [0.0, 0.0, 1.0], max_distance=10) is None
    # from inside the table top looking up: the top is ignored
    assert raycast(sc, [0.0, 0.0, 0.72], [0.0, 0.0, 1.0]) is None
    assert raycast(sc, [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]) is None  # zero direction
    assert raycast(ArScene([]), [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]) is None


def test_batch_matches_single() -> None:
    sc = _scene()
    rng = np.random.default_rng(1)
    o = rng.uniform([-1, -1, 1.0], [4, 2, 2.0], (200, 3))
    d = rng.normal(size=(200, 3))
    hits = raycast_many(sc, o, d)
    for k in range(0, 200, 7):
        h = raycast(sc, o[k], d[k])
        if h is None:
            assert not hits.hit[k]
        else:
            assert hits.object_id[k] == h.object_id and abs(hits.distance[k] - h.distance) < 1e-9
    assert hits.hit.sum() > 50


def _slab_reference(o: np.ndarray, d: np.ndarray, c: np.ndarray, half: np.ndarray, R: np.ndarray) -> float:
    """Entry distance of one ray into one box (inf: none, or the origin inside), plainly."""
    ol, dl = (o - c) @ R, d @ R
    lo, hi = -np.inf, np.inf
    for k in range(3):
        if abs(dl[k]) < 1e-20:
            if abs(ol[k]) > half[k]:
                return np.inf
            continue
        t1, t2 = sorted(((-half[k] - ol[k]) / dl[k], (half[k] - ol[k]) / dl[k]))
        lo, hi = max(lo, t1), min(hi, t2)
    return lo if 0.0 < lo <= hi else np.inf


def test_compiled_slab_test_matches_a_plain_one_and_skips_bad_rays() -> None:
    from shape_detector.ar.box_rays import first_boxes

    sc = _scene()
    b = sc.boxes
    rng = np.random.default_rng(3)
    o = rng.uniform([-1, -1, 0.1], [4, 2, 2.0], (300, 3))
    d = b.centers[rng.integers(0, len(b.centers), 300)] + rng.normal(0.0, 0.3, (300, 3)) - o  # aimed near boxes
    d[:40, 2] = 0.0  # parallel to the tops
    d[40:60, :2] = 0.0  # straight up or down
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dist, box, normal = first_boxes(o, d, b.centers, b.half, b.rot, np.inf)
    want = np.array([[_slab_reference(o[i], d[i], b.centers[p], b.half[p], b.rot[p]) for p in range(len(b.centers))]
                     for i in range(len(o))])
    np.testing.assert_allclose(dist, want.min(1), rtol=1e-9, atol=1e-9)
    hit = np.isfinite(dist)
    assert hit.sum() > 100 and np.all(box[hit] == want[hit].argmin(1)) and np.all(box[~hit] == -1)
    np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=1), 1.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", normal[hit], d[hit]) < 0)  # the face entered faces the ray
    bad = raycast_many(sc, [[np.nan, 0.0, 2.0], [0.0, 0.0, 2.0]], [[0.0, 0.0, -1.0], [np.inf, 0.0, 0.0]])
    assert not bad.hit.any() and np.all(bad.object_id == -1)


def test_a_batch_split_over_two_threads_gives_the_serial_answers(monkeypatch) -> None:
    import shape_detector.ar.row_split as row_split
    from shape_detector.ar.bench import bench_scene

    scene = bench_scene(n_objects=8)  # primitives, observed surfaces and structure
    rng = np.random.default_rng(4)
    o = np.column_stack([rng.uniform(0, 10, (400, 2)), rng.uniform(1.2, 1.8, 400)])
    d = np.array([scene.objects[k].center for k in rng.integers(0, len(scene.objects), 400)]) - o
    monkeypatch.setattr(row_split, "usable_cores", lambda: 1)
    serial = raycast_many(scene, o, d)
    monkeypatch.setattr(row_split, "usable_cores", lambda: 2)
    monkeypatch.setattr(row_split, "MIN_ROWS", 2)
    split = raycast_many(scene, o, d)
    assert serial.hit.sum() > 200
    for field in ("distance", "object_id", "normal", "box_index"):
        np.testing.assert_array_equal(getattr(serial, field), getattr(split, field))
