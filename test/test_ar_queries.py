"""SceneQueries on a scene loaded from the --scene-out JSON, and loader errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from ar_scenes import chair, scene_json, table, wall_grid

from shape_detector.ar import ArScene, SceneQueries, load_scene


def _scene() -> ArScene:
    return ArScene([table(1, (1.0, 1.0)), chair(2, (1.0, 3.0))], wall_grid(gap=True))


def test_load_from_json_file(tmp_path: Path) -> None:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene_json(_scene())))
    q = SceneQueries.load(path)
    assert [o.id for o in q.scene.objects] == [1, 2]
    assert len(q.scene.boxes) == 7
    np.testing.assert_array_equal(q.grid.data, wall_grid(gap=True).data)
    hit = q.raycast([1.0, 1.0, 2.0], [0.0, 0.0, -1.0])
    assert hit is not None and hit.object_id == 1 and abs(hit.distance - 1.25) < 1e-5
    assert q.collides([1.0, 3.0, 0.5], radius=0.1)
    assert q.contacts(np.array([[1.0, 3.0, 0.5]]), 0.1) == [(2, 0)]
    path_xy = q.plan((1.0, 0.5), (3.0, 0.5), agent_radius=0.2)
    assert path_xy is not None and path_xy[-1] == (3.0, 0.5)
    assert [s.affordance for s in q.surfaces()] == ["place", "sit"]


def test_graph_is_cached_per_radius() -> None:
    q = SceneQueries(_scene())
    q.plan((1.0, 0.5), (3.0, 0.5), 0.2)
    g = q.graph(0.2)
    q.plan((1.0, 0.5), (1.0, 3.5), 0.2)
    assert q.graph(0.2) is g and q.graph(0.3) is not g


def test_loader_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        SceneQueries.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError):
        load_scene(bad)
    with pytest.raises(ValueError):
        load_scene({"objects": [{"id": 1}]})
    with pytest.raises(ValueError):
        load_scene(42)
    with pytest.raises(ValueError, match="objects"):
        load_scene({"frame_id": "odom"})
    with pytest.raises(ValueError, match="mistypes"):
        load_scene({"objects": [{"id": 1, "class": "chair", "center": [0, 0, 0.4], "size": [1, 1, 1],
                                 "rotation": np.eye(3).tolist(), "class_probs": ["chair"]}]})
    with pytest.raises(ValueError):  # non-finite numbers are refused, not queried
        load_scene({"objects": [{"id": 1, "class": "chair", "center": [0, 0, float("nan")], "size": [1, 1, 1],
                                 "rotation": np.eye(3).tolist()}]})


def test_from_objects_shaped_like_scene_objects() -> None:
    class Obj:  # duck-typed SceneObject
        id, class_name, score = 4, "desk", 0.9
        center, size, rotation, primitives = np.array([0, 0, 0.37]), np.array([0.7, 1.4, 0.74]), np.eye(3), []

    q = SceneQueries([Obj()])
    assert q.collides([0.0, 0.0, 0.7]) and q.grid is None
    with pytest.raises(ValueError):
        q.plan((0, 0), (1, 1))


def test_live_scene_map() -> None:
    scene_pkg = pytest.importorskip("shape_detector.scene")
    m = scene_pkg.SceneMap.from_json(scene_json(_scene()))
    q = SceneQueries(m)
    assert sorted((o.id, o.class_name, len(o.primitives)) for o in q.scene.objects) == [(1, "table", 5), (2, "chair", 2)]
    hit = q.raycast([1.0, 1.0, 2.0], [0.0, 0.0, -1.0])
    assert hit is not None and hit.object_id == 1 and abs(hit.distance - 1.25) < 0.02
    assert q.grid is not None and q.grid.data.size > 0


def test_empty_grid_plans_nothing() -> None:
    from shape_detector.scene.grid import NavGrid

    q = SceneQueries(ArScene([], NavGrid(0.05, np.zeros(2), np.zeros((0, 0), np.int8))))
    assert q.plan((0.0, 0.0), (1.0, 1.0)) is None
