"""Published scene objects (world frame: z up, metres; stamps int ns)."""

from __future__ import annotations

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
    #: one of :data:`shape_detector.classes.CLASSES`, decided from the accumulated class evidence
    class_name: str
    #: 0..1; grows with consistent observations
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

    def to_dict(self) -> dict:
        """The JSON form (``"class"`` for ``class_name``)."""
        return {"id": int(self.id), "class": self.class_name, "score": float(self.score),
                "center": np.asarray(self.center, float).tolist(), "size": np.asarray(self.size, float).tolist(),
                "rotation": np.asarray(self.rotation, float).tolist(), "yaw": float(self.yaw),
                "observations": int(self.observations), "first_seen_ns": int(self.first_seen_ns),
                "last_seen_ns": int(self.last_seen_ns), "primitives": [p.to_dict() for p in self.primitives]}

    @classmethod
    def from_dict(cls, d: dict) -> SceneObject:
        """From the JSON form (see :meth:`to_dict`)."""
        return cls(id=int(d["id"]), class_name=str(d["class"]), score=float(d.get("score", 1.0)),
                   center=np.asarray(d["center"], float).reshape(3), size=np.asarray(d["size"], float).reshape(3),
                   rotation=np.asarray(d["rotation"], float).reshape(3, 3), yaw=float(d.get("yaw", 0.0)),
                   observations=int(d.get("observations", 1)), first_seen_ns=int(d.get("first_seen_ns", 0)),
                   last_seen_ns=int(d.get("last_seen_ns", 0)),
                   primitives=[ScenePrimitive.from_dict(p) for p in d.get("primitives", [])])
