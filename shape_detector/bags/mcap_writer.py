"""A rosbag2 MCAP writer that records chunk and data-section CRCs.

rosbags' own MCAP storage writes a chunk CRC of 0 ("not recorded"), so a reader cannot
tell a damaged chunk from a good one. :class:`CrcWriter` keeps rosbags' ``Writer`` for
what it does well (connections, message definitions, type hashes, ``metadata.yaml``) and
swaps the storage for :class:`CrcMcapStorage`, built on the ``mcap`` library's writer
with CRCs on. The result reads with rosbags, ``ros2 bag`` (Jazzy) and Foxglove.
"""

from __future__ import annotations

from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType
from mcap.writer import Writer as _McapWriter
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

#: chunk size before compression, bytes (the rosbag2 recorder's default too)
CHUNK_SIZE = 1 << 20


def open_exclusive(path: Path) -> IO[bytes]:
    """Create ``path`` for binary writing; fails if it exists (tests patch this to
    simulate a full disk)."""
    return open(path, "xb")


class CrcMcapStorage:
    """rosbags storage plugin: one MCAP file ``<dir>/<file_name>.mcap`` (zstd chunks,
    chunk CRCs, data-section CRC, message indexes, summary, ``rosbag2`` metadata record)."""

    #: chunk compression (tests switch it off to damage record bytes in place)
    COMPRESSION = CompressionType.ZSTD

    def __init__(self, path: Path, compression: Any = None, file_name: str | None = None) -> None:
        self.path = path / f"{file_name or path.name}.mcap"
        self._file = open_exclusive(self.path)
        self._mcap = _McapWriter(
            self._file,
            chunk_size=CHUNK_SIZE,
            compression=self.COMPRESSION,
            enable_crcs=True,
            enable_data_crcs=True,
        )
        self._mcap.start(profile="ros2", library="shape_detector (mcap-python)")
        self._schemas: dict[str, int] = {}
        self._channels: dict[int, int] = {}

    def add_msgtype(self, connection: Any) -> None:
        """Register the schema (message definition) of ``connection.msgtype``."""
        fmt = "ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG else "ros2idl"
        data = connection.msgdef.data
        self._schemas[connection.msgtype] = self._mcap.register_schema(
            connection.msgtype, fmt, data.encode() if isinstance(data, str) else bytes(data)
        )

    def add_connection(self, connection: Any, offered_qos_profiles: str) -> None:
        """Register a channel; its QoS goes into the channel metadata as rosbag2 expects."""
        self._channels[connection.id] = self._mcap.register_channel(
            connection.topic,
            connection.ext.serialization_format,
            self._schemas[connection.msgtype],
            {"offered_qos_profiles": offered_qos_profiles},
        )

    def write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        """One message; log and publish time = ``timestamp`` (ns)."""
        self._mcap.add_message(self._channels[connection.id], int(timestamp), bytes(data), int(timestamp))

    def close(self, version: int, metadata: str) -> None:
        """Last chunk, summary, footer; the file is closed even when that fails."""
        try:
            self._mcap.add_metadata("rosbag2", {"serialized_metadata": metadata})
            self._mcap.finish()
        finally:
            self._file.close()

    def abort(self) -> None:
        """Close the file without summary or footer."""
        self._file.close()


class CrcWriter(Writer):
    """rosbags' rosbag2 ``Writer`` (version 8, MCAP) writing through :class:`CrcMcapStorage`.

    ``file_name``: stem of the ``.mcap`` inside the bag directory (default: the
    directory's name) - lets a bag be written under a temporary directory name and
    renamed afterwards without a file name that still says "partial"."""

    def __init__(self, path: Path | str, file_name: str | None = None) -> None:
        super().__init__(path, version=8, storage_plugin=StoragePlugin.MCAP)
        self._file_name = file_name

    def open(self) -> None:
        """Create the bag directory and the MCAP storage."""
        try:
            self.path.mkdir(mode=0o755, parents=True)
        except FileExistsError:
            raise WriterError(f"{self.path} exists already, not overwriting.") from None
        self.storage = CrcMcapStorage(self.path, self.compression_mode, self._file_name)  # type: ignore[assignment]
