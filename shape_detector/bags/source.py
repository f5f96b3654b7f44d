"""Opening bags for sequential reading: rosbag2 directories or single files (MCAP or sqlite3)
and ROS 1 ``.bag`` files through rosbags' ``AnyReader``, with a damaged or unfinalised MCAP
handed to :mod:`.mcap_recovery` / :mod:`.mcap_check`.

A :class:`BagSource` yields :class:`RawMessage` s (topic, type, log time, serialized bytes) in
bag order and deserialises them; :class:`BagReadError` says where reading stopped.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

IMAGE_T = "sensor_msgs/msg/Image"
CAMERA_INFO_T = "sensor_msgs/msg/CameraInfo"
IMU_T = "sensor_msgs/msg/Imu"
DET2D_T = "vision_msgs/msg/Detection2DArray"
MARKERS_T = "visualization_msgs/msg/MarkerArray"
DET3D_T = "vision_msgs/msg/Detection3DArray"
OCCUPANCY_T = "nav_msgs/msg/OccupancyGrid"
TF_T = "tf2_msgs/msg/TFMessage"
ODOMETRY_T = "nav_msgs/msg/Odometry"
POSE_STAMPED_T = "geometry_msgs/msg/PoseStamped"

MARKERS_TOPIC = "/shape_detector/markers"
DETECTIONS_TOPIC = "/shape_detector/detections"
SCENE_TOPIC = "/shape_detector/scene"
MAP_TOPIC = "/shape_detector/map"


class BagReadError(RuntimeError):
    """A bag could not be read (completely). ``messages_read`` messages (up to log time
    ``last_time_ns``) were read before the damage."""

    def __init__(self, path: Any, reason: str, messages_read: int = 0, last_time_ns: int | None = None) -> None:
        self.path = str(path)
        self.reason = reason
        self.messages_read = messages_read
        self.last_time_ns = last_time_ns
        where = f" after {messages_read} message(s)" if messages_read else ""
        if last_time_ns is not None:
            where += f" (last good log time {last_time_ns / 1e9:.3f} s)"
        super().__init__(f"bag {self.path!r} is damaged or unreadable{where}: {reason}")

@dataclass
class RawMessage:
    """One message as stored: topic, ROS 2 type name, log time, serialized bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    raw: bytes
    connection: Any = None


class BagSource:
    """Sequential access to one bag's messages (base of the two readers)."""

    path: Path
    is_ros1: bool = False
    recovered: bool = False
    topics: dict[str, str]
    message_count: int | None = None
    typestore: Any = None
    messages_read: int = 0
    last_time_ns: int | None = None
    #: damaged chunks skipped while reading (``shape_detector.bags.mcap_check.ChunkDamage``)
    damage: Sequence[Any] = ()

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        """The messages (of ``topics``, default all) in bag order; :class:`BagReadError` on damage."""
        raise NotImplementedError

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        """The message of type ``msgtype`` serialized in ``raw``."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the file(s)."""

    def __enter__(self) -> BagSource:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class AnyReaderSource(BagSource):
    """A bag read through rosbags' ``AnyReader`` (every format rosbags opens)."""

    def __init__(self, path: Path, reader: Any) -> None:
        self.path = path
        self.reader = reader
        self.is_ros1 = not reader.is2
        self.typestore = reader.typestore
        self.topics = {c.topic: c.msgtype for c in reader.connections}
        self.message_count = int(reader.message_count)
        self.connections = list(reader.connections)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        """See :meth:`BagSource.messages`."""
        wanted = set(topics) if topics is not None else None
        conns = [c for c in self.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        try:
            for conn, t, raw in self.reader.messages(connections=conns):
                self.messages_read += 1
                self.last_time_ns = t
                yield RawMessage(conn.topic, conn.msgtype, t, bytes(raw), conn)
        except GeneratorExit:
            raise
        except Exception as e:  # noqa: BLE001 - any reader failure is bag damage
            raise BagReadError(self.path, f"{type(e).__name__}: {e}", self.messages_read, self.last_time_ns) from e

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        """See :meth:`BagSource.deserialize`."""
        try:
            return self.reader.deserialize(raw, msgtype)
        except Exception as e:  # noqa: BLE001
            raise BagReadError(
                self.path, f"cannot deserialise a {msgtype} message: {type(e).__name__}: {e}", self.messages_read, self.last_time_ns
            ) from e

    def close(self) -> None:
        """Close the reader (errors while closing are ignored)."""
        try:
            self.reader.close()
        except Exception:  # noqa: BLE001
            pass


def _default_typestore(path: Path) -> Any:
    from rosbags.typesys import Stores, get_typestore

    if path.suffix == ".bag":
        return get_typestore(Stores.ROS1_NOETIC)
    return get_typestore(Stores.ROS2_JAZZY)


def _mcap_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == ".mcap" else []
    meta = path / "metadata.yaml"
    files: list[Path] = []
    if meta.is_file():
        try:
            import yaml

            info = yaml.safe_load(meta.read_text()) or {}
            rel = (info.get("rosbag2_bagfile_information") or {}).get("relative_file_paths") or []
            files = [path / r for r in rel if str(r).endswith(".mcap") and (path / r).is_file()]
        except Exception:  # noqa: BLE001
            files = []
    if not files:
        files = sorted(path.glob("*.mcap"))
    return files


def open_bag(path: str | Path) -> BagSource:
    """Open a bag for sequential reading: a rosbag2 directory, a single ``.mcap`` /
    ``.db3`` file or a ROS 1 ``.bag``. Bags without message definitions use the ROS 2
    Jazzy (or ROS 1 Noetic for ``.bag``) typestore. An MCAP that rosbags cannot open
    (truncated, unfinalised) is opened in sequential recovery mode (``recovered=True``).
    Raises FileNotFoundError or :class:`BagReadError`."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such bag: {str(path)!r}")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        inner = sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3"))
        if len(inner) == 1:
            path = inner[0]
        elif not inner:
            raise BagReadError(path, "directory has neither metadata.yaml nor a .mcap/.db3 file: not a rosbag2 bag")
    if path.is_file() and path.suffix not in (".mcap", ".db3", ".bag"):
        raise BagReadError(path, f"unknown bag file type {path.suffix!r} (expected .mcap, .db3 or .bag)")
    reader = AnyReader([path], default_typestore=_default_typestore(path))
    try:
        reader.open()
    except Exception as e:  # noqa: BLE001
        err = f"{type(e).__name__}: {e}"
        files = _mcap_files(path)
        if files:
            from .mcap_recovery import McapRecoverySource

            return McapRecoverySource(path, files, f"cannot open normally ({err})")
        raise BagReadError(path, err) from e
    files = _mcap_files(path)
    if files:  # rosbags reads a damaged chunk as corrupt data or fails mid-way: check first
        from .mcap_checked import checked_source

        try:
            checked = checked_source(path, files)
        except OSError as e:
            reader.close()
            raise BagReadError(path, f"{type(e).__name__}: {e}") from e
        except BaseException:
            reader.close()
            raise
        if checked is not None:
            reader.close()
            return checked
    return AnyReaderSource(path, reader)


# --- topic selection ---------------------------------------------------------------------


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(topic, log_time_ns, message)`` of a bag (deserialised), for tests and tools."""
    with open_bag(path) as src:
        for m in src.messages(topics):
            yield m.topic, m.log_time_ns, src.deserialize(m.raw, m.msgtype)

