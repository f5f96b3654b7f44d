"""Sequential reading of MCAP files that rosbags cannot open (truncated, unfinalised, damaged).

The ``mcap`` library's :class:`~mcap.stream_reader.StreamReader` reads the records in file
order without the summary section; schemas become rosbags types here. What the library cannot
do, and this module keeps by hand:

* **a cut-off last record**: the library raises at the first record that ends past the end of
  the file. When that record is a chunk, its header is parsed here, the compressed bytes that
  exist are decompressed as far as they go (streaming zstd / lz4) and every complete record
  inside is read, so messages recorded before a recorder was killed are not lost;
* **a chunk whose header does not parse**: the library's reader is dead after the error; here
  the chunk is recorded as damage and reading resumes after it (its length is in the record
  header);
* **damaged chunks in files without a summary**: a CRC mismatch is recorded (file, chunk,
  offset, CRCs) with the messages lost per topic from the message-index records that follow.
"""

from __future__ import annotations

import struct
from collections.abc import Generator, Iterable, Iterator
from io import BytesIO
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Footer, Message, MessageIndex, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from .mcap_check import ChunkDamage, Truncated, chunk_problem, iter_records
from .source import BagReadError, BagSource, RawMessage

MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x03, 0x04, 0x05, 0x06
#: chunk header: start time, end time, uncompressed size (u64 each), uncompressed CRC (u32), then
#: the compression string (u32 length + bytes) and the records length (u64)
_CHUNK_FIXED = 8 * 3 + 4
#: what a record that does not parse raises inside the mcap library
_PARSE_ERRORS = (McapError, struct.error, ValueError, UnicodeDecodeError, EOFError, IndexError)


def decompress_prefix(compression: str, data: bytes) -> bytes:
    """As much of a chunk's records as the (possibly cut-off) compressed ``data`` gives."""
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        try:
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except zstandard.ZstdError:
            return b""
    if compression == "lz4":
        import lz4.frame

        try:
            return lz4.frame.LZ4FrameDecompressor().decompress(data)
        except RuntimeError:
            return b""
    raise ValueError(f"unsupported MCAP chunk compression {compression!r}")


def _parse_inner(op: int, content: bytes) -> Any:
    """An mcap record object for one complete record inside a chunk (None for other kinds)."""
    stream = ReadDataStream(BytesIO(content))
    if op == _OP_SCHEMA:
        return Schema.read(stream)
    if op == _OP_CHANNEL:
        return Channel.read(stream)
    if op == _OP_MESSAGE:
        return Message.read(stream, len(content))
    return None


