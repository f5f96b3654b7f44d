"""Stamps: ``builtin_interfaces/Time`` <-> integer nanoseconds, headers."""

from __future__ import annotations

from typing import Any

from .msgtypes import MsgTypes

_NS = 1_000_000_000


def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a stamp.

    Accepts a ``Time``/``Duration`` message of either flavour (``sec``/``nanosec``), a ROS 1
    style object (``secs``/``nsecs``), an ``rclpy.time.Time`` (``nanoseconds``), a
    ``Header`` (its ``stamp``) or a plain int (returned unchanged).
    """
    if isinstance(stamp, bool):
        raise TypeError("stamp must not be a bool")
    if isinstance(stamp, int):
        return stamp
    if hasattr(stamp, "sec") and hasattr(stamp, "nanosec"):
        return int(stamp.sec) * _NS + int(stamp.nanosec)
    if hasattr(stamp, "secs") and hasattr(stamp, "nsecs"):
        return int(stamp.secs) * _NS + int(stamp.nsecs)
    if hasattr(stamp, "nanoseconds"):
        return int(stamp.nanoseconds)
    if hasattr(stamp, "stamp"):
        return stamp_to_ns(stamp.stamp)
    raise TypeError(f"cannot read a stamp from {type(stamp).__name__}")


def _split_ns(ns: int) -> tuple[int, int]:
    ns = int(ns)
    return ns // _NS, ns % _NS  # floor division keeps nanosec in [0, 1e9)


def ns_to_stamp(ns: int, types: MsgTypes) -> Any:
    """A ``builtin_interfaces/Time`` of ``types`` for integer nanoseconds ``ns``."""
    sec, nanosec = _split_ns(ns)
    return types.make(types.Time, sec=sec, nanosec=nanosec)


def ns_to_duration(ns: int, types: MsgTypes) -> Any:
    """A ``builtin_interfaces/Duration`` of ``types`` for integer nanoseconds ``ns``."""
    sec, nanosec = _split_ns(ns)
    return types.make(types.Duration, sec=sec, nanosec=nanosec)


def seconds_to_duration(seconds: float, types: MsgTypes) -> Any:
    """A ``Duration`` for a float number of seconds (rounded to the nanosecond)."""
    return ns_to_duration(int(round(float(seconds) * _NS)), types)


def make_header(types: MsgTypes, stamp_ns: int, frame_id: str) -> Any:
    """A ``std_msgs/Header`` of ``types`` with the given stamp (ns) and frame id."""
    return types.make(types.Header, stamp=ns_to_stamp(stamp_ns, types), frame_id=str(frame_id))


def header_to_ns_frame(header: Any) -> tuple[int, str]:
    """``(stamp_ns, frame_id)`` of a header of either flavour."""
    return stamp_to_ns(header.stamp), str(header.frame_id)
