"""The scene map's JSON form (world frame, z up, metres; stamps int ns).

::

    {"frame_id": "odom", "stamp_ns": int,
     "objects": [{"id", "class", "score", "center": [x, y, z], "size": [l, w, h],
                  "rotation": [[3x3]] (columns = box axes, world), "yaw", "observations",
                  "first_seen_ns", "last_seen_ns",
                  "primitives": [{"center": [3], "size": [3], "rotation": [[3x3]]}],
                  "face_sd": [4] (spread of the observed -x, +x, -y, +y faces, m; optional),
                  "class_probs": {class: probability} (classes under 5% left out; optional),
                  "track_score": the track's own score, "score" being the track classifier's
                                 class probability (optional),
                  "surface" (optional): {"encoding": "base64-int16-mm-from-center", "count",
                               "data": observed surface points, x y z int16 mm from "center"}}],
     "grid": {"resolution", "origin": [x, y], "width", "height", "floor_z",
              "encoding": "base64-int8", "data": base64 of the (height, width) int8 cells, row-major},
     "structure" (optional): {"center": [x, y, z], "encoding": "base64-int16-mm-from-center", "count",
                              "data": observed surface points no object claims (walls, clutter,
                              furniture not mapped yet), x y z int16 mm from "center"}}
"""

from __future__ import annotations

import base64
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from .grid import NavGrid
from .types import SceneObject, surface_from_dict, surface_to_dict

log = logging.getLogger(__name__)


def grid_to_dict(grid: NavGrid) -> dict[str, Any]:
    """The ``"grid"`` entry."""
    data = np.ascontiguousarray(grid.data, dtype=np.int8)
    return {"resolution": float(grid.resolution), "origin": [float(v) for v in grid.origin],
            "width": grid.width, "height": grid.height, "floor_z": float(grid.floor_z),
            "encoding": "base64-int8", "data": base64.b64encode(data.tobytes()).decode("ascii")}


def grid_from_dict(d: dict[str, Any]) -> NavGrid:
    """A :class:`NavGrid` from its ``"grid"`` entry; ValueError when the cells do not fit."""
    h, w = int(d["height"]), int(d["width"])
    enc = d.get("encoding", "base64-int8")
    if "data" not in d:  # header only: nothing known
        cells = np.full((h, w), -1, np.int8)
    elif enc == "base64-int8":
        cells = np.frombuffer(base64.b64decode(d["data"]), dtype=np.int8)
        if cells.size != h * w:
            raise ValueError(f"grid data holds {cells.size} cells, expected {h} x {w}")
        cells = cells.reshape(h, w).copy()
    else:
        raise ValueError(f"unknown grid encoding {enc!r}")
    return NavGrid(float(d["resolution"]), np.asarray(d["origin"], float), cells, float(d.get("floor_z", 0.0)))


def scene_to_dict(frame_id: str, stamp_ns: int, objects: list[SceneObject], grid: NavGrid,
                  structure: np.ndarray | None = None) -> dict[str, Any]:
    """The whole JSON document as a dict (``structure``: (K,3) world points, optional)."""
    d = {"frame_id": frame_id, "stamp_ns": int(stamp_ns), "objects": [o.to_dict() for o in objects],
         "grid": grid_to_dict(grid)}
    if structure is not None and len(structure):
        pts = np.asarray(structure, float).reshape(-1, 3)
        center = np.round(0.5 * (pts.min(0) + pts.max(0)), 2)  # int16 millimetres reach 32 m either way
        keep = np.all(np.abs(pts - center) < 32.0, axis=1)
        if not keep.all():
            log.warning("scene JSON: %d observed points more than 32 m from the others' centre not written",
                        int((~keep).sum()))
        d["structure"] = {"center": center.tolist(), **surface_to_dict(pts[keep], center)}
    return d


def structure_from_dict(d: dict[str, Any]) -> np.ndarray:
    """(K,3) world points of a document's ``"structure"`` entry ((0,3) without one);
    ValueError on a malformed entry."""
    s = d.get("structure")
    if not s:
        return np.zeros((0, 3))
    try:
        return surface_from_dict(s, np.asarray(s["center"], float).reshape(3))
    except (KeyError, TypeError) as e:
        raise ValueError(f"scene JSON 'structure' lacks or mistypes a field: {e}") from None


def write_json(path: str | Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` to ``path`` atomically (a temporary file beside it, renamed), so that a
    reader never sees a half-written map."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc), encoding="utf-8")
    os.replace(tmp, path)


def load_dict(path_or_dict: str | Path | dict[str, Any]) -> dict[str, Any]:
    """A JSON document given as a dict or a file path; ValueError when it is not a scene."""
    if isinstance(path_or_dict, dict):
        d = path_or_dict
    else:
        with open(path_or_dict, encoding="utf-8") as f:
            d = json.load(f)
    if not isinstance(d, dict) or "objects" not in d or "frame_id" not in d:
        raise ValueError("not a scene map JSON document (needs 'frame_id' and 'objects')")
    return d
