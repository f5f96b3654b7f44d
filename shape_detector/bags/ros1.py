"""ROS 1 messages -> ROS 2 messages of the same type (rosbags typestores), for copying ROS 1 bags."""

from __future__ import annotations

from typing import Any

import numpy as np


def _fielddefs(store: Any, msgtype: str) -> list:
    """rosbags field definitions of ``msgtype`` in ``store``."""
    return store.fielddefs[msgtype][1]


def convert_message(msg: Any, msgtype: str, store: Any) -> Any:
    """A message of ``store`` (e.g. ROS 2 Jazzy) with the field values of ``msg`` (e.g. a
    ROS 1 message of the same type): fields matched by name, case-insensitively (ROS 1
    CameraInfo ``K`` -> ``k``); fields the source lacks get defaults (``seq`` dropped)."""
    from msg_conversion.msgtypes import MsgTypes

    helper = MsgTypes("rosbags", {}, typestore=store)

    def conv(value: Any, desc: Any) -> Any:
        kind = int(desc[0])
        if kind == 1:  # base
            base = desc[1][0]
            if base in ("string", "wstring"):
                return str(value)
            if base == "bool":
                return bool(value)
            if base.startswith("float"):
                return float(value)
            return int(value)
        if kind == 2:  # nested message
            return build(value, desc[1])
        sub = desc[1][0]
        if int(sub[0]) == 1 and sub[1][0] not in ("string", "wstring"):
            dt = {"float32": np.float32, "float64": np.float64, "bool": np.bool_}.get(sub[1][0])
            arr = np.asarray(value)
            if dt is None:
                dt = helper._default(desc).dtype if kind == 3 else np.asarray(helper._default((4, (sub, 0)))).dtype
            return np.asarray(arr, dtype=dt).reshape(-1)
        return [conv(v, sub) for v in value]

    def build(src: Any, typ: str) -> Any:
        cls = store.types[typ]
        kwargs = {}
        for name, desc in _fielddefs(store, typ):
            value = None
            for cand in (name, name.upper(), name.lower()):
                if hasattr(src, cand):
                    value = getattr(src, cand)
                    break
            else:
                if typ == "builtin_interfaces/msg/Time" and hasattr(src, "secs"):
                    value = {"sec": src.secs, "nanosec": src.nsecs}[name]
            kwargs[name] = helper._default(desc) if value is None else conv(value, desc)
        return cls(**kwargs)

    return build(msg, msgtype)
