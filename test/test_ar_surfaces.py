"""Usable top faces and affordances of hand-made furniture."""

from __future__ import annotations

import numpy as np
from ar_scenes import bed, box_object, chair, table

from shape_detector.ar import ArScene, surfaces
from shape_detector.scene.types import ScenePrimitive


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_table_top_only() -> None:
    s = surfaces(ArScene([table(4, (1.0, 2.0), yaw=0.3)]))
    assert len(s) == 1  # the legs' tops are covered by the top slab
    top = s[0]
    assert (top.object_id, top.class_name, top.affordance, top.primitive_index) == (4, "table", "place", 0)
    assert abs(top.height - 0.75) < 1e-9
    assert top.polygon.shape == (4, 2)
    assert abs(_area(top.polygon) - 0.6) < 1e-9  # counter-clockwise, 1.0 m x 0.6 m
    np.testing.assert_allclose(top.polygon.mean(axis=0), [1.0, 2.0], atol=1e-9)


def test_chair_seat_not_back() -> None:
    s = surfaces(ArScene([chair(2, (0.0, 0.0))]))
    assert [(x.affordance, round(x.height, 3)) for x in s] == [("sit", 0.45)]  # the 5 cm back top is too thin


def test_bed_mattress_lie_and_sit() -> None:
    s = surfaces(ArScene([bed(9, (0.0, 0.0))]))
    assert len(s) == 1  # the frame is under the mattress
    assert s[0].affordance == "lie" and s[0].affordances == ("lie", "sit")
    assert abs(s[0].height - 0.55) < 1e-9 and abs(s[0].area - 1.95 * 1.55) < 1e-9


def test_classes_without_affordance_and_boxes_without_primitives() -> None:
    sc = ArScene([box_object(1, "toilet", (0, 0, 0.4), (0.7, 0.45, 0.8)),
                  box_object(2, "dresser", (2, 0, 0.6), (0.5, 1.0, 1.2), yaw=0.5),
                  box_object(3, "bookshelf", (4, 0, 1.5), (0.4, 1.0, 3.0))])  # 3 m: too tall to place on
    s = surfaces(sc)
    assert [(x.object_id, x.affordance, x.primitive_index) for x in s] == [(2, "place", -1)]
    assert abs(s[0].height - 1.2) < 1e-9


def test_tilted_box_has_no_top() -> None:
    o = box_object(1, "table", (0, 0, 0.4), (1.0, 1.0, 0.8))
    a = np.radians(30)
    o.rotation = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    assert surfaces(ArScene([o])) == []


def test_level_faces_merge_and_level_neighbours_do_not_cover() -> None:
    o = table(1, (0.0, 0.0))
    # a pedestal whose top is level with the table top: one surface, not two
    o.primitives.append(ScenePrimitive(np.array([0.0, 0.0, 0.375]), np.array([0.3, 0.3, 0.75]), np.eye(3)))
    s = surfaces(ArScene([o]))
    assert [x.primitive_index for x in s] == [0]
    # a cushion level with the top of the base it sits in stays a seat
    c = chair(2, (0.0, 0.0))
    c.primitives.append(ScenePrimitive(np.array([0.05, 0.0, 0.43]), np.array([0.4, 0.4, 0.04]), np.eye(3)))
    c.primitives[0] = ScenePrimitive(np.array([0.0, 0.0, 0.2]), np.array([0.5, 0.5, 0.4]), np.eye(3))
    assert [(x.affordance, round(x.height, 2)) for x in surfaces(ArScene([c]))] == [("sit", 0.45)]


def test_floor_height_without_a_grid() -> None:
    # a map whose world frame has the floor at z = -1.2 (no grid): heights count from the lowest bottom
    o = table(1, (0.0, 0.0))
    for p in o.primitives:
        p.center = p.center - [0, 0, 1.2]
    o.center = o.center - [0, 0, 1.2]
    assert [x.affordance for x in surfaces(ArScene([o]))] == ["place"]
    assert surfaces(ArScene([o]), floor_z=0.0) == []  # 0.45 m below "the floor": no use


def test_a_top_the_camera_saw_takes_its_measured_height() -> None:
    from dataclasses import replace

    rng = np.random.default_rng(4)
    xy = rng.uniform([0.55, 1.75], [1.45, 2.25], (400, 2))  # over the 1.0 x 0.6 m top centred at (1, 2)
    seen = np.column_stack([xy, rng.normal(0.72, 0.004, 400)])  # the real top: 3 cm below the estimate
    cup = np.column_stack([rng.uniform([0.9, 1.9], [1.0, 2.0], (60, 2)), rng.uniform(0.73, 0.79, 60)])
    beside = np.column_stack([rng.uniform([1.6, 1.8], [1.7, 2.2], (200, 2)), np.full(200, 0.70)])  # off the top
    obj = replace(table(4, (1.0, 2.0)), surface=np.concatenate([seen, cup, beside]))
    top = surfaces(ArScene([obj]))[0]
    assert abs(top.height - 0.72) < 0.003
    assert abs(surfaces(ArScene([obj]), measured=False)[0].height - 0.75) < 1e-9
    few = replace(obj, surface=seen[:5])  # too few points: the primitive's estimate stands
    assert abs(surfaces(ArScene([few]))[0].height - 0.75) < 1e-9
    far = replace(obj, surface=seen + [0.0, 0.0, -0.2])  # a layer 20 cm lower is not this top
    assert abs(surfaces(ArScene([far]))[0].height - 0.75) < 1e-9
