"""``SceneQueries``: the AR / robot questions asked of one scene map, in one object.

World frame, z up, metres. Load once, ask many times::

    q = SceneQueries.load("scene.json")
    hit = q.raycast(camera_position, tap_direction)
    path = q.plan((0.5, 0.5), (3.0, 2.0), agent_radius=0.25)

The navigation graph is built once per agent radius and cached. A JSON file is read as
saved (its grid cell for cell), a live ``SceneMap`` through ``objects()`` and ``grid()``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from . import collision, planning
from .affordances import Surface, surfaces
from .margins import UNCERTAINTY
from .rays import RayHit, RayHits, raycast, raycast_many
from ..scene.grid import NavGrid
from .scene_data import load_scene


class SceneQueries:
    """Collision, ray casts, paths and surfaces on one scene (see module doc)."""

    def __init__(self, scene: Any) -> None:
        """``scene``: a ``SceneMap``, an ``ArScene``, scene objects, the JSON dict or its path; a
        live ``SceneMap`` is copied as it is now (make new queries after it updates)."""
        self.scene = load_scene(scene)
        self._graphs: dict[tuple[float, str, float, float], planning.CellGraph] = {}
        self._surfaces: list[Surface] | None = None

    @classmethod
    def load(cls, path: str | Path) -> SceneQueries:
        """Queries on the scene JSON written by ``--scene-out``."""
        return cls(Path(path))

    @property
    def grid(self) -> NavGrid | None:
        """The floor grid (None: the scene has none)."""
        return self.scene.grid

    def collides(self, point: np.ndarray, radius: float = 0.0, surfaces: bool = True) -> bool:
        """Does a sphere (world centre (3,), ``radius`` m) touch any furniture primitive (or,
        with ``surfaces``, the furniture's observed surface)?"""
        return collision.collides(self.scene, point, radius, surfaces)

    def collides_many(self, points: np.ndarray, radius: float = 0.0, surfaces: bool = True) -> np.ndarray:
        """(N,) bool for spheres at ``points`` (N,3)."""
        return collision.collides_many(self.scene, points, radius, surfaces)

    def contacts(self, points: np.ndarray, radius: float = 0.0, surfaces: bool = True) -> list[tuple[int, int]]:
        """Distinct (object_id, primitive_index) touched by spheres at ``points`` (N,3); -1: the
        object's box or observed surface."""
        return collision.contacts(self.scene, points, radius, surfaces)

    def raycast(self, origin: np.ndarray, direction: np.ndarray, max_distance: float = np.inf,
                surfaces: bool = True) -> RayHit | None:
        """First hit of a world ray on furniture (its observed surface where the ray meets one,
        else its primitives; ``surfaces=False``: the primitives only) or the floor (object id 0),
        or None."""
        return raycast(self.scene, origin, direction, max_distance, surfaces=surfaces)

    def raycast_many(self, origins: np.ndarray, directions: np.ndarray, max_distance: float = np.inf,
                     surfaces: bool = True) -> RayHits:
        """First hits of N rays (arrays; distance inf = no hit); ``surfaces`` as :meth:`raycast`."""
        return raycast_many(self.scene, origins, directions, max_distance, surfaces=surfaces)

    def graph(self, agent_radius: float, unknown: str = "interior", uncertainty: float = UNCERTAINTY,
              squeeze: float = planning.SQUEEZE) -> planning.CellGraph:
        """The cached navigation graph for a disc of ``agent_radius`` m (margins of
        ``uncertainty`` standard deviations, :mod:`.margins`; ``squeeze`` as :func:`.planning.plan`)."""
        if self.scene.grid is None:
            raise ValueError("this scene has no navigation grid")
        key = (round(float(agent_radius), 6), str(unknown), round(float(uncertainty), 6), round(float(squeeze), 6))
        if key not in self._graphs:
            padded, grid = planning.planning_grids(self.scene, uncertainty)
            self._graphs[key] = planning.nav_graph(padded, agent_radius, unknown, grid, squeeze)
        return self._graphs[key]

    def plan(self, start_xy: Any, goal_xy: Any, agent_radius: float = 0.2, unknown: str = "interior",
             snap_distance: float | None = None, uncertainty: float = UNCERTAINTY,
             squeeze: float = planning.SQUEEZE) -> list[tuple[float, float]] | None:
        """Smoothed shortest path (world (x, y) waypoints) on the grid, or None; ``unknown``:
        ``"interior"`` (default), ``"blocked"`` or ``"free"`` (see :mod:`.planning`);
        ``uncertainty``: margins where the map is unsure of a box (:mod:`.margins`, 0 = none);
        ``squeeze``: how much closer (m) a plan may pass where nothing else gets through (0 = never)."""
        if not np.isfinite(agent_radius) or agent_radius < 0:
            raise ValueError(f"agent_radius={agent_radius} must be finite and >= 0 (metres)")
        g = self.graph(agent_radius, unknown, uncertainty, squeeze)
        snap = planning.default_snap(agent_radius) if snap_distance is None else float(snap_distance)
        return planning.plan_on_graph(self.scene.grid, g, start_xy, goal_xy, snap)

    def surfaces(self) -> list[Surface]:
        """Usable horizontal top faces (cached)."""
        if self._surfaces is None:
            self._surfaces = surfaces(self.scene)
        return self._surfaces
