"""``nav_msgs/srv/GetPlan`` as a pure function: request fields in, path poses out.

The node's ``~/get_plan`` service calls :func:`plan_request` with the request (duck-typed:
``start``/``goal`` as ``geometry_msgs/PoseStamped``, ``tolerance`` in metres) and fills the
response's ``plan`` with :func:`path_message`. Poses are in the map's world frame (z up,
metres); a request in another frame is refused (no TF lookup here). A live map changes
every frame: build ``SceneQueries(scene_map)`` per request (tens of milliseconds with the
graph), not once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .margins import UNCERTAINTY
from .planning import SQUEEZE
from .queries import SceneQueries


@dataclass
class PlanResult:
    """``poses`` (K,4): x, y, z (the floor), yaw (rad, direction of travel; the last keeps the
    goal's yaw); empty when ``ok`` is False, with the reason in ``message``."""

    ok: bool
    poses: np.ndarray
    message: str = ""


def _xy_yaw(pose_stamped: Any) -> tuple[np.ndarray, float, str]:
    p = pose_stamped.pose.position
    q = pose_stamped.pose.orientation
    yaw = float(np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z)))
    return np.array([float(p.x), float(p.y)]), yaw, str(pose_stamped.header.frame_id)


def densify(waypoints: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` m along the polyline ``waypoints`` (K,2), both ends kept."""
    out = [waypoints[:1]]
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def plan_request(queries: SceneQueries, request: Any, frame_id: str, agent_radius: float = 0.2,
                 step: float = 0.05, unknown: str = "interior", uncertainty: float = UNCERTAINTY,
                 squeeze: float = SQUEEZE) -> PlanResult:
    """Answer a GetPlan request on the map: a path for a disc of ``agent_radius`` m, resampled
    every ``step`` m, with ``unknown`` cells treated as :mod:`.planning` says, margins of
    ``uncertainty`` standard deviations (:mod:`.margins`) and a ``squeeze`` (m) where nothing
    else gets through (:mod:`.planning`). ``request.tolerance`` (m) widens how
    far start and goal may move onto traversable floor (at least the radius). Empty frame ids
    count as ``frame_id``."""
    try:
        start, _, f_start = _xy_yaw(request.start)
        goal, goal_yaw, f_goal = _xy_yaw(request.goal)
    except AttributeError as e:
        return PlanResult(False, np.zeros((0, 4)), f"malformed request: {e}")
    for f in (f_start, f_goal):
        if f and f != frame_id:
            return PlanResult(False, np.zeros((0, 4)), f"poses must be in frame {frame_id!r}, got {f!r}")
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal))):
        return PlanResult(False, np.zeros((0, 4)), "start or goal is not finite")
    if queries.grid is None:
        return PlanResult(False, np.zeros((0, 4)), "the map has no navigation grid yet")
    tol = float(getattr(request, "tolerance", 0.0) or 0.0)
    snap = max(agent_radius, tol if np.isfinite(tol) else 0.0)
    path = queries.plan(start, goal, agent_radius=agent_radius, unknown=unknown, snap_distance=snap,
                        uncertainty=uncertainty, squeeze=squeeze)
    if path is None:
        return PlanResult(False, np.zeros((0, 4)), "no path")
    pts = densify(np.array(path), step)
    d = np.diff(pts, axis=0)
    yaw = np.append(np.arctan2(d[:, 1], d[:, 0]), goal_yaw)
    if len(pts) > 1:
        yaw[-1] = goal_yaw
    z = np.full(len(pts), queries.scene.floor_z)
    return PlanResult(True, np.column_stack([pts, z, yaw]))


def path_message(result: PlanResult, types: Any, stamp_ns: int, frame_id: str) -> Any:
    """A ``nav_msgs/Path`` of ``types`` (``msg_conversion.MsgTypes``) holding the result's poses."""
    from msg_conversion.markers import make_pose
    from msg_conversion.stamps import make_header

    header = make_header(types, stamp_ns, frame_id)
    poses = []
    for x, y, z, yaw in result.poses:
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        poses.append(types.make_by_name("geometry_msgs/msg/PoseStamped", header=header,
                                        pose=make_pose(types, (x, y, z), R)))
    return types.make_by_name("nav_msgs/msg/Path", header=header, poses=poses)
