"""The scene as the AR queries see it: flat arrays of oriented boxes plus the floor grid.

World frame: z up, metres. Each object contributes its primitives (cuboid parts) or, when it
has none, its own box. ``ArScene`` accepts anything shaped like the scene API
(``SceneMap``, a list of ``SceneObject``, the JSON dict written by ``--scene-out`` or its path)
so the same queries work live and offline.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..scene.grid import NavGrid
from ..scene.json_io import grid_from_dict, structure_from_dict
from ..scene.types import SceneObject, ScenePrimitive

#: object id reported for hits on the floor plane (track ids start at 1).
FLOOR_ID = 0
#: object id reported for hits on observed surfaces no object claims (walls, clutter, furniture
#: not mapped yet); -1 means no hit
STRUCTURE_ID = -2
#: the structure's points are indexed for ray casts in cubes of this size (metres), each
#: bounded tightly, so that a wall does not span one huge grid
STRUCTURE_BLOCK = 1.0
#: an object's observed surface points count for collisions within its box grown by this
#: much (metres): the points its box claims farther out are mostly the wall or floor beside it
CONTACT_PAD = 0.02


@dataclass
class BoxSet:
    """All boxes of a scene as arrays: ``P`` boxes, world frame.

    ``half`` (P,3) half extents, ``rot`` (P,3,3) columns = box axes, ``object_ids`` (P,)
    owning track id, ``prim_index`` (P,) index into the owner's primitives (-1: the object's
    own box, used when it has no primitives); ``lo``/``hi`` (P,3) world AABB corners.
    """

    centers: np.ndarray
    half: np.ndarray
    rot: np.ndarray
    object_ids: np.ndarray
    prim_index: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def __len__(self) -> int:
        return int(self.centers.shape[0])


def _arr(v: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: expected finite array of shape {shape}, got {a.shape}")
    return a


def _as_object(o: Any) -> SceneObject:
    """A checked :class:`SceneObject` from anything shaped like one (finite arrays, sizes >= 0)."""
    prims = [
        ScenePrimitive(
            _arr(p.center, (3,), "primitive center"),
            np.abs(_arr(p.size, (3,), "primitive size")),
            _arr(p.rotation, (3, 3), "primitive rotation"),
        )
        for p in getattr(o, "primitives", []) or []
    ]
    surface = getattr(o, "surface", None)
    if surface is not None:
        surface = np.asarray(surface, dtype=np.float64).reshape(-1, 3)
        surface = surface[np.all(np.isfinite(surface), axis=1)]
    return SceneObject(
        id=int(o.id), class_name=str(o.class_name), score=float(getattr(o, "score", 1.0)),
        center=_arr(o.center, (3,), "object center"), size=np.abs(_arr(o.size, (3,), "object size")),
        rotation=_arr(o.rotation, (3, 3), "object rotation"), yaw=float(getattr(o, "yaw", 0.0)),
        observations=int(getattr(o, "observations", 1)), first_seen_ns=int(getattr(o, "first_seen_ns", 0)),
        last_seen_ns=int(getattr(o, "last_seen_ns", 0)), primitives=prims, surface=surface,
        face_sd=_face_sd(getattr(o, "face_sd", None)),
        class_probs={str(k): float(v) for k, v in (getattr(o, "class_probs", None) or {}).items()},
        track_score=None if getattr(o, "track_score", None) is None else float(o.track_score),
    )


def _face_sd(v: Any) -> np.ndarray:
    """(4,) face spreads, metres (zeros when the object has none, as maps written before them)."""
    return np.zeros(4) if v is None else np.abs(_arr(v, (4,), "object face_sd"))


def build_boxes(objects: Sequence[SceneObject]) -> BoxSet:
    """Flatten objects to a :class:`BoxSet` (primitives, or the object's box without any)."""
    rows = [(p.center, p.size, p.rotation, o.id, i) for o in objects for i, p in enumerate(o.primitives)]
    rows += [(o.center, o.size, o.rotation, o.id, -1) for o in objects if not o.primitives]
    if not rows:
        z3 = np.zeros((0, 3))
        return BoxSet(z3, z3, np.zeros((0, 3, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64), z3, z3)
    cen, size, rot, oid, pidx = zip(*rows)
    centers = np.array(cen, dtype=np.float64)
    half = 0.5 * np.array(size, dtype=np.float64)
    R = np.array(rot, dtype=np.float64)
    ext = np.einsum("pij,pj->pi", np.abs(R), half)  # world half extents of each box's AABB
    return BoxSet(centers, half, R, np.array(oid, np.int64), np.array(pidx, np.int64), centers - ext, centers + ext)


@dataclass
class ArScene:
    """Objects, their boxes and the floor grid (None: no grid). ``floor_z`` (world z of the
    floor) defaults to the grid's, else to the lowest box bottom (furniture stands on the
    floor), else 0."""

    objects: list[SceneObject]
    grid: NavGrid | None = None
    frame_id: str = "odom"
    floor_z: float | None = None
    #: observed surface points not yet split among the objects ((M,3) world points, the pad by which
    #: an object's box is grown to claim them), as a live ``SceneMap`` hands them over; the split
    #: waits for the first ray cast, which plans and collisions never pay for
    observed: tuple[np.ndarray, float] | None = field(default=None, repr=False)
    #: (K,3) observed surface points no object claims (world), as saved; None: what ``observed``
    #: leaves over, or none
    structure: np.ndarray | None = field(default=None, repr=False)
    boxes: BoxSet = field(init=False)

    def __post_init__(self) -> None:
        self.boxes = build_boxes(self.objects)
        if self.floor_z is None:
            if self.grid is not None:
                self.floor_z = float(self.grid.floor_z)
            else:
                self.floor_z = float(self.boxes.lo[:, 2].min()) if len(self.boxes) else 0.0

    @cached_property
    def _split(self) -> tuple[list[np.ndarray | None], np.ndarray | None]:
        """(each object's observed surface points or None, the structure's or None)."""
        from ..scene.surface import split_points

        surfaces: list = [o.surface for o in self.objects]
        structure = self.structure
        if self.observed is not None and all(s is None for s in surfaces):
            surfaces, rest = split_points(self.observed[0], self.objects, self.observed[1])
            structure = rest if structure is None else structure
        return ([s if s is not None and len(s) else None for s in surfaces],
                structure if structure is not None and len(structure) else None)

    @property
    def surface_points(self) -> list[np.ndarray | None]:
        """Each object's observed surface points (M,3) world: ``SceneObject.surface``, else its
        share of ``observed`` (split on first use); None where it has none."""
        return self._split[0]

    @property
    def structure_points(self) -> np.ndarray | None:
        """(K,3) the observed surface points no object claims (:attr:`structure`, else what
        ``observed`` leaves over), or None."""
        return self._split[1]

    @cached_property
    def surface_index(self) -> Any:
        """The objects' observed surface points (:attr:`surface_points`) and the structure's
        (:attr:`structure_points`, id :data:`STRUCTURE_ID`, in :data:`STRUCTURE_BLOCK` cubes)
        arranged for ray casts (:class:`~shape_detector.ar.surface_rays.SurfaceIndex`, built on
        first use), or None when there are none."""
        given = [(o.id, s, o.rotation) for o, s in zip(self.objects, self.surface_points) if s is not None]
        rest = self.structure_points
        if rest is not None:
            cube = np.floor(rest / STRUCTURE_BLOCK).astype(np.int64)
            order = np.lexsort(cube.T[::-1])
            cube, pts = cube[order], rest[order]
            starts = np.flatnonzero(np.r_[True, np.any(cube[1:] != cube[:-1], axis=1)])
            given += [(STRUCTURE_ID, block, np.eye(3)) for block in np.split(pts, starts[1:])]
        if not given:
            return None  # without importing numba
        from .surface_rays import build_index

        return build_index(given)

    @cached_property
    def contact_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The objects' observed surface points inside their boxes grown by :data:`CONTACT_PAD`,
        for collision queries: ((M,3) world points, (M,) their object ids), or None when there
        are none."""
        from ..geometry import points_in_box

        pts, ids = [], []
        for o, s in zip(self.objects, self.surface_points):
            if s is not None:
                inside = s[points_in_box(s, o.center, np.abs(o.size), o.rotation, CONTACT_PAD)]
                pts.append(inside)
                ids.append(np.full(len(inside), o.id, np.int64))
        if not sum(len(p) for p in pts):
            return None
        return np.concatenate(pts), np.concatenate(ids)

    def object(self, object_id: int) -> SceneObject | None:
        """The object with this track id, or None."""
        return next((o for o in self.objects if o.id == object_id), None)


def _grid_of(g: Any) -> NavGrid | None:
    if g is None:
        return None
    data = np.asarray(g.data)
    if data.ndim != 2:
        raise ValueError(f"grid data must be 2D, got shape {data.shape}")
    return NavGrid(float(g.resolution), _arr(g.origin, (2,), "grid origin"), data.astype(np.int8),
                   float(getattr(g, "floor_z", 0.0)))


def load_scene(source: Any) -> ArScene:
    """An :class:`ArScene` from a ``SceneMap`` (``objects()``/``grid()``), a JSON dict, a path to
    the JSON, an ``ArScene`` or a sequence of scene objects. Raises ``ValueError`` on bad input."""
    if isinstance(source, ArScene):
        return source
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"scene file {path} does not exist")
        try:
            source = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"scene file {path} is not valid JSON: {e}") from None
    if isinstance(source, dict):
        if not isinstance(source.get("objects"), list):
            raise ValueError("not a scene map JSON document (needs an 'objects' list)")
        try:
            grid = _grid_of(grid_from_dict(source["grid"])) if source.get("grid") else None
            objects = [_as_object(SceneObject.from_dict(o)) for o in source["objects"]]
            structure = structure_from_dict(source)
            return ArScene(objects, grid, str(source.get("frame_id", "odom")),
                           structure=structure if len(structure) else None)
        except (KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"scene JSON lacks or mistypes a field: {e}") from None
    if hasattr(source, "objects") and callable(source.objects):
        from ..scene.map import SceneMap

        grid_fn = getattr(source, "grid", None)
        grid = _grid_of(grid_fn() if callable(grid_fn) else grid_fn)
        observed = source.observed_surfaces() if isinstance(source, SceneMap) else None
        return ArScene([_as_object(o) for o in source.objects()], grid, str(getattr(source, "frame_id", "odom")),
                       observed=observed)
    if isinstance(source, (list, tuple)):
        return ArScene([_as_object(o) for o in source])
    raise ValueError(f"cannot read a scene from {type(source).__name__}")


def as_grid(source: Any) -> NavGrid:
    """The floor grid of a scene (anything :func:`load_scene` reads) or of a ``NavGrid``-like
    object (``resolution``, ``origin``, ``data``, ``floor_z``); ValueError when there is none."""
    if isinstance(source, NavGrid):
        return source
    if hasattr(source, "resolution") and hasattr(source, "data"):
        grid = _grid_of(source)
    else:
        grid = load_scene(source).grid
    if grid is None:
        raise ValueError("the scene has no navigation grid")
    return grid
