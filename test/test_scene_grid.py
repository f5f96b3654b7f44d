"""Navigation grid cells on hand-made scenes (world frame, z up, 5 cm cells)."""

from __future__ import annotations

import numpy as np

from shape_detector.scene import SceneConfig, SceneMap
from shape_detector.scene.grid import FREE, OCCUPIED, UNKNOWN, FloorMemory, NavGrid, build_grid
from test_scene_support import K, detection, pose, render, room

RES = 0.05
EYE = np.eye(3)


def _floor(x0, x1, y0, y1) -> FloorMemory:
    f = FloorMemory(RES)
    xs, ys = np.meshgrid(np.arange(x0, x1, RES / 2), np.arange(y0, y1, RES / 2))
    f.add(np.stack([xs.ravel(), ys.ravel()], axis=1))
    return f


def _table():
    """A 1.0 x 0.6 m table, top 0.72-0.75 m, four 5 cm legs at the corners; centred at (1, 1)."""
    parts = [((1.0, 1.0, 0.735), (1.0, 0.6, 0.03), EYE)]
    for dx in (-0.475, 0.475):
        for dy in (-0.275, 0.275):
            parts.append(((1.0 + dx, 1.0 + dy, 0.36), (0.05, 0.05, 0.72), EYE))
    return parts


def _value(g: NavGrid, x: float, y: float) -> int:
    r, c = g.world_to_cell(np.array([[x, y]]))[0]
    return int(g.data[r, c])


def test_free_unknown_and_occupied():
    g = build_grid(_floor(0.0, 2.0, 0.0, 2.0), [((1.0, 1.0, 0.45), (0.5, 0.5, 0.9), EYE)], 0.0)
    assert _value(g, 0.2, 0.2) == FREE
    assert _value(g, 1.0, 1.0) == OCCUPIED
    assert _value(g, 1.2, 1.2) == OCCUPIED and _value(g, 1.3, 1.3) == FREE
    assert (g.data == UNKNOWN).any()  # the padding around the seen floor
    assert g.data.dtype == np.int8 and g.data.shape == (g.height, g.width)
    assert abs(g.origin[0] / RES - round(g.origin[0] / RES)) < 1e-9


def test_table_blocks_a_person_but_a_small_robot_passes_under_it():
    floor = _floor(0.0, 2.0, 0.0, 2.0)
    person = build_grid(floor, _table(), 0.0, agent_height=1.8)
    robot = build_grid(floor, _table(), 0.0, agent_height=0.5)
    assert _value(person, 1.0, 1.0) == OCCUPIED  # under the top: the top is below 1.8 m
    assert _value(robot, 1.0, 1.0) == FREE  # the top is above 0.5 m: only the legs block
    assert _value(robot, 1.475, 1.275) == OCCUPIED  # a leg
    assert (robot.data == OCCUPIED).sum() == 4  # one 5 cm cell per 5 cm leg
    n_person = (person.data == OCCUPIED).sum()
    assert abs(n_person - (1.0 / RES) * (0.6 / RES)) <= 2 * (1.0 + 0.6) / RES + 4


def test_rug_and_high_shelf_do_not_block():
    parts = [((1.0, 1.0, 0.01), (1.0, 1.0, 0.02), EYE), ((0.5, 0.5, 2.0), (0.4, 0.3, 0.3), EYE)]
    g = build_grid(_floor(0.0, 2.0, 0.0, 2.0), parts, 0.0, agent_height=1.8)
    assert not (g.data == OCCUPIED).any()


def test_rotated_footprint():
    yaw = np.pi / 4
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
    g = build_grid(FloorMemory(RES), [((1.0, 1.0, 0.5), (1.0, 0.2, 1.0), R)], 0.0)
    assert _value(g, 1.3, 1.3) == OCCUPIED and _value(g, 1.3, 0.7) != OCCUPIED
    assert abs((g.data == OCCUPIED).sum() * RES**2 - 0.2) < 0.05