class McapRecoverySource(BagSource):
    """Reads MCAP files record by record, without the summary section, up to the damage."""

    def __init__(self, path: Path, files: list[Path], open_error: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.files = files
        self.open_error = open_error
        self.recovered = True
        self.topics = {}
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._channels: dict[int, tuple[str, str]] = {}
        self.typestore = get_typestore(Stores.EMPTY)
        self._fallback = get_typestore(Stores.ROS2_JAZZY)
        self._registered: set[str] = set()
        self.damage: list = []
        self._last_chunk = -1
        self._chunk_no = 0
        # a first pass over the readable part finds the topics, their types and the count
        self._scan = True
        self._scan_count = 0
        for f in files:
            try:
                for _ in self._records_of(f):
                    pass
            except (Truncated, OSError, ValueError, struct.error, RuntimeError):
                pass
        self._scan = False
        self.message_count = self._scan_count
        if not self.topics:
            raise BagReadError(path, f"{open_error}; sequential recovery found no channels")

    # --- schemas, channels, messages -----------------------------------------------------
    def _register_schema(self, name: str, encoding: str, data: bytes) -> None:
        if name in self._registered:
            return
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        text = data.decode("utf-8", "replace")
        try:
            if encoding == "ros2msg" and text.strip():
                self.typestore.register(get_types_from_msg(text, name))
            elif encoding == "ros2idl" and text.strip():
                sep = "=" * 80 + "\n"
                if text.startswith(f"{sep}IDL: "):
                    for part in text.split(sep)[1:]:
                        _, idl = part.split("\n", 1)
                        self.typestore.register(get_types_from_idl(idl))
                else:
                    self.typestore.register(get_types_from_idl(text))
        except Exception:  # noqa: BLE001 - a bad schema: deserialise with the Jazzy definitions
            pass
        self._registered.add(name)

    def _schema(self, s: Schema) -> None:
        self._schemas[s.id] = (s.name, s.encoding, bytes(s.data))
        self._register_schema(s.name, s.encoding, bytes(s.data))

    def _channel(self, c: Channel) -> None:
        name = self._schemas.get(c.schema_id, ("", "", b""))[0]
        self._channels[c.id] = (c.topic, name)
        if name:
            self.topics.setdefault(c.topic, name)

    def _record(self, rec: Any) -> RawMessage | None:
        """Handle a schema / channel; a message of a known channel becomes a RawMessage."""
        if isinstance(rec, Schema):
            self._schema(rec)
        elif isinstance(rec, Channel):
            self._channel(rec)
        elif isinstance(rec, Message):
            ch = self._channels.get(rec.channel_id)
            if ch is None:
                return None
            if self._scan:
                self._scan_count += 1
                return None
            return RawMessage(ch[0], ch[1], rec.log_time, bytes(rec.data))
        return None

    # --- chunks ------------------------------------------------------------------------
    def _damaged(self, f: Path, offset: int, problem: tuple[str, int | None, int | None]) -> None:
        self._last_chunk = offset
        if not self._scan:
            self.damage.append(ChunkDamage(f, self._chunk_no - 1, offset, *problem))

    def _chunk(self, f: Path, offset: int, chunk: Chunk) -> Iterator[RawMessage]:
        self._chunk_no += 1
        problem = chunk_problem(chunk)
        if problem is not None:  # skipped whole; its messages are reported, not replayed
            self._damaged(f, offset, problem)
            return
        for rec in breakup_chunk(chunk, validate_crc=False):
            msg = self._record(rec)
            if msg is not None:
                yield msg

    def _count_lost(self, index: MessageIndex) -> None:
        """Messages of a damaged chunk, from the message index right after it."""
        if not self.damage or self.damage[-1].offset != self._last_chunk or self._scan:
            return
        topic = self._channels.get(index.channel_id, (f"channel {index.channel_id}", ""))[0]
        lost = self.damage[-1].messages
        lost[topic] = lost.get(topic, 0) + len(index.records)

    def _tail(self, f: Path, fh: IO[bytes], pos: int, size: int) -> Iterator[RawMessage]:
        """The complete records inside a chunk cut off at the end of the file."""
        fh.seek(pos)
        data = fh.read(size - pos)
        if len(data) < 9 + _CHUNK_FIXED + 4 or data[0] != _OP_CHUNK:
            return
        content = data[9:]
        (n,) = struct.unpack_from("<I", content, _CHUNK_FIXED)
        off = _CHUNK_FIXED + 4 + n
        if off + 8 > len(content):
            return
        compression = content[_CHUNK_FIXED + 4 : off].decode("utf-8", "replace")
        records = decompress_prefix(compression, bytes(content[off + 8 :]))
        for op, body in iter_records(records, partial_ok=True):
            try:
                rec = _parse_inner(op, body)
            except _PARSE_ERRORS:
                return  # garbage past the cut: what came before is all there is
            msg = self._record(rec)
            if msg is not None:
                yield msg

    def _records_of(self, f: Path) -> Iterator[RawMessage]:
        size = f.stat().st_size
        with open(f, "rb") as fh:
            if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise Truncated(f"{f.name}: not an MCAP file (bad magic)")
            pos = len(MCAP_MAGIC)
            self._chunk_no = 0
            while True:
                fh.seek(pos)
                reader = StreamReader(fh, skip_magic=True, emit_chunks=True, record_size_limit=None)
                try:
                    for rec in reader.records:
                        start, pos = pos, fh.tell()
                        if isinstance(rec, Footer):
                            return
                        if isinstance(rec, Chunk):
                            yield from self._chunk(f, start, rec)
                        elif isinstance(rec, MessageIndex):
                            self._count_lost(rec)
                        elif (msg := self._record(rec)) is not None:
                            yield msg
                    return
                except _PARSE_ERRORS as e:
                    pos = yield from self._after_error(f, fh, pos, size, e)

    def _after_error(self, f: Path, fh: IO[bytes], pos: int, size: int,
                     err: Exception) -> Generator[RawMessage, None, int]:
        """The record at ``pos`` did not parse: skip a complete damaged chunk (returns where to
        resume), or read what a cut-off one holds and raise :class:`Truncated`."""
        if pos >= size:
            raise Truncated(f"{f.name}: no footer (file not finalised)")
        if pos + 9 > size:
            raise Truncated(f"{f.name}: cut off in a record header at byte {pos}")
        fh.seek(pos)
        head = fh.read(9)
        op = head[0]
        (length,) = struct.unpack_from("<Q", head, 1)
        end = pos + 9 + length
        if end <= size:
            if op != _OP_CHUNK:
                raise Truncated(f"{f.name}: record at byte {pos} unreadable ({type(err).__name__}: {err})")
            self._chunk_no += 1
            self._damaged(f, pos, (f"chunk record unreadable ({type(err).__name__}: {err})", None, None))
            return end
        if op == _OP_CHUNK:
            yield from self._tail(f, fh, pos, size)
            raise Truncated(f"{f.name}: cut off inside a chunk at byte {size} (of {end})")
        raise Truncated(f"{f.name}: cut off inside a record at byte {size}")

    # --- BagSource ---------------------------------------------------------------------
    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        """The readable messages in file order; :class:`BagReadError` at the damage."""
        wanted = set(topics) if topics is not None else None
        for f in self.files:
            try:
                for m in self._records_of(f):
                    self.messages_read += 1
                    self.last_time_ns = m.log_time_ns
                    if wanted is None or m.topic in wanted:
                        yield m
            except GeneratorExit:
                raise
            except (Truncated, OSError, ValueError, struct.error, RuntimeError, ImportError) as e:
                raise BagReadError(
                    self.path, f"{self.open_error}; read sequentially up to the damage: {e}", self.messages_read,
                    self.last_time_ns,
                ) from None

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        """A message of ``msgtype`` (the file's own definitions, else ROS 2 Jazzy's)."""
        try:
            store = self.typestore if msgtype in self.typestore.types else self._fallback
            return store.deserialize_cdr(raw, msgtype)
        except Exception as e:  # noqa: BLE001
            raise BagReadError(
                self.path, f"cannot deserialise a {msgtype} message: {type(e).__name__}: {e}", self.messages_read,
                self.last_time_ns,
            ) from e
