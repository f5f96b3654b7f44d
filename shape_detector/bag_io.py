"""Compatibility names for the bag modules (import from the modules themselves in new code).

* frame preparation: :mod:`shape_detector.frame_prep`
* opening bags, raw messages, topic names: :mod:`shape_detector.bags.source`
* topic selection: :mod:`shape_detector.bags.topics`
* synchronised frames: :mod:`shape_detector.bags.reader`
* damaged / truncated MCAP: :mod:`shape_detector.bags.mcap_recovery`, :mod:`~shape_detector.bags.mcap_check`,
  :mod:`~shape_detector.bags.mcap_checked`
* ROS 1 -> ROS 2 messages: :mod:`shape_detector.bags.ros1`
* the output bag: :mod:`shape_detector.bags.output`; synthetic RGB-D bags: :mod:`shape_detector.synth.bag`
"""

from __future__ import annotations

from typing import Any

from .bags.reader import BagFrameReader, ReadStats, SyncedFrame, iter_frames
from .bags.ros1 import convert_message
from .bags.source import (
    CAMERA_INFO_T,
    DET2D_T,
    DET3D_T,
    DETECTIONS_TOPIC,
    IMAGE_T,
    IMU_T,
    MAP_TOPIC,
    MARKERS_T,
    MARKERS_TOPIC,
    SCENE_TOPIC,
    BagReadError,
    BagSource,
    RawMessage,
    open_bag,
    read_messages,
)
from .bags.topics import COLOR_ENCODINGS, DEPTH_ENCODINGS, TopicSelection, select_topics
from .frame_prep import FrameError, PreparedFrame, prepare_frame


def __getattr__(name: str) -> Any:
    # lazy: these modules import this package's heavier parts
    if name == "OutputBag":
        from .bags.output import OutputBag

        return OutputBag
    if name == "write_rgbd_bag":
        from .synth.bag import write_rgbd_bag

        return write_rgbd_bag
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "CAMERA_INFO_T",
    "COLOR_ENCODINGS",
    "DEPTH_ENCODINGS",
    "DET2D_T",
    "DET3D_T",
    "DETECTIONS_TOPIC",
    "IMAGE_T",
    "IMU_T",
    "MAP_TOPIC",
    "MARKERS_T",
    "MARKERS_TOPIC",
    "SCENE_TOPIC",
    "BagFrameReader",
    "BagReadError",
    "BagSource",
    "FrameError",
    "PreparedFrame",
    "RawMessage",
    "ReadStats",
    "SyncedFrame",
    "TopicSelection",
    "convert_message",
    "iter_frames",
    "open_bag",
    "prepare_frame",
    "read_messages",
    "select_topics",
]
