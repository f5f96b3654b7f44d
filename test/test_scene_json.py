"""Scene map JSON: round trip of objects and grid; a loaded map keeps updating."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shape_detector.scene import SceneConfig, SceneMap
from test_scene_support import K, detection, pose, render, room

T0 = pose(0.0, 0.0, 1.2, 0.0)
CHAIR = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.2)
SEAT = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.05))


def _map() -> SceneMap:
    m = SceneMap()
    d = render(room([CHAIR]), T0)
    for i in range(4):
        m.update([detection(*CHAIR, T0, score=0.9, parts=[SEAT])], T0, d, K, stamp_ns=1_000 + i)
    return m


def test_round_trip(tmp_path):
    m = _map()
    path = tmp_path / "scene.json"
    m.save_json(path)
    doc = json.loads(path.read_text())
    assert doc["frame_id"] == "odom" and doc["stamp_ns"] == 1_003
    o = doc["objects"][0]
    assert set(o) >= {"id", "class", "score", "center", "size", "rotation", "yaw", "observations",
                      "first_seen_ns", "last_seen_ns", "primitives"}
    assert {"resolution", "origin", "width", "height"} <= set(doc["grid"])
    back = SceneMap.from_json(path)
    assert back.frame_id == "odom" and back.stamp_ns == m.stamp_ns
    a, b = m.objects()[0], back.objects()[0]
    assert (a.id, a.class_name, a.observations, a.first_seen_ns, a.last_seen_ns) == \
        (b.id, b.class_name, b.observations, b.first_seen_ns, b.last_seen_ns)
    assert abs(a.score - b.score) < 1e-9 and abs(a.yaw - b.yaw) < 1e-9
    for x, y in ((a.center, b.center), (a.size, b.size), (a.rotation, b.rotation)):
        np.testing.assert_allclose(x, y, atol=1e-9)
    np.testing.assert_allclose(a.primitives[0].center, b.primitives[0].center, atol=1e-9)
    np.testing.assert_allclose(a.primitives[0].size, b.primitives[0].size, atol=1e-9)
    ga, gb = m.grid(), back.grid()
    assert (ga.width, ga.height) == (gb.width, gb.height)
    np.testing.assert_allclose(ga.origin, gb.origin, atol=1e-9)
    assert np.array_equal(ga.data, gb.data)
    assert SceneMap.from_json(doc).objects()[0].id == a.id  # a dict works too


def test_face_spread_survives_the_round_trip_and_old_documents_load():
    m = SceneMap()
    for i, x in enumerate([3.0, 3.1, 2.9, 3.1]):
        m.update([detection((x, 0.0, 0.45), CHAIR[1], 0.0, T0, score=0.9)], T0, None, None, stamp_ns=i)
    a = m.objects()[0]
    assert np.all(a.face_sd[:2] > 0.03) and np.all(a.face_sd[2:] < 1e-9)  # the boxes moved along x
    doc = m.to_json()
    np.testing.assert_allclose(SceneMap.from_json(doc).objects()[0].face_sd, a.face_sd, atol=1e-4)
    for o in doc["objects"]:
        del o["face_sd"]
    assert np.all(SceneMap.from_json(doc).objects()[0].face_sd == 0.0)


def test_class_probabilities_are_published_saved_and_restored():
    evidence = SceneConfig(track_classifier="")  # the class evidence's own bookkeeping
    m = SceneMap(evidence)
    for i, cls in enumerate(["desk", "table", "desk", "desk"]):
        m.update([detection(*CHAIR, T0, cls=cls, score=0.9)], T0, None, None, stamp_ns=i)
    a = m.objects()[0]
    assert a.class_name == "desk" and set(a.class_probs) == {"desk", "table"}
    assert a.class_probs["desk"] > a.class_probs["table"] > 0.1
    assert 0.85 < sum(a.class_probs.values()) <= 1.0 + 1e-9  # the eight others under 5% each are left out
    doc = m.to_json()
    assert doc["objects"][0]["class_probs"] == pytest.approx(a.class_probs, abs=1e-3)
    back = SceneMap.from_json(doc, evidence)
    assert back.objects()[0].class_probs == pytest.approx(a.class_probs, abs=2e-3)
    # the restored evidence keeps the runner-up: two more "table" frames tip the class
    for i in range(2):
        back.update([detection(*CHAIR, T0, cls="table", score=0.9)], T0, None, None, stamp_ns=10 + i)
    assert back.objects()[0].class_probs["table"] > a.class_probs["table"]
    for o in doc["objects"]:  # documents without class_probs (and inconsistent ones) load one-hot
        o["class_probs"] = {"table": 1.0} if o is doc["objects"][0] else {}
    assert SceneMap.from_json(doc, evidence).objects()[0].class_probs == {"desk": 1.0}


def test_loaded_map_keeps_updating_with_the_same_id():
    back = SceneMap.from_json(_map().to_json())
    back.update([detection(*CHAIR, T0)], T0, None, None, stamp_ns=5_000)
    objs = back.objects()
    assert len(objs) == 1 and objs[0].id == 1 and objs[0].last_seen_ns == 5_000
    new = detection((3.0, 2.0, 0.4), (0.5, 0.5, 0.8), 0.0, T0)
    for i in range(3):
        back.update([new], T0, None, None, stamp_ns=6_000 + i)
    assert [o.id for o in back.objects()] == [1, 2]


def test_bad_documents_raise_clearly(tmp_path):
    with pytest.raises(ValueError, match="scene map"):
        SceneMap.from_json({"objects": []})
    doc = _map().to_json()
    doc["grid"]["width"] += 1
    with pytest.raises(ValueError, match="grid data"):
        SceneMap.from_json(doc)
    for field, bad in (("center", None), ("class_probs", ["desk"]), ("size", [1.0, 2.0])):
        doc = _map().to_json()
        doc["objects"][0][field] = bad
        with pytest.raises(ValueError, match="object 0"):
            SceneMap.from_json(doc)
