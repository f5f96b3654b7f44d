"""Planning margins where the map is unsure of a box: grown per face by its spread, capped,
only around objects that block the agent over their whole footprint."""

from __future__ import annotations

import numpy as np
import pytest
from ar_scenes import box_object, table

from shape_detector.ar import ArScene, SceneQueries, plan
from shape_detector.ar.margins import MAX_MARGIN, padded_grid
from shape_detector.scene.grid import FloorMemory, NavGrid, build_grid

RES = 0.05


def _floor() -> FloorMemory:
    f = FloorMemory(RES)
    xs = np.arange(0.0, 4.0, RES) + RES / 2
    f.add(np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2))
    return f


def _scene(objects: list, agent_height: float = 1.8) -> ArScene:
    parts = [(p.center, p.size, p.rotation) for o in objects for p in (o.primitives or [o])]
    return ArScene(objects, build_grid(_floor(), parts, 0.0, agent_height))


def _pair(sd_near_gap: float) -> list:
    """Two 1 m boxes with a 0.6 m gap between them (x 1.5..2.1), the faces at the gap with
    spread ``sd_near_gap``."""
    a = box_object(1, "dresser", (1.0, 2.0, 0.5), (1.0, 1.0, 1.0))
    b = box_object(2, "dresser", (2.6, 2.0, 0.5), (1.0, 1.0, 1.0))
    a.face_sd = np.array([0.0, sd_near_gap, 0.0, 0.0])  # -x, +x, -y, +y
    b.face_sd = np.array([sd_near_gap, 0.0, 0.0, 0.0])
    return [a, b]


def test_margins_grow_the_unsure_faces_only() -> None:
    sc = _scene(_pair(0.06))
    g = padded_grid(sc.grid, sc.objects, uncertainty=1.0)
    added = (g.data == 100) & (sc.grid.data != 100)
    cols = np.flatnonzero(added.any(axis=0))
    x = sc.grid.origin[0] + (cols + 0.5) * RES
    assert np.all(((x > 1.5) & (x < 1.57)) | ((x > 2.03) & (x < 2.1)))  # 6 cm into the gap, nowhere else
    assert padded_grid(sc.grid, sc.objects, uncertainty=0.0) is sc.grid
    big = padded_grid(sc.grid, _pair(1.0), uncertainty=1.0)  # capped
    added = (big.data == 100) & (sc.grid.data != 100)
    assert added.any(axis=0).sum() <= 2 * int(np.ceil(MAX_MARGIN / RES)) + 2
    with pytest.raises(ValueError):
        padded_grid(sc.grid, sc.objects, uncertainty=-1.0)


def test_a_passage_closes_when_its_sides_are_unsure() -> None:
    start, goal = (1.8, 1.0), (1.8, 3.0)  # through the gap between the boxes
    sure, unsure = _scene(_pair(0.0)), _scene(_pair(0.1))
    assert plan(sure, start, goal, agent_radius=0.2, unknown="blocked") is not None
    path = plan(unsure, start, goal, agent_radius=0.2, unknown="blocked")
    assert path is not None and np.all(np.abs(np.array(path)[:, 1] - 2.0) > 0.5)  # around the boxes
    q = SceneQueries(unsure)
    assert q.plan(start, goal, unknown="blocked", uncertainty=0.0) is not None
    assert np.array_equal(q.plan(start, goal, unknown="blocked"), path)  # SceneQueries: the same default


def test_a_table_over_a_small_robot_keeps_the_space_under_it() -> None:
    t = table(1, (2.0, 2.0))
    t.face_sd = np.full(4, 0.1)
    low = _scene([t], agent_height=0.5)  # only the legs block a 0.5 m robot
    assert padded_grid(low.grid, low.objects, uncertainty=1.0) is low.grid
    tall = _scene([t])  # the top blocks a person: the whole footprint, grown
    assert (padded_grid(tall.grid, tall.objects, uncertainty=1.0).data == 100).sum() > (tall.grid.data == 100).sum()


def test_a_bare_grid_plans_without_margins() -> None:
    g: NavGrid = _scene(_pair(0.1)).grid
    assert plan(g, (1.8, 1.0), (1.8, 3.0), agent_radius=0.2, unknown="blocked") is not None
