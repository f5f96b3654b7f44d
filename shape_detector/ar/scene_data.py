"""The scene as the AR queries see it: flat arrays of oriented boxes plus the floor grid.

World frame: z up, metres. Each object contributes its primitives (cuboid parts) or, when it
has none, its own box. ``ArScene`` accepts anything shaped like the scene API
(``SceneMap``, a list of ``SceneObject``, the JSON dict written by ``--scene-out`` or its path)
so the same queries work live and offline.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence
from typing import Any

import numpy as np

#: object id reported for hits on the floor plane (track ids start at 1).
FLOOR_ID = 0


@dataclass
class ArPrimitive:
    """One cuboid part, world frame: centre (3,), full size (3,), rotation (3,3) columns = axes."""

    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray


@dataclass
class ArObject:
    """The fields of ``shape_detector.scene.SceneObject`` the queries use (world frame)."""

    id: int
    class_name: str
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    primitives: list[ArPrimitive] = field(default_factory=list)
    score: float = 1.0


@dataclass
class ArGrid:
    """Floor grid like ``NavGrid``: int8 cells (-1 unknown, 0 free, 100 occupied), row = y, col = x."""

    resolution: float
    origin: np.ndarray
    data: np.ndarray
    floor_z: float = 0.0

    @property
    def height(self) -> int:
        """Rows (y)."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Columns (x)."""
        return int(self.data.shape[1])


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


def _as_object(o: Any) -> ArObject:
    prims = [
        ArPrimitive(
            _arr(p.center, (3,), "primitive center"),
            np.abs(_arr(p.size, (3,), "primitive size")),
            _arr(p.rotation, (3, 3), "primitive rotation"),
        )
        for p in getattr(o, "primitives", []) or []
    ]
    return ArObject(
        id=int(o.id),
        class_name=str(o.class_name),
        center=_arr(o.center, (3,), "object center"),
        size=np.abs(_arr(o.size, (3,), "object size")),
        rotation=_arr(o.rotation, (3, 3), "object rotation"),
        primitives=prims,
        score=float(getattr(o, "score", 1.0)),
    )


def build_boxes(objects: Sequence[ArObject]) -> BoxSet:
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


def decode_grid_data(d: dict[str, Any]) -> np.ndarray:
    """Cells (height, width) int8 of a JSON grid: a flat or nested list, base64 of int8, or
    run-length pairs ``[[value, count], ...]`` (keys ``data`` or ``rle``)."""
    h, w = int(d["height"]), int(d["width"])
    raw = d.get("data", d.get("rle"))
    enc = str(d.get("encoding", "")).lower()
    if isinstance(raw, dict):  # {"encoding": ..., "data"/"runs": ...}
        enc = str(raw.get("encoding", enc)).lower()
        raw = raw.get("data", raw.get("runs", raw.get("rle")))
    if isinstance(raw, str):
        cells = np.frombuffer(base64.b64decode(raw), dtype=np.int8).copy()
    elif "rle" in enc or "rle" in d or (isinstance(raw, list) and raw and isinstance(raw[0], (list, tuple))
                                           and len(raw) != h):
        runs = np.asarray(raw, dtype=np.int64).reshape(-1, 2)
        cells = np.repeat(runs[:, 0], runs[:, 1]).astype(np.int8)
    else:
        cells = np.asarray(raw, dtype=np.int64).astype(np.int8).ravel()
    if cells.size != h * w:
        raise ValueError(f"grid data has {cells.size} cells, expected {h}x{w}")
    return cells.reshape(h, w)


def grid_from_json(d: dict[str, Any]) -> ArGrid:
    """An :class:`ArGrid` from the ``grid`` entry of the scene JSON."""
    return ArGrid(float(d["resolution"]), _arr(d["origin"], (2,), "grid origin"), decode_grid_data(d),
                  float(d.get("floor_z", 0.0)))


def objects_from_json(d: dict[str, Any]) -> list[ArObject]:
    """Objects of the scene JSON (world frame)."""
    out = []
    for o in d.get("objects", []):
        prims = [ArPrimitive(_arr(p["center"], (3,), "primitive center"), np.abs(_arr(p["size"], (3,), "size")),
                             _arr(p["rotation"], (3, 3), "primitive rotation")) for p in o.get("primitives", [])]
        out.append(ArObject(int(o["id"]), str(o["class"]), _arr(o["center"], (3,), "center"),
                            np.abs(_arr(o["size"], (3,), "size")), _arr(o["rotation"], (3, 3), "rotation"),
                            prims, float(o.get("score", 1.0))))
    return out


@dataclass
class ArScene:
    """Objects, their boxes and the floor grid (None: no grid). ``floor_z`` (world z of the
    floor) defaults to the grid's, else to the lowest box bottom (furniture stands on the
    floor), else 0."""

    objects: list[ArObject]
    grid: ArGrid | None = None
    frame_id: str = "odom"
    floor_z: float | None = None
    boxes: BoxSet = field(init=False)

    def __post_init__(self) -> None:
        self.boxes = build_boxes(self.objects)
        if self.floor_z is None:
            if self.grid is not None:
                self.floor_z = float(self.grid.floor_z)
            else:
                self.floor_z = float(self.boxes.lo[:, 2].min()) if len(self.boxes) else 0.0

    def object(self, object_id: int) -> ArObject | None:
        """The object with this track id, or None."""
        return next((o for o in self.objects if o.id == object_id), None)


def _grid_of(g: Any) -> ArGrid | None:
    if g is None:
        return None
    data = np.asarray(g.data)
    if data.ndim != 2:
        raise ValueError(f"grid data must be 2D, got shape {data.shape}")
    return ArGrid(float(g.resolution), _arr(g.origin, (2,), "grid origin"), data.astype(np.int8),
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
            grid = grid_from_json(source["grid"]) if source.get("grid") else None
            return ArScene(objects_from_json(source), grid, str(source.get("frame_id", "odom")))
        except (KeyError, TypeError) as e:
            raise ValueError(f"scene JSON lacks or mistypes a field: {e}") from None
    if hasattr(source, "objects") and callable(source.objects):
        grid_fn = getattr(source, "grid", None)
        grid = _grid_of(grid_fn() if callable(grid_fn) else grid_fn)
        return ArScene([_as_object(o) for o in source.objects()], grid, str(getattr(source, "frame_id", "odom")))
    if isinstance(source, (list, tuple)):
        return ArScene([_as_object(o) for o in source])
    raise ValueError(f"cannot read a scene from {type(source).__name__}")


def as_grid(source: Any) -> ArGrid:
    """The floor grid of a scene (anything :func:`load_scene` reads) or of a ``NavGrid``-like
    object (``resolution``, ``origin``, ``data``, ``floor_z``); ValueError when there is none."""
    if isinstance(source, ArGrid):
        return source
    if hasattr(source, "resolution") and hasattr(source, "data"):
        grid = _grid_of(source)
    else:
        grid = load_scene(source).grid
    if grid is None:
        raise ValueError("the scene has no navigation grid")
    return grid
