"""The output bag of a replay: a rosbag2 MCAP (CRC-checked chunks) holding the input
topics plus ``/shape_detector/markers`` and ``/shape_detector/detections`` and, with a scene,
``/shape_detector/scene`` (MarkerArray, world frame) and ``/shape_detector/map`` (OccupancyGrid).

Every OS error while writing (disk full, read-only file system, permission denied)
surfaces as :class:`OutputError`, which names the output path and the cause.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Literal

from .ros1 import convert_message
from .source import (
    DET3D_T,
    DETECTIONS_TOPIC,
    MAP_TOPIC,
    MARKERS_T,
    MARKERS_TOPIC,
    OCCUPANCY_T,
    SCENE_TOPIC,
    BagSource,
    RawMessage,
)
from .mcap_writer import CrcWriter
from .output_safety import OutputError


class OutputBag:
    """A rosbag2 MCAP being written at directory ``out_path``.

    ``out_path`` must not exist (``overwrite=True`` first removes an existing bag
    directory; the replay tool does not use this - it writes under a temporary name and
    swaps, see :mod:`shape_detector.bags.output_safety`). ``file_name``: stem of the
    ``.mcap`` file (default: the directory name). ``report_path``: the path named in
    :class:`OutputError` (default ``out_path``)."""

    def __init__(
        self,
        out_path: str | Path,
        overwrite: bool = False,
        write_detections: bool = True,
        *,
        file_name: str | None = None,
        report_path: str | Path | None = None,
    ) -> None:
        from msg_conversion.msgtypes import rosbags_types

        self.path = Path(out_path)
        self.report_path = Path(report_path) if report_path is not None else self.path
        self._closed = True
        if self.path.exists():
            if not overwrite:
                raise FileExistsError(f"output {str(self.path)!r} exists (use --overwrite)")
            _remove_old_bag(self.path)
        self.types = rosbags_types()
        self.store = self.types.typestore
        self._conns: dict[str, Any] = {}
        self._scene_conns: dict[str, Any] = {}
        self.skipped_topics: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.write_detections = bool(write_detections and self.types.has_vision_msgs)
        with self._os_errors():
            self._writer = CrcWriter(self.path, file_name=file_name)
            self._writer.open()
            self._closed = False
            self._markers = self._writer.add_connection(MARKERS_TOPIC, MARKERS_T, typestore=self.store)
            self._dets = (
                self._writer.add_connection(DETECTIONS_TOPIC, DET3D_T, typestore=self.store)
                if self.write_detections else None
            )

    def _os_errors(self) -> Any:
        return _WrapOSError(self.report_path)

    def _connection(self, m: RawMessage, source: BagSource) -> Any:
        conn = self._conns.get(m.topic)
        if conn is not None or m.topic in self.skipped_topics:
            return conn
        if m.topic in (MARKERS_TOPIC, DETECTIONS_TOPIC, SCENE_TOPIC, MAP_TOPIC):
            self.skipped_topics[m.topic] = "the input's own copy; replaced by this run's output"
            return None
        try:
            if source.is_ros1:
                if m.msgtype not in self.store.types:
                    raise KeyError(f"{m.msgtype} has no ROS 2 Jazzy definition")
                conn = self._writer.add_connection(m.topic, m.msgtype, typestore=self.store)
            else:
                store = source.typestore if m.msgtype in source.typestore.types else self.store
                conn = self._writer.add_connection(m.topic, m.msgtype, typestore=store)
        except OSError:
            raise
        except Exception as e:  # noqa: BLE001 - a topic without a usable definition is not copied
            self.skipped_topics[m.topic] = f"{type(e).__name__}: {e}"
            return None
        self._conns[m.topic] = conn
        return conn

    def copy(self, m: RawMessage, source: BagSource) -> None:
        """Copy one input message (ROS 1 messages are converted to ROS 2 CDR)."""
        with self._os_errors():
            conn = self._connection(m, source)
            if conn is None:
                return
            data = m.raw
            if source.is_ros1:
                try:
                    msg = source.deserialize(m.raw, m.msgtype)
                    data = self.store.serialize_cdr(convert_message(msg, m.msgtype, self.store), m.msgtype)
                except Exception as e:  # noqa: BLE001
                    self.skipped_topics[m.topic] = f"conversion to ROS 2 failed: {type(e).__name__}: {e}"
                    return
            self._writer.write(conn, m.log_time_ns, data)
        self.counts[m.topic] = self.counts.get(m.topic, 0) + 1

    def write_objects(self, objects: list, stamp_ns: int, frame_id: str) -> None:
        """Markers (and detections) of one frame, at log time = the frame's stamp (ns)."""
        from msg_conversion.markers import objects_to_markers

        markers = objects_to_markers(objects, self.types, stamp_ns, frame_id)
        with self._os_errors():
            self._writer.write(self._markers, int(stamp_ns), self.store.serialize_cdr(markers, MARKERS_T))
        self.counts[MARKERS_TOPIC] = self.counts.get(MARKERS_TOPIC, 0) + 1
        if self._dets is not None:
            from msg_conversion.detections import objects_to_detection3d_array

            dets = objects_to_detection3d_array(objects, self.types, stamp_ns, frame_id)
            with self._os_errors():
                self._writer.write(self._dets, int(stamp_ns), self.store.serialize_cdr(dets, DET3D_T))
            self.counts[DETECTIONS_TOPIC] = self.counts.get(DETECTIONS_TOPIC, 0) + 1

    def write_scene(self, objects: list, grid: Any, stamp_ns: int, frame_id: str) -> None:
        """The scene's objects (MarkerArray) and navigation grid (OccupancyGrid) in world frame
        ``frame_id``, at log time ``stamp_ns``."""
        from msg_conversion.scene import grid_to_occupancy, scene_to_markers

        with self._os_errors():
            for topic, msgtype, msg in (
                (SCENE_TOPIC, MARKERS_T, scene_to_markers(objects, self.types, stamp_ns, frame_id)),
                (MAP_TOPIC, OCCUPANCY_T, grid_to_occupancy(grid, self.types, stamp_ns, frame_id)),
            ):
                conn = self._scene_conns.get(topic)
                if conn is None:
                    conn = self._scene_conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.store)
                self._writer.write(conn, int(stamp_ns), self.store.serialize_cdr(msg, msgtype))
                self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        """Finalise: MCAP summary and footer, then ``metadata.yaml``."""
        if not self._closed:
            self._closed = True
            with self._os_errors():
                self._writer.close()

    def abort(self) -> None:
        """Close the file without finalising it (after a write already failed)."""
        if not self._closed:
            self._closed = True
            try:
                self._writer.abort()
            except OSError:
                pass

    def __enter__(self) -> OutputBag:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class _WrapOSError:
    """Context manager: an OSError inside becomes :class:`OutputError` for ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> Literal[False]:
        if exc is not None and isinstance(exc, OSError) and not isinstance(exc, OutputError):
            raise OutputError(self.path, exc) from exc
        return False


def _remove_old_bag(path: Path) -> None:
    """Remove an existing output bag; refuses anything that does not look like one."""
    if path.is_dir():
        if not (path / "metadata.yaml").exists() and any(path.iterdir()):
            raise FileExistsError(f"output {str(path)!r} is a non-empty directory that is not a bag")
        shutil.rmtree(path)
    else:
        path.unlink()


__all__ = ["OutputBag", "OutputError"]
