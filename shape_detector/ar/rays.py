"""Ray casts against the scene's observed surfaces, oriented boxes and the floor plane.

World frame, metres. Directions need not be unit length; distances are along the unit
direction. Where an object carries observed surface points (``SceneObject.surface``) and the
ray meets them, the hit is on them (:mod:`.surface_rays`: what the camera measured, within a
centimetre or two); elsewhere on the first box (primitives, slab method). Boxes that contain
a ray's origin are ignored by that ray (a camera inside a loosely estimated box still sees
what is in front of it). The observed surfaces no object claims (walls, clutter, furniture not
mapped yet; ``ArScene.structure_points``) stop rays too, reporting ``STRUCTURE_ID``. The floor
is the plane ``z = floor_z`` seen from above; its hits report ``FLOOR_ID``, and no surface
behind it counts.
"""

from __future__ import annotations

from dataclasses import dataclass

from typing import Any

import numpy as np

from .scene_data import FLOOR_ID, ArScene, load_scene

_EPS = 1e-12


@dataclass
class RayHit:
    """First hit of one ray: ``distance`` (m) along the unit direction, the hit object's id
    (``FLOOR_ID`` = 0 for the floor, ``STRUCTURE_ID`` = -2 for an observed surface of no
    object), the outward unit ``normal`` (3,) and ``point`` (3,), world frame;
    ``primitive_index`` into the object's primitives (-1: its box, an observed surface or the floor)."""

    distance: float
    object_id: int
    normal: np.ndarray
    point: np.ndarray
    primitive_index: int = -1


@dataclass
class RayHits:
    """First hits of N rays: ``distance`` (N,) (inf: no hit), ``object_id`` (N,) (as
    :class:`RayHit`; -1: no hit), ``normal`` (N,3), ``box_index`` (N,) into ``scene.boxes`` (-1:
    floor, observed surface or no hit)."""

    distance: np.ndarray
    object_id: np.ndarray
    normal: np.ndarray
    box_index: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: did the ray hit anything."""
        return np.isfinite(self.distance)


def _unit_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim == 1:
        o = o[None]
    if d.ndim == 1:
        d = d[None]
    if o.shape[-1] != 3 or d.shape[-1] != 3 or o.ndim != 2 or d.ndim != 2:
        raise ValueError(f"origins and directions must have shape (N, 3), got {o.shape} and {d.shape}")
    o, d = np.broadcast_arrays(o, d)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    bad = ~(np.isfinite(n[:, 0]) & (n[:, 0] > _EPS) & np.all(np.isfinite(o), axis=1))
    with np.errstate(invalid="ignore"):  # an infinite direction: inf / inf, marked bad anyway
        d = np.where(bad[:, None], np.nan, d / np.where(n > _EPS, n, 1.0))
    return o, d


def raycast_many(scene: ArScene | Any, origins: np.ndarray, directions: np.ndarray, max_distance: float = np.inf,
                 floor: bool = True, surfaces: bool = True) -> RayHits:
    """First hits of rays ``origins`` (N,3) + t ``directions`` (N,3) (either may be (3,)),
    world frame, ``0 < t <= max_distance`` m; ``floor``: also hit the floor plane;
    ``surfaces``: land on the observed surfaces where the ray meets them (module doc)."""
    scene = load_scene(scene)
    o, d = _unit_rays(origins, directions)
    n = len(o)
    dist = np.full(n, np.inf)
    oid = np.full(n, -1, np.int64)
    box = np.full(n, -1, np.int64)
    normal = np.zeros((n, 3))
    if len(scene.boxes) and n:
        from .box_rays import first_boxes  # compiled on first use: a node that never casts skips numba

        b = scene.boxes
        dist, box, normal = first_boxes(o, d, b.centers, b.half, b.rot, max_distance)
        oid = np.where(box >= 0, b.object_ids[np.maximum(box, 0)], -1)
    tf = np.full(n, np.inf)
    if floor:
        with np.errstate(divide="ignore", invalid="ignore"):
            down = (d[:, 2] < -_EPS) & (o[:, 2] > scene.floor_z)
            tf = np.where(down, (scene.floor_z - o[:, 2]) / np.where(down, d[:, 2], -1.0), np.inf)
        tf = np.where(tf <= max_distance, tf, np.inf)
        f = tf < dist
        dist[f], oid[f], box[f] = tf[f], FLOOR_ID, -1
        normal[f] = (0.0, 0.0, 1.0)
    index = scene.surface_index if surfaces else None
    if index is not None and n:
        from .surface_rays import cast as surface_cast  # compiled on first use: a node that never casts skips numba

        ok = np.all(np.isfinite(d), axis=1)
        ts, sid, sn = surface_cast(index, o[ok], d[ok], np.minimum(tf[ok], max_distance))
        s = np.flatnonzero(ok)[np.isfinite(ts)]
        hit = np.isfinite(ts)
        dist[s], oid[s], box[s], normal[s] = ts[hit], sid[hit], -1, sn[hit]
    return RayHits(dist, oid, normal, box)


def raycast(scene: ArScene | Any, origin: np.ndarray, direction: np.ndarray, max_distance: float = np.inf,
            floor: bool = True, surfaces: bool = True) -> RayHit | None:
    """First hit of the ray ``origin`` (3,) + t ``direction`` (3,), world frame; None: no hit
    (``primitive_index`` -1 on the floor, an object's own box or its observed surface)."""
    scene = load_scene(scene)
    hits = raycast_many(scene, np.reshape(origin, (1, 3)), np.reshape(direction, (1, 3)), max_distance, floor,
                        surfaces)
    if not hits.hit[0]:
        return None
    _, d = _unit_rays(np.reshape(origin, (1, 3)), np.reshape(direction, (1, 3)))
    t = float(hits.distance[0])
    bi = int(hits.box_index[0])
    prim = int(scene.boxes.prim_index[bi]) if bi >= 0 else -1
    point = np.asarray(origin, dtype=np.float64).reshape(3) + t * d[0]
    return RayHit(t, int(hits.object_id[0]), hits.normal[0].copy(), point, prim)
