"""AR and robot queries on a scene map: collision, ray casts, paths, surfaces (pure numpy).

World frame z up, metres. Start with :class:`SceneQueries`.
"""

from .affordances import Surface, surfaces
from .collision import collides, collides_many, contacts
from .planning import plan
from .queries import SceneQueries
from .rays import RayHit, RayHits, raycast, raycast_many
from .scene_data import FLOOR_ID, STRUCTURE_ID, ArScene, load_scene

__all__ = [
    "FLOOR_ID", "STRUCTURE_ID", "ArScene", "RayHit", "RayHits", "SceneQueries", "Surface",
    "collides", "collides_many", "contacts", "load_scene", "plan", "raycast", "raycast_many", "surfaces",
]
