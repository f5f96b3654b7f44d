"""Paths on hand-made grids: through a gap, none through a closed wall, clearance, unknown cells."""

from __future__ import annotations

import numpy as np
import pytest
from ar_scenes import wall_grid

from shape_detector.ar import ArScene, plan, planning
from shape_detector.scene.grid import NavGrid
from shape_detector.ar.planning import COMFORT, traversable, visible


def _clearance(grid: NavGrid, path: list[tuple[float, float]], step: float = 0.01) -> float:
    """Smallest distance (m) from the densely sampled path to an occupied cell's centre."""
    occ = (np.argwhere(grid.data == 100)[:, ::-1] + 0.5) * grid.resolution + grid.origin
    p = np.array(path)
    pts = np.concatenate([np.linspace(a, b, max(2, int(np.linalg.norm(b - a) / step))) for a, b in zip(p[:-1], p[1:])])
    return float(np.min(np.linalg.norm(pts[:, None] - occ[None], axis=2)))


def _length(path: list[tuple[float, float]]) -> float:
    return float(np.sum(np.linalg.norm(np.diff(np.array(path), axis=0), axis=1)))


def test_path_through_the_gap() -> None:
    g = wall_grid(gap=True)
    path = plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.2)
    assert path is not None
    assert path[0] == (1.0, 0.5) and path[-1] == (3.0, 0.5)
    p = np.array(path)
    length = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    # through the opening (y in [1.5, 2.5]) passing the wall's end at the radius (0.2 m) plus
    # at most the comfort band: about 2 x hypot(1, 1.2 + COMFORT)
    assert 2 * np.hypot(1.0, 1.2) - 0.05 < length < 2 * np.hypot(1.0, 1.2 + COMFORT) + 0.25
    assert len(path) <= 5  # smoothed: a few corners, not a staircase of cells
    assert _clearance(g, path) >= 0.2 - 1e-6


def test_comfort_keeps_plans_off_the_walls_where_there_is_room(monkeypatch: pytest.MonkeyPatch) -> None:
    g = wall_grid(gap=True)
    tight = plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.2)
    monkeypatch.setattr(planning, "COMFORT", 0.0)
    bare = plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.2)
    # the band's cost pulls the path towards the opening's middle (y = 2 m): clearer, a little longer
    def crossing(path: list[tuple[float, float]]) -> float:
        p = np.array(path)
        pts = np.concatenate([np.linspace(a, b, 400) for a, b in zip(p[:-1], p[1:])])
        return float(np.mean(pts[(pts[:, 0] >= 2.0) & (pts[:, 0] <= 2.1), 1]))

    assert abs(crossing(tight) - 2.0) < abs(crossing(bare) - 2.0) - 0.05
    assert _clearance(g, tight) > _clearance(g, bare) + 0.01
    assert _length(bare) < _length(tight) < _length(bare) + 0.3


def test_squeeze_through_a_passage_a_little_too_narrow() -> None:
    g = wall_grid(gap=True, width=0.45)  # 9 cells: the middle one 0.225 m from each side
    assert plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.24, squeeze=0.0) is None
    path = plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.24, squeeze=0.02)
    assert path is not None and path[0] == (1.0, 0.5) and path[-1] == (3.0, 0.5)
    assert _clearance(g, path) >= 0.22 - 1e-6
    # only where it must: away from the opening the path keeps the full radius from the wall
    p = np.array(path)
    pts = np.concatenate([np.linspace(a, b, 200) for a, b in zip(p[:-1], p[1:])])
    away = pts[np.abs(pts[:, 1] - 1.725) > 0.3]
    assert np.min(np.abs(away[:, 0] - 2.05)) - 0.05 >= 0.24 - 1e-6
    assert plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.27, squeeze=0.02) is None  # 4.5 cm short
    with pytest.raises(ValueError):
        plan(g, (1.0, 0.5), (3.0, 0.5), squeeze=-0.1)


def test_a_squeeze_only_when_nothing_else_gets_through() -> None:
    g = wall_grid(gap=True, width=0.45)
    g.data[60:75, 40:42] = 0  # a second opening, wide, 1.7 m further up
    path = np.array(plan(g, (1.0, 1.7), (3.0, 1.7), agent_radius=0.24))
    assert path[:, 1].max() > 2.9  # the detour through the wide opening, not the 2 m straight squeeze


def test_no_path_through_a_closed_wall() -> None:
    g = wall_grid(gap=False)
    assert plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.2) is None
    assert plan(g, (1.0, 0.5), (1.0, 3.5), agent_radius=0.2) is not None  # same side


def test_gap_too_narrow_for_a_wide_agent() -> None:
    g = wall_grid(gap=True)  # 1 m opening
    assert plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.45) is not None
    assert plan(g, (1.0, 0.5), (3.0, 0.5), agent_radius=0.55) is None


