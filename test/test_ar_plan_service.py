"""GetPlan as a pure function: request-like objects in, poses and a nav_msgs/Path out."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from ar_scenes import wall_grid

from shape_detector.ar import ArScene, SceneQueries
from shape_detector.ar.plan_service import path_message, plan_request

RCLPY_MSGS = "nav_msgs"  # for conftest's ``types`` fixture


def _pose(x: float, y: float, yaw: float = 0.0, frame: str = "odom") -> SimpleNamespace:
    q = SimpleNamespace(x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2))
    return SimpleNamespace(header=SimpleNamespace(frame_id=frame),
                           pose=SimpleNamespace(position=SimpleNamespace(x=x, y=y, z=0.0), orientation=q))


def _req(start, goal, tol: float = 0.0) -> SimpleNamespace:
    return SimpleNamespace(start=start, goal=goal, tolerance=tol)


def test_plan_request_through_gap() -> None:
    q = SceneQueries(ArScene([], wall_grid(gap=True)))
    r = plan_request(q, _req(_pose(1.0, 0.5), _pose(3.0, 0.5, yaw=1.0)), "odom", agent_radius=0.2, step=0.05)
    assert r.ok and r.poses.shape[1] == 4
    np.testing.assert_allclose(r.poses[0, :2], [1.0, 0.5])
    np.testing.assert_allclose(r.poses[-1, :2], [3.0, 0.5])
    assert abs(r.poses[-1, 3] - 1.0) < 1e-9  # the goal's yaw
    assert np.max(np.linalg.norm(np.diff(r.poses[:, :2], axis=0), axis=1)) <= 0.05 + 1e-9
    assert 0.6 < r.poses[1, 3] < 1.0  # heading up towards the gap first


def test_plan_request_refusals() -> None:
    q = SceneQueries(ArScene([], wall_grid(gap=False)))
    assert plan_request(q, _req(_pose(1.0, 0.5), _pose(3.0, 0.5)), "odom").message == "no path"
    r = plan_request(q, _req(_pose(1.0, 0.5, frame="map"), _pose(1.0, 3.0)), "odom")
    assert not r.ok and "frame" in r.message
    assert not plan_request(q, SimpleNamespace(start=None, goal=None), "odom").ok
    assert not plan_request(SceneQueries(ArScene([])), _req(_pose(1.0, 0.5), _pose(1.0, 3.0)), "odom").ok
    # goal inside the wall's margin: refused at tolerance 0, found with a tolerance of 0.3 m
    assert not plan_request(q, _req(_pose(1.0, 0.5), _pose(2.05, 3.0)), "odom").ok
    assert plan_request(q, _req(_pose(1.0, 0.5), _pose(2.05, 3.0), tol=0.3), "odom").ok


def test_path_message(types) -> None:
    q = SceneQueries(ArScene([], wall_grid(gap=True)))
    r = plan_request(q, _req(_pose(1.0, 0.5), _pose(1.0, 2.0)), "odom", step=0.5)
    msg = path_message(r, types, stamp_ns=2_000_000_001, frame_id="odom")
    assert msg.header.frame_id == "odom" and len(msg.poses) == len(r.poses) == 4
    p = msg.poses[1].pose
    assert p.position.y == pytest.approx(1.0) and p.orientation.z == pytest.approx(np.sin(np.pi / 4))
