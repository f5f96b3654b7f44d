"""Message-class namespaces for the two message flavours this package handles.

* ``rclpy`` - the generated Python classes of a ROS 2 install (``sensor_msgs.msg.Image`` ...),
  used by the live node;
* ``rosbags`` - the dataclasses of a :mod:`rosbags` typestore, used to read and write bags
  without a ROS install.

Conversion functions take a :class:`MsgTypes` to *build* messages and duck-type fields
when *reading* them, so they work on either flavour. Nothing here imports rclpy (or any
ROS package) at module level.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: rosbags base-type name -> numpy dtype for numeric fields stored as numpy arrays.
_BASE_DTYPES: dict[str, Any] = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}

# rosbags' Nodetype values (rosbags.interfaces.Nodetype); compared by value to stay
# independent of the enum's import path.
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4

#: (attribute on MsgTypes, ROS 2 type name); the vision_msgs ones are optional.
_CORE_TYPES: tuple[tuple[str, str], ...] = (
    ("Header", "std_msgs/msg/Header"),
    ("ColorRGBA", "std_msgs/msg/ColorRGBA"),
    ("Time", "builtin_interfaces/msg/Time"),
    ("Duration", "builtin_interfaces/msg/Duration"),
    ("Image", "sensor_msgs/msg/Image"),
    ("CameraInfo", "sensor_msgs/msg/CameraInfo"),
    ("Marker", "visualization_msgs/msg/Marker"),
    ("MarkerArray", "visualization_msgs/msg/MarkerArray"),
    ("Point", "geometry_msgs/msg/Point"),
    ("Pose", "geometry_msgs/msg/Pose"),
    ("Quaternion", "geometry_msgs/msg/Quaternion"),
    ("Vector3", "geometry_msgs/msg/Vector3"),
)
_VISION_TYPES: tuple[tuple[str, str], ...] = (
    ("Detection3DArray", "vision_msgs/msg/Detection3DArray"),
    ("Detection3D", "vision_msgs/msg/Detection3D"),
    ("ObjectHypothesisWithPose", "vision_msgs/msg/ObjectHypothesisWithPose"),
    ("ObjectHypothesis", "vision_msgs/msg/ObjectHypothesis"),
    ("BoundingBox3D", "vision_msgs/msg/BoundingBox3D"),
    ("Detection2DArray", "vision_msgs/msg/Detection2DArray"),
    ("Detection2D", "vision_msgs/msg/Detection2D"),
    ("BoundingBox2D", "vision_msgs/msg/BoundingBox2D"),
)


class MsgTypes:
    """A namespace of message classes of one flavour plus a generic constructor.

    Attributes: ``Header, Time, Duration, Image, CameraInfo, Marker, MarkerArray, Point,
    Pose, Quaternion, Vector3, ColorRGBA`` always; ``Detection3DArray, Detection3D,
    ObjectHypothesisWithPose, ObjectHypothesis, BoundingBox3D, Detection2DArray,
    Detection2D, BoundingBox2D`` when vision_msgs is available, else ``None``.
    ``flavour`` is ``'rclpy'`` or ``'rosbags'``; ``typestore`` the rosbags typestore (None
    for rclpy).
    """

    Header: Any = None
    Time: Any = None
    Duration: Any = None
    Image: Any = None
    CameraInfo: Any = None
    Marker: Any = None
    MarkerArray: Any = None
    Point: Any = None
    Pose: Any = None
    Quaternion: Any = None
    Vector3: Any = None
    ColorRGBA: Any = None
    Detection3DArray: Any = None
    Detection3D: Any = None
    ObjectHypothesisWithPose: Any = None
    ObjectHypothesis: Any = None
    BoundingBox3D: Any = None
    Detection2DArray: Any = None
    Detection2D: Any = None
    BoundingBox2D: Any = None

    def __init__(self, flavour: str, classes: dict[str, Any], typestore: Any = None) -> None:
        if flavour not in ("rclpy", "rosbags"):
            raise ValueError(f"flavour must be 'rclpy' or 'rosbags', got {flavour!r}")
        self.flavour = flavour
        self.typestore = typestore
        for name, cls in classes.items():
            setattr(self, name, cls)

    @property
    def has_vision_msgs(self) -> bool:
        """True when the vision_msgs detection classes are available."""
        return self.Detection3DArray is not None

    def make(self, cls: Any, **fields: Any) -> Any:
        """An instance of message class ``cls`` with ``fields`` set and every other field at
        its default (recursively for nested messages).

        rclpy classes fill defaults themselves; rosbags dataclasses need every field, so
        the defaults are built from the typestore's field definitions.
        """
        if cls is None:
            raise ValueError("message class is None (type not available in this MsgTypes)")
        if self.flavour == "rclpy":
            return cls(**fields)
        msgtype = getattr(cls, "__msgtype__", None)
        if msgtype is None:
            raise TypeError(f"{cls!r} is not a rosbags message class")
        fielddefs = self.typestore.fielddefs[msgtype][1]
        known = {name for name, _ in fielddefs}
        unknown = set(fields) - known
        if unknown:
            raise TypeError(f"{msgtype} has no field(s) {sorted(unknown)}")
        kwargs = {}
        for name, desc in fielddefs:
            kwargs[name] = fields[name] if name in fields else self._default(desc)
        if msgtype == "geometry_msgs/msg/Quaternion" and "w" not in fields:
            kwargs["w"] = 1.0  # the .msg default (rosbags' field definitions drop it)
        return cls(**kwargs)

    def make_by_name(self, msgtype: str, **fields: Any) -> Any:
        """Like :meth:`make` with a ROS type name (``'geometry_msgs/msg/PoseWithCovariance'``)."""
        return self.make(self.get_class(msgtype), **fields)

    def get_class(self, msgtype: str) -> Any:
        """The message class of ROS type ``msgtype`` (``pkg/msg/Name`` or ``pkg/Name``)."""
        pkg, name = _split_type(msgtype)
        if self.flavour == "rosbags":
            return self.typestore.types[f"{pkg}/msg/{name}"]
        import importlib

        return getattr(importlib.import_module(f"{pkg}.msg"), name)

    # --- rosbags defaults -------------------------------------------------------------
    def _default(self, desc: Any) -> Any:
        kind = int(desc[0])
        if kind == _BASE:
            return _base_default(desc[1][0])
        if kind == _NAME:
            return self.make(self.typestore.types[desc[1]])
        if kind in (_ARRAY, _SEQUENCE):
            sub, length = desc[1]
            n = length if kind == _ARRAY else 0
            if int(sub[0]) == _BASE and sub[1][0] in _BASE_DTYPES:
                return np.zeros(n, dtype=_BASE_DTYPES[sub[1][0]])
            return [self._default(sub) for _ in range(n)]
        raise TypeError(f"unsupported rosbags field description {desc!r}")

    def __repr__(self) -> str:
        return f"MsgTypes(flavour={self.flavour!r}, vision_msgs={self.has_vision_msgs})"


def _base_default(basename: str) -> Any:
    if basename in ("string", "wstring"):
        return ""
    if basename == "bool":
        return False
    if basename.startswith("float"):
        return 0.0
    return 0


def _split_type(msgtype: str) -> tuple[str, str]:
    parts = msgtype.split("/")
    if len(parts) == 3:
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f"bad message type name {msgtype!r}")


def rclpy_types() -> MsgTypes:
    """The rclpy (generated ROS 2 Python) message classes; vision_msgs if importable."""
    import importlib

    classes: dict[str, Any] = {}
    for attr, msgtype in _CORE_TYPES:
        pkg, name = _split_type(msgtype)
        classes[attr] = getattr(importlib.import_module(f"{pkg}.msg"), name)
    try:
        vision = importlib.import_module("vision_msgs.msg")
    except ImportError:
        vision = None
    for attr, msgtype in _VISION_TYPES:
        classes[attr] = getattr(vision, _split_type(msgtype)[1], None) if vision else None
    return MsgTypes("rclpy", classes)


_ROSBAGS_CACHE: dict[int, MsgTypes] = {}


def rosbags_types(typestore: Any = None) -> MsgTypes:
    """The rosbags dataclasses of ``typestore`` (default: ROS 2 Jazzy) with vision_msgs
    registered into it (so Detection3DArray etc. can be written to bags)."""
    from rosbags.typesys import Stores, get_typestore

    from .vision_msgs_defs import register_vision_msgs

    if typestore is None:
        cached = _ROSBAGS_CACHE.get(0)
        if cached is not None:
            return cached
        store = get_typestore(Stores.ROS2_JAZZY)
    else:
        store = typestore
    register_vision_msgs(store)
    classes = {attr: store.types[msgtype] for attr, msgtype in _CORE_TYPES}
    for attr, msgtype in _VISION_TYPES:
        classes[attr] = store.types.get(msgtype)
    types = MsgTypes("rosbags", classes, typestore=store)
    if typestore is None:
        _ROSBAGS_CACHE[0] = types
    return types


def message_type_name(msg_or_cls: Any) -> str:
    """ROS type name ``pkg/msg/Name`` of a message (or class) of either flavour."""
    t = getattr(msg_or_cls, "__msgtype__", None)
    if isinstance(t, str):
        return t
    cls = msg_or_cls if isinstance(msg_or_cls, type) else type(msg_or_cls)
    module = cls.__module__.split(".")
    return f"{module[0]}/msg/{cls.__name__}"
