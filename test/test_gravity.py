"""Gravity from depth: tilted floors, no floor, walls only, no planes (fallback)."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.gravity import GravityEstimate, estimate_up, make_grid
from shape_detector.proposals.evaluate import VGA_K, angle_deg

from toy_scenes import box_part, chair_parts, toy_scene, up_from_pitch_roll

OBJECTS = [
    ("table", [box_part(0.3, 3.0, 1.2, 0.8, 0.75)]),
    ("chair", chair_parts(-0.9, 2.6, 0.4)),
    ("dresser", [box_part(1.5, 3.6, 1.0, 0.5, 1.1)]),
]
WALLS = [(np.pi / 2, 5.0), (0.0, 2.6), (np.pi, 2.6)]


@pytest.mark.parametrize("pitch,roll,cam_h", [(0.0, 0.0, 1.3), (18.0, 4.0, 1.1), (35.0, -6.0, 1.6)])
def test_up_from_tilted_floor(pitch, roll, cam_h):
    up = up_from_pitch_roll(pitch, roll)
    f = toy_scene(OBJECTS, up=up, cam_height=cam_h, walls=WALLS, seed=int(pitch))
    g = estimate_up(f.depth, f.K)
    assert isinstance(g, GravityEstimate)
    assert g.source == "floor"
    assert angle_deg(g.up, up) < 1.0
    assert np.linalg.norm(g.up) == pytest.approx(1.0)
    assert g.floor_height == pytest.approx(cam_h, abs=0.03)
    assert 0.5 <= g.confidence <= 1.0
    # the plane: up . p + d = 0 on the floor, heights of floor points ~ 0
    assert g.plane is not None and np.allclose(g.plane[:3], g.up)
    grid = make_grid(f.depth, f.K)
    floor_pts = grid.points[grid.valid & (f.instance_mask[2::4, 2::4] == 0)]
    h = g.height_above_floor(floor_pts)
    assert np.median(np.abs(h[h < 0.3])) < 0.02


def test_steep_pitch_prefers_floor_over_wall():
    # looking 50 deg down at a wall 1.6 m ahead: the wall is the densest near-horizontal mode
    # (40 deg from a level prior), the floor is 50 deg away but is the one with nothing under it
    up = up_from_pitch_roll(50.0, 3.0)
    f = toy_scene([("chair", chair_parts(0.4, 1.2, 0.3))], up=up, cam_height=1.5, walls=[(np.pi / 2, 1.6)], seed=3)
    g = estimate_up(f.depth, f.K)
    assert g.source == "floor"
    assert angle_deg(g.up, up) < 1.5


def test_no_floor_uses_horizontal_surfaces():
    up = up_from_pitch_roll(20.0, 5.0)
    f = toy_scene(OBJECTS, up=up, floor=False, walls=WALLS, seed=5)
    g = estimate_up(f.depth, f.K)
    assert g.source == "horizontal"
    assert g.floor_height is None and g.plane is None
    assert angle_deg(g.up, up) < 2.0
    assert 0.0 < g.confidence < 0.7


def test_walls_only_manhattan():
    up = up_from_pitch_roll(15.0, -8.0)
    f = toy_scene([], up=up, floor=False, walls=[(np.pi / 2, 4.0), (0.0, 1.5), (np.pi, 2.0)], seed=7)
    g = estimate_up(f.depth, f.K)
    assert g.source == "walls"
    assert angle_deg(g.up, up) < 2.0
    assert 0.0 < g.confidence <= 0.4


def _sphere_depth(center=(0.0, 0.0, 3.0), r=1.0, K=VGA_K, shape=(480, 640)) -> np.ndarray:
    uu, vv = np.meshgrid(np.arange(shape[1]), np.arange(shape[0]))
    d = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones(shape)], -1)
    c = np.asarray(center)
    a = (d * d).sum(-1)
    b = -2 * (d @ c)
    disc = b * b - 4 * a * (c @ c - r * r)
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.nan)
    return t.astype(np.float32)


@pytest.mark.parametrize("kind", ["sphere", "noise", "empty"])
def test_fallback_to_prior_without_planes(kind):
    rng = np.random.default_rng(0)
    if kind == "sphere":
        depth = _sphere_depth()
    elif kind == "noise":
        depth = rng.uniform(0.5, 6.0, (480, 640)).astype(np.float32)
    else:
        depth = np.full((480, 640), np.nan, np.float32)
    g = estimate_up(depth, VGA_K)
    assert g.source == "prior" and g.confidence == 0.0
    np.testing.assert_allclose(g.up, [0.0, -1.0, 0.0])
    prior = np.array([0.1, -0.9, -0.3])
    g = estimate_up(depth, VGA_K, prior_up=prior)
    assert g.source == "prior" and g.confidence == 0.0
    np.testing.assert_allclose(g.up, prior / np.linalg.norm(prior))


def test_grid_reuse_and_shapes():
    up = up_from_pitch_roll(10.0, 0.0)
    f = toy_scene(OBJECTS[:1], up=up, seed=1)
    grid = make_grid(f.depth, f.K, stride=4)
    assert grid.shape == (120, 160) and grid.points.shape == (120, 160, 3)
    assert grid.image_shape == (480, 640) and grid.u[0] == 1.5 and grid.v[-1] == 477.5
    assert np.isnan(grid.points[~grid.valid]).all() and np.isfinite(grid.points[grid.valid]).all()
    n = grid.normals[grid.nvalid]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert (np.einsum("ij,ij->i", n, grid.pmean[grid.nvalid]) <= 1e-6).all()  # facing the camera
    a = estimate_up(f.depth, f.K)
    b = estimate_up(None, f.K, grid=grid)
    np.testing.assert_allclose(a.up, b.up)
    # another stride: thresholds scale with the grid, same answer
    c = estimate_up(f.depth, f.K, stride=6)
    assert c.source == "floor" and angle_deg(c.up, up) < 1.0
