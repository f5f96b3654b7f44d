"""Scene export: GLB / glTF / OBJ read back with trimesh (node names, counts, box sizes, bounds)."""

from __future__ import annotations

import argparse
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh
from ar_scenes import box_object, chair, scene_json, table, wall_grid

from shape_detector.ar import ArScene
from shape_detector.export import Z_UP_TO_Y_UP, export_scene
from shape_detector.export import cli as export_cli
from shape_detector.export.picture import write_picture
from shape_detector.geometry import box_corners


def _scene() -> ArScene:
    return ArScene([table(1, (1.0, 1.0), yaw=0.4), chair(2, (1.0, 3.0)),
                    box_object(3, "dresser", (3.0, 0.5, 0.6), (0.5, 1.0, 1.2), yaw=-0.3)], wall_grid())


def _expected_bounds(scene: ArScene) -> np.ndarray:
    corners = np.concatenate([box_corners(c, 2 * h, R) for c, h, R in
                              zip(scene.boxes.centers, scene.boxes.half, scene.boxes.rot)])
    y_up = corners @ Z_UP_TO_Y_UP[:3, :3].T
    return np.array([y_up.min(axis=0), y_up.max(axis=0)])


def _glb_json(path: Path) -> dict:
    data = path.read_bytes()
    n = struct.unpack("<I", data[12:16])[0]
    return json.loads(data[20 : 20 + n])


def test_glb_round_trip(tmp_path: Path) -> None:
    sc = _scene()
    (path,) = export_scene(sc, tmp_path / "scene.glb")
    back = trimesh.load(path)
    assert isinstance(back, trimesh.Scene)
    names = set(back.graph.nodes) - {back.graph.base_frame}
    expected = set()
    for o, n_parts in ((sc.objects[0], 5), (sc.objects[1], 2), (sc.objects[2], 1)):
        base = f"{o.class_name} #{o.id}"
        expected |= {base, f"{base} collider"}
        expected |= {f"{base} part {k}" for k in range(n_parts)} | {f"{base} collider {k}" for k in range(n_parts)}
    assert names == expected
    np.testing.assert_allclose(back.bounds, _expected_bounds(sc), atol=1e-4)
    # each part is a box of its primitive's size, placed where the primitive is (y-up)
    for o in sc.objects:
        boxes = [(p.center, p.size, p.rotation) for p in o.primitives] or [(o.center, o.size, o.rotation)]
        for k, (center, size, rotation) in enumerate(boxes):
            node = f"{o.class_name} #{o.id} part {k}"
            T, geom = back.graph[node]
            mesh = back.geometry[geom].copy().apply_transform(T)
            want = box_corners(center, size, rotation) @ Z_UP_TO_Y_UP[:3, :3].T
            np.testing.assert_allclose(mesh.bounds, [want.min(axis=0), want.max(axis=0)], atol=1e-4)
    tree = _glb_json(path)
    assert sorted(m["name"] for m in tree["materials"]) == ["chair", "dresser", "table"]
    extras = {n["name"]: n.get("extras") for n in tree["nodes"]}
    assert extras["table #1 collider 0"]["collider"] == "box"
    np.testing.assert_allclose(sorted(extras["table #1 collider 0"]["size"]), [0.05, 0.6, 1.0], atol=1e-5)
    assert extras["table #1 part 0"] is None
    assert extras["dresser #3"] == {"class": "dresser", "id": 3, "score": 1.0}


def test_class_probabilities_reach_the_node_extras(tmp_path: Path) -> None:
    sc = _scene()
    sc.objects[0].class_probs = {"table": 0.7, "desk": 0.25}
    (path,) = export_scene(sc, tmp_path / "scene.glb")
    extras = {n["name"]: n.get("extras") for n in _glb_json(path)["nodes"]}
    assert extras["table #1"]["class_probs"] == {"table": 0.7, "desk": 0.25}
    assert "class_probs" not in extras["dresser #3"]


def test_no_colliders_and_gltf(tmp_path: Path) -> None:
    sc = _scene()
    (path,) = export_scene(sc, tmp_path / "scene.gltf", colliders=False)
    back = trimesh.load(path)
    assert isinstance(back, trimesh.Scene)
    assert not any("collider" in n for n in back.graph.nodes)
    assert len(back.geometry) == 8
    np.testing.assert_allclose(back.bounds, _expected_bounds(sc), atol=1e-4)


def test_obj_with_material_library(tmp_path: Path) -> None:
    files = export_scene(_scene(), tmp_path / "scene.obj")
    assert [f.name for f in files] == ["scene.obj", "scene.mtl"]
    text = files[0].read_text()
    assert "mtllib scene.mtl" in text and "o table_1_part_0" in text and "o dresser_3_collider_0" in text
    assert "#1" not in text.split("\n", 1)[1]  # '#' starts an OBJ comment: never inside names
    back = trimesh.load(files[0], force="mesh")
    np.testing.assert_allclose(back.bounds, _expected_bounds(_scene()), atol=1e-4)


def test_bad_requests(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="format"):
        export_scene(_scene(), tmp_path / "scene.fbx")
    with pytest.raises(ValueError, match="no objects"):
        export_scene(ArScene([]), tmp_path / "scene.glb")


def test_cli_and_picture(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    src = tmp_path / "scene.json"
    src.write_text(json.dumps(scene_json(_scene())))
    p = argparse.ArgumentParser()
    export_cli.configure_parser(p)
    out = tmp_path / "out" / "scene.glb"
    assert export_cli.main(p.parse_args([str(src), "-o", str(out), "--picture", str(tmp_path / "s.png")])) == 0
    assert out.is_file() and (tmp_path / "s.png").stat().st_size > 1000
    assert "3 objects" in capsys.readouterr().out
    assert export_cli.main(p.parse_args([str(tmp_path / "missing.json"), "-o", str(out)])) == 2
    img = write_picture(_scene(), tmp_path / "p.png")
    assert img.stat().st_size > 1000
