"""Sphere collision and contacts against hand-made scenes with known distances."""

from __future__ import annotations

import numpy as np
import pytest
from ar_scenes import box_object, rotz, table

from shape_detector.ar import ArScene, collides, collides_many, contacts
from shape_detector.ar.collision import box_distances, distance_to_scene


def test_box_distance_rotated_box() -> None:
    R = rotz(np.pi / 4)
    c, half = np.array([1.0, 1.0, 0.5]), np.array([0.5, 0.2, 0.5])
    # 0.3 m beyond the +x face, along the box's own x axis; a point inside; a corner point
    p = np.array([c + R[:, 0] * 0.8, c, c + R @ np.array([0.6, 0.3, 0.5])])
    d = box_distances(p, np.repeat(c[None], 3, 0), np.repeat(half[None], 3, 0), np.repeat(R[None], 3, 0))
    np.testing.assert_allclose(d, [0.3, 0.0, np.sqrt(0.1**2 + 0.1**2)], atol=1e-9)


def test_collides_table_top_and_under() -> None:
    sc = ArScene([table(3, (0.0, 0.0))])  # top 0.70..0.75 m, legs at the corners
    assert collides(sc, [0.0, 0.0, 0.72])
    assert not collides(sc, [0.0, 0.0, 0.4], radius=0.2)  # under the top, away from the legs
    assert collides(sc, [0.0, 0.0, 0.55], radius=0.16)  # 15 cm below the top
    assert not collides(sc, [0.0, 0.0, 0.85], radius=0.09)  # 10 cm above
    assert collides(sc, [0.0, 0.0, 0.85], radius=0.11)
    assert collides(sc, [0.475, 0.275, 0.2])  # inside a leg


def test_contacts_names_object_and_primitive() -> None:
    sc = ArScene([table(3, (0.0, 0.0)), box_object(7, "dresser", (3.0, 0.0, 0.6), (0.5, 1.0, 1.2))])
    pts = np.array([[0.475, 0.275, 0.2], [0.0, 0.0, 0.8], [3.0, 0.0, 1.25], [10.0, 10.0, 0.0]])
    assert contacts(sc, pts, radius=0.06) == [(3, 0), (3, 4), (7, -1)]
    np.testing.assert_array_equal(collides_many(sc, pts, 0.06), [True, True, True, False])


def test_rotated_box_near_corner() -> None:
    sc = ArScene([box_object(1, "dresser", (0.0, 0.0, 0.5), (1.0, 1.0, 1.0), yaw=np.pi / 4)])
    # the box's corner along world +x lies at x = sqrt(2)/2; an AABB test would say "inside" at (0.6, 0.6)
    assert not collides(sc, [0.6, 0.6, 0.5], radius=0.1)
    assert collides(sc, [0.75, 0.0, 0.5], radius=0.05)
    np.testing.assert_allclose(distance_to_scene(sc, np.array([[0.6, 0.6, 0.5]])), [np.hypot(0.6, 0.6) - 0.5],
                               atol=1e-9)


def test_matches_brute_force_on_random_points() -> None:
    rng = np.random.default_rng(0)
    sc = ArScene([table(i + 1, tuple(rng.uniform(0, 4, 2)), yaw=float(rng.uniform(-3, 3))) for i in range(6)])
    pts = rng.uniform([-0.5, -0.5, 0.0], [4.5, 4.5, 1.0], (3000, 3))
    b = sc.boxes
    d = np.min([box_distances(pts, np.repeat(b.centers[k][None], len(pts), 0), np.repeat(b.half[k][None], len(pts), 0),
                              np.repeat(b.rot[k][None], len(pts), 0)) for k in range(len(b))], axis=0)
    for r in (0.0, 0.1, 0.3):
        np.testing.assert_array_equal(collides_many(sc, pts, r), d <= r)


def test_bad_input() -> None:
    sc = ArScene([table(1, (0.0, 0.0))])
    assert not collides(sc, [np.nan, 0.0, 0.7], 0.1)
    assert not collides(ArScene([]), [0.0, 0.0, 0.0], 1.0)
    with pytest.raises(ValueError):
        collides(sc, [0.0, 0.0], 0.1)
    with pytest.raises(ValueError):
        collides(sc, [0.0, 0.0, 0.0], -0.1)


def test_observed_surface_inside_the_box_collides_where_the_primitives_fall_short() -> None:
    from dataclasses import replace

    # the depth saw an apron 4 cm under the table top (x, y in [-0.3, 0.3], z = 0.66), which
    # the fused primitives miss; and a wall point beside the table, outside its box
    xs = np.arange(-0.3, 0.31, 0.02)
    apron = np.array([[x, y, 0.66] for x in xs for y in xs])
    wall = np.array([[0.0, 0.48, 0.6]])
    sc = ArScene([replace(table(3, (0.0, 0.0)), surface=np.concatenate([apron, wall]))])
    below = [0.0, 0.0, 0.58]  # 8 cm under the apron, 12 cm under the top primitive
    assert collides(sc, below, radius=0.1)
    assert not collides(sc, below, radius=0.1, surfaces=False)
    assert not collides(sc, below, radius=0.07)
    assert contacts(sc, [below], radius=0.1) == [(3, -1)]
    assert contacts(sc, [below], radius=0.1, surfaces=False) == []
    beside = [0.0, 0.4, 0.6]  # 8 cm from the wall point, which the table's box does not hold
    assert not collides(sc, beside, radius=0.1)
    got = collides_many(sc, [below, beside, [0.0, 0.0, 0.72], [np.nan, 0.0, 0.5]], radius=0.1)
    assert got.tolist() == [True, False, True, False]


def test_surface_contacts_match_a_brute_force_search_at_any_radius() -> None:
    from dataclasses import replace

    from shape_detector.ar.collision import surface_contacts

    rng = np.random.default_rng(7)
    # points spread through each box (the chair's partly outside its turned box: not counted)
    a = replace(box_object(4, "dresser", (0.0, 0.0, 0.5), (1.0, 0.5, 1.0)),
                surface=rng.uniform(-0.5, 0.5, (400, 3)) * [1.0, 0.5, 1.0] + [0.0, 0.0, 0.5])
    b = replace(box_object(9, "chair", (2.0, 0.0, 0.4), (0.5, 0.5, 0.8), yaw=0.5),
                surface=rng.uniform(-0.25, 0.25, (300, 3)) * [1.0, 1.0, 1.6] + [2.0, 0.0, 0.4])
    sc = ArScene([a, b])
    pts = rng.uniform([-1.0, -1.0, -0.2], [3.0, 1.0, 1.5], (500, 3))
    inside = sc.contact_points[0]
    for r in (0.03, 0.1, 0.3, 1.2):
        got = surface_contacts(sc, pts, r)
        d = np.linalg.norm(pts[:, None] - inside[None], axis=2).min(axis=1)
        assert np.array_equal(got >= 0, d <= r), r
    assert set(surface_contacts(sc, pts, 0.3).tolist()) == {-1, 4, 9}
