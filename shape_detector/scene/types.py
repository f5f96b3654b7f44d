"""Published scene objects (world frame: z up, metres; stamps int ns)."""

from __future__ import annotations

import base64
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ScenePrimitive:
    """One cuboid part of a scene object, world frame."""

    #: (3,) centre, metres
    center: np.ndarray
    #: (3,) full extents along the columns of ``rotation``, metres
    size: np.ndarray
    #: (3,3) columns = the part's axes in the world frame
    rotation: np.ndarray

    def to_dict(self) -> dict:
        """The JSON form."""
        return {"center": np.asarray(self.center, float).tolist(), "size": np.asarray(self.size, float).tolist(),
                "rotation": np.asarray(self.rotation, float).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> ScenePrimitive:
        """From the JSON form."""
        return cls(np.asarray(d["center"], float).reshape(3), np.asarray(d["size"], float).reshape(3),
                   np.asarray(d["rotation"], float).reshape(3, 3))


@dataclass
class SceneObject:
    """One confirmed track of the scene map, world frame."""

    #: stable track id (>= 1)
    id: int
    #: one of :data:`shape_detector.classes.CLASSES`, decided by the map's track classifier from the
    #: whole track (its accumulated class evidence, fused box, detections, neighbours), or by the
    #: class evidence alone when the map has none (``SceneConfig.track_classifier``)
    class_name: str
    #: 0..1; with a track classifier the probability that the object is of ``class_name`` (background
    #: counted), else the detections' mean score grown with consistent observations
    score: float
    #: (3,) box centre, metres
    center: np.ndarray
    #: (3,) box extents (l, w, h), h along world up, metres
    size: np.ndarray
    #: (3,3) columns = box axes in the world (third column = +z)
    rotation: np.ndarray
    #: radians, the box x axis about world z
    yaw: float = 0.0
    #: number of frames the object was detected in
    observations: int = 1
    first_seen_ns: int = 0
    last_seen_ns: int = 0
    primitives: list[ScenePrimitive] = field(default_factory=list)
    #: (M,3) observed surface points inside the box (voxel means of the depth, world frame), or
    #: None when not asked for (see :mod:`shape_detector.scene.surface`)
    surface: np.ndarray | None = field(default=None, repr=False)
    #: (4,) how far apart the observations put the box's -x, +x, -y, +y faces (along its axes):
    #: their weighted standard deviation, metres; zeros when unknown
    face_sd: np.ndarray = field(default_factory=lambda: np.zeros(4))
    #: class -> probability, from the track classifier (background left out) or the accumulated
    #: class evidence (classes under 5% left out);
    #: empty when only ``class_name`` is known
    class_probs: dict[str, float] = field(default_factory=dict)
    #: the track's own score (its detections' mean score, grown with consistent observations),
    #: whatever the track classifier decided: how sure the map is that something stands there
    #: (planning's doubt rule reads it); None when unknown (then ``score`` stands in)
    track_score: float | None = None

    @property
    def own_score(self) -> float:
        """How sure the map is that the object stands there: :attr:`track_score`, else
        :attr:`score` (not the track classifier's class probability, which also falls when two
        classes compete)."""
        return float(self.track_score if self.track_score is not None else self.score)

    def to_dict(self) -> dict:
        """The JSON form (``"class"`` for ``class_name``; ``"surface"`` only when there is one)."""
        d = {"id": int(self.id), "class": self.class_name, "score": float(self.score),
             "center": np.asarray(self.center, float).tolist(), "size": np.asarray(self.size, float).tolist(),
             "rotation": np.asarray(self.rotation, float).tolist(), "yaw": float(self.yaw),
             "observations": int(self.observations), "first_seen_ns": int(self.first_seen_ns),
             "last_seen_ns": int(self.last_seen_ns), "primitives": [p.to_dict() for p in self.primitives],
             "face_sd": [round(float(v), 4) for v in np.asarray(self.face_sd, float).reshape(4)]}
        if self.class_probs:
            d["class_probs"] = {str(k): round(float(v), 3) for k, v in self.class_probs.items()}
        if self.track_score is not None:
            d["track_score"] = round(float(self.track_score), 4)
        if self.surface is not None and len(self.surface):
            d["surface"] = surface_to_dict(self.surface, self.center)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SceneObject:
        """From the JSON form (see :meth:`to_dict`)."""
        return cls(id=int(d["id"]), class_name=str(d["class"]), score=float(d.get("score", 1.0)),
                   center=np.asarray(d["center"], float).reshape(3), size=np.asarray(d["size"], float).reshape(3),
                   rotation=np.asarray(d["rotation"], float).reshape(3, 3), yaw=float(d.get("yaw", 0.0)),
                   observations=int(d.get("observations", 1)), first_seen_ns=int(d.get("first_seen_ns", 0)),
                   last_seen_ns=int(d.get("last_seen_ns", 0)),
                   primitives=[ScenePrimitive.from_dict(p) for p in d.get("primitives", [])],
                   surface=surface_from_dict(d["surface"], d["center"]) if d.get("surface") else None,
                   face_sd=np.asarray(d.get("face_sd", np.zeros(4)), float).reshape(4),
                   class_probs={str(k): float(v) for k, v in d.get("class_probs", {}).items()},
                   track_score=float(d["track_score"]) if d.get("track_score") is not None else None)


def object_parts(o: SceneObject) -> list[ScenePrimitive]:
    """The object's primitives, or its own box when it has none."""
    return o.primitives or [ScenePrimitive(o.center, o.size, o.rotation)]


def surface_to_dict(points: np.ndarray, center: np.ndarray) -> dict:
    """The ``"surface"`` entry: points as millimetre offsets from the object's centre, int16
    little-endian x y z per point, base64 (a room's surfaces in a few hundred kB)."""
    mm = np.round((np.asarray(points, float).reshape(-1, 3) - np.asarray(center, float)) * 1000.0)
    mm = np.clip(mm, -32767, 32767).astype("<i2")
    return {"encoding": "base64-int16-mm-from-center", "count": int(len(mm)),
            "data": base64.b64encode(mm.tobytes()).decode("ascii")}


def surface_from_dict(d: dict, center) -> np.ndarray:
    """(M,3) world points of a ``"surface"`` entry; ValueError on an unknown encoding or size."""
    if d.get("encoding") != "base64-int16-mm-from-center":
        raise ValueError(f"unknown surface encoding {d.get('encoding')!r}")
    raw = np.frombuffer(base64.b64decode(d["data"]), dtype="<i2")
    if raw.size != 3 * int(d.get("count", raw.size // 3)) or raw.size % 3:
        raise ValueError(f"surface data holds {raw.size} values, expected 3 x {d.get('count')}")
    return raw.reshape(-1, 3).astype(np.float64) / 1000.0 + np.asarray(center, float).reshape(3)