def test_inflation_grows_occupied_over_free_only():
    data = np.full((9, 9), FREE, np.int8)
    data[:, 0] = UNKNOWN
    data[4, 4] = OCCUPIED
    g = NavGrid(RES, np.zeros(2), data)
    big = g.inflated(0.1)
    assert (big.data == OCCUPIED).sum() == 13  # a radius-2 disc
    assert (big.data[:, 0] == UNKNOWN).all()
    assert (g.data == OCCUPIED).sum() == 1  # the original is unchanged
    np.testing.assert_allclose(g.cell_centers()[0, 0], [0.025, 0.025])


def test_scene_map_grid_from_depth_and_tracks():
    T = pose(0.0, 0.0, 1.2, 0.0)
    chair = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)
    m = SceneMap(SceneConfig(floor_z=None))
    d = render(room([chair]), T)
    for i in range(4):
        m.update([detection(*chair, T)], T, d, K, stamp_ns=i)
    g = m.grid()
    assert abs(m.floor_z) < 0.02
    assert _value(g, 3.0, 0.0) == OCCUPIED
    assert _value(g, 2.55, 0.0) == FREE  # floor seen in front of the chair (the view starts 2.4 m out)
    assert _value(g, 1.0, 0.0) == UNKNOWN  # below the view
    assert _value(g, 4.0, 0.0) == UNKNOWN or _value(g, 4.0, 0.0) == FREE
    assert _value(g, 3.6, 0.0) != OCCUPIED
    inflated = m.grid(inflate=True)
    assert (inflated.data == OCCUPIED).sum() > (g.data == OCCUPIED).sum()


def test_floor_under_the_camera_path_is_free_even_when_never_seen():
    m = SceneMap(SceneConfig(floor_z=0.0, camera_path_radius=0.3))
    for k, x in enumerate(np.linspace(0.0, 2.0, 5)):
        T = np.eye(4)
        T[:3, 3] = (x, 1.0, 1.5)
        m.update([], T, None, None, k)
    g = m.grid()
    cells = g.world_to_cell(np.array([[x, y] for x in np.linspace(0.0, 2.0, 21) for y in (0.8, 1.0, 1.2)]))
    assert all(int(g.data[r, c]) == FREE for r, c in cells)  # a free corridor along the path
    far = g.world_to_cell(np.array([[1.0, 1.6]]))[0]
    inside = 0 <= far[0] < g.height and 0 <= far[1] < g.width
    assert not inside or int(g.data[far[0], far[1]]) == UNKNOWN
    still = SceneMap(SceneConfig(floor_z=0.0, camera_path_radius=0.0))
    still.update([], np.eye(4), None, None, 0)
    assert not (still.grid().data == FREE).any()


def test_floor_is_the_lowest_level_enough_frames_agree_on():
    from shape_detector.scene.grid import floor_from_estimates

    assert floor_from_estimates([0.46] * 32 + [0.0] * 8) < 0.01  # a bed filled most frames
    assert floor_from_estimates([0.0] * 40 + [-0.35, -0.36]) == 0.0  # two odd frames are not enough
    assert floor_from_estimates([0.3, 0.5]) == 0.4  # too few to tell: the median
    assert floor_from_estimates([None, 0.01, 0.02, 0.03]) == 0.02
    assert floor_from_estimates([]) is None


def test_scene_map_floor_survives_frames_filled_by_a_bed():
    # a bed 0.5 m high fills the lower half of the view looking along +x (the wall behind it
    # at 8 m); looking back along -x the camera sees the floor
    bed = ((4.2, 0.0, 0.25), (7.4, 19.0, 0.5), 0.0)
    m = SceneMap(SceneConfig(floor_z=None))
    for i in range(6):
        T = pose(0.0, 0.0, 1.2, 0.0)
        m.update([], T, render(room([bed]), T), K, stamp_ns=i)
    assert abs(m.floor_z - 0.5) < 0.03  # all it has seen so far is the bed's top
    for i in range(6, 9):
        T = pose(0.0, 0.0, 1.2, np.pi)
        m.update([], T, render(room([bed]), T), K, stamp_ns=i)
    assert abs(m.floor_z) < 0.02