def test_enclosed_unknown_cells_are_walkable_by_default() -> None:
    g = wall_grid(gap=False)
    g.data[:, 40:42] = -1  # the wall is unknown space instead
    assert plan(g, (1.0, 0.5), (3.0, 0.5), unknown="blocked") is None
    assert plan(g, (1.0, 0.5), (3.0, 0.5), unknown="free") is not None
    # a 10 cm unseen band between seen floor is enclosed (a gap between depth samples)
    assert plan(g, (1.0, 0.5), (3.0, 0.5)) is not None
    assert plan(g, (1.0, 0.5), (3.0, 0.5), unknown="interior") is not None
    with pytest.raises(ValueError):
        plan(g, (1.0, 0.5), (3.0, 0.5), unknown="maybe")


def test_interior_unknown_only_inside_the_seen_floor() -> None:
    g = wall_grid(gap=True)
    g.data[:, 60:] = -1  # the far side beyond x = 3 m was never seen
    assert plan(g, (1.0, 0.5), (3.5, 0.5), unknown="interior") is None  # outside the seen extent
    assert plan(g, (1.0, 0.5), (3.5, 0.5), unknown="free") is not None
    # an unseen patch inside the seen floor is walkable ...
    g = wall_grid(gap=False)
    g.data[10:70, 5:35] = -1
    assert plan(g, (1.0, 2.0), (1.2, 2.0), unknown="blocked") is None
    assert plan(g, (1.0, 2.0), (1.2, 2.0), unknown="interior") is not None
    # ... at twice the cost: a detour over seen floor up to twice as long wins
    g = wall_grid(gap=False)
    g.data[30:50, 10:30] = -1  # y 1.5..2.5, x 0.5..1.5
    path = np.array(plan(g, (0.2, 2.0), (1.8, 2.0), unknown="interior"))
    assert np.all((path[:, 1] <= 1.5 + 1e-9) | (path[:, 1] >= 2.5 - 1e-9) | (path[:, 0] <= 0.5) | (path[:, 0] >= 1.5))


def test_start_in_the_margin_snaps() -> None:
    g = wall_grid(gap=True)
    path = plan(g, (1.9, 0.5), (1.0, 0.5), agent_radius=0.2)  # 5 cm from the wall
    assert path is not None and 1.7 <= path[0][0] <= 1.8
    assert plan(g, (1.9, 0.5), (1.0, 0.5), agent_radius=0.2, snap_distance=0.0) is None
    assert plan(g, (10.0, 10.0), (1.0, 0.5)) is None  # off the grid


def test_plan_accepts_scene_and_rejects_bad_input() -> None:
    sc = ArScene([], wall_grid(gap=True))
    assert plan(sc, (1.0, 0.5), (1.0, 3.0)) is not None
    with pytest.raises(ValueError):
        plan(sc, (np.nan, 0.5), (1.0, 3.0))
    with pytest.raises(ValueError):
        plan(sc, (1.0, 0.5), (1.0, 3.0), agent_radius=-1)
    with pytest.raises(ValueError):
        plan(ArScene([]), (1.0, 0.5), (1.0, 3.0))


def test_traversable_and_visibility() -> None:
    g = wall_grid(gap=False)
    m = traversable(g, 0.2)
    assert m[10, 10] and not m[10, 37] and not m[10, 40] and m[10, 46]  # 0.2 m margin at 5 cm cells
    assert visible(m, np.array([10, 10]), np.array([[10, 30], [10, 50]])).tolist() == [True, False]


def test_a_doubtful_track_is_crossed_only_where_nothing_else_gets_through() -> None:
    from dataclasses import replace

    from ar_scenes import box_object

    from shape_detector.ar.margins import DOUBT_SCORE

    g = wall_grid(gap=True)  # the opening: y in [1.5, 2.5] at x = 2
    g.data[30:50, 40:42] = 100  # filled by an object's footprint
    chair = box_object(5, "chair", (2.05, 2.0, 0.4), (0.1, 1.0, 0.8))
    sure, doubtful = replace(chair, score=0.9), replace(chair, score=DOUBT_SCORE - 0.05)
    assert plan(ArScene([sure], g), (1.0, 0.5), (3.0, 0.5)) is None
    path = plan(ArScene([doubtful], g), (1.0, 0.5), (3.0, 0.5))
    assert path is not None and 1.5 < max(y for _, y in path) < 2.5  # through the doubtful track
    assert plan(ArScene([doubtful], g), (1.0, 0.5), (3.0, 0.5), squeeze=0.0) is None
    g.data[60:75, 40:42] = 0  # a second opening, 1.5 m further up
    detour = np.array(plan(ArScene([doubtful], g), (1.0, 0.5), (3.0, 0.5)))
    assert detour[:, 1].max() > 3.0  # around the doubtful track where the map allows it
