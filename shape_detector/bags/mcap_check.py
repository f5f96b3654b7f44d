"""Chunk-level integrity of MCAP inputs: find damaged chunks, read around them.

A chunk is damaged when its recorded CRC (of the uncompressed records) does not match,
when it does not decompress, or when its records do not parse. :func:`scan_mcap` checks
every chunk of a file through its summary's chunk index; :class:`McapCheckedSource`
then reads the file chunk by chunk, skipping the damaged ones, so their messages are
reported (file, chunk, byte offset, expected vs actual CRC, messages per topic) instead
of being replayed as corrupt data. Files written with CRC 0 ("not recorded") can only be
checked for decompression and record framing.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, ChunkIndex, Message, Schema
from mcap.stream_reader import CRCValidationError, breakup_chunk, get_chunk_data_stream

from ..bag_io import RawMessage, _iter_records, _McapRecoverySource, _Truncated

_OP_CHUNK, _OP_MESSAGE_INDEX = 0x06, 0x07


@dataclass
class ChunkDamage:
    """One damaged chunk: ``file``, 0-based ``index`` in file order, byte ``offset`` of
    the chunk record, ``reason``, CRCs when the mismatch is a CRC one, and
    ``messages``: topic -> messages lost (from the message index; empty = unknown)."""

    file: Path
    index: int
    offset: int
    reason: str
    expected_crc: int | None = None
    actual_crc: int | None = None
    messages: dict[str, int] = field(default_factory=dict)

    def lost(self, topic: str) -> int | None:
        """Messages of ``topic`` lost with this chunk (None: no message index)."""
        return self.messages.get(topic, 0) if self.messages else None

    def __str__(self) -> str:
        lost = ", ".join(f"{t} {n}" for t, n in sorted(self.messages.items())) or "unknown (no message index)"
        return f"{self.file.name}: chunk {self.index} at byte {self.offset}: {self.reason}; messages lost: {lost}"


def chunk_problem(chunk: Chunk) -> tuple[str, int | None, int | None] | None:
    """``(reason, expected_crc, actual_crc)`` when ``chunk`` is damaged, else None."""
    try:
        stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    except CRCValidationError as e:
        return f"CRC mismatch (expected 0x{e.expected:08x}, actual 0x{e.actual:08x})", e.expected, e.actual
    except Exception as e:  # noqa: BLE001 - any decompression failure is damage
        return f"does not decompress ({type(e).__name__}: {e})", None, None
    data = stream.read(length)
    if len(data) != chunk.uncompressed_size:
        return f"uncompressed size {len(data)} != recorded {chunk.uncompressed_size}", None, None
    try:
        for op, content in _iter_records(data, partial_ok=False):
            if op == 0x05 and len(content) < 22:
                raise _Truncated("message record shorter than its header")
    except (_Truncated, struct.error) as e:
        return f"records do not parse ({e})", None, None
    return None


def read_chunk(fh: IO[bytes], ci: ChunkIndex) -> Chunk:
    """The chunk record that ``ci`` points at (ValueError when it is not one)."""
    fh.seek(ci.chunk_start_offset)
    head = fh.read(9)
    if len(head) != 9 or head[0] != _OP_CHUNK:
        raise ValueError(f"no chunk record at byte {ci.chunk_start_offset}")
    (length,) = struct.unpack_from("<Q", head, 1)
    return parse_chunk(fh.read(min(length, ci.chunk_length)))


def parse_chunk(content: bytes) -> Chunk:
    """A Chunk from the content of a chunk record (the bytes after opcode and length)."""
    chunk = Chunk.read(ReadDataStream(BytesIO(content)))
    if len(chunk.data) > len(content):
        raise ValueError("chunk data longer than its record")
    return chunk


def _lost_messages(fh: IO[bytes], ci: ChunkIndex, topics: dict[int, str]) -> dict[str, int]:
    lost: dict[str, int] = {}
    for cid, off in ci.message_index_offsets.items():
        fh.seek(off)
        head = fh.read(15)
        if len(head) < 15 or head[0] != _OP_MESSAGE_INDEX:
            continue
        (nbytes,) = struct.unpack_from("<I", head, 11)
        topic = topics.get(cid, f"channel {cid}")
        lost[topic] = lost.get(topic, 0) + nbytes // 16
    return lost


def _summary(fh: IO[bytes]) -> Any:
    from mcap.reader import make_reader

    try:
        return make_reader(fh).get_summary()
    except Exception:  # noqa: BLE001 - no readable summary: the caller falls back to recovery
        return None


def scan_mcap(path: Path) -> list[ChunkDamage] | None:
    """Damaged chunks of one MCAP file (``[]``: all good); None when the file has no
    readable summary (truncated or unfinalised - checked while reading instead)."""
    with open(path, "rb") as fh:
        summary = _summary(fh)
        if summary is None:
            return None
        topics = {cid: ch.topic for cid, ch in summary.channels.items()}
        damage = []
        for k, ci in enumerate(sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)):
            try:
                problem = chunk_problem(read_chunk(fh, ci))
            except Exception as e:  # noqa: BLE001 - an unreadable chunk record is damage too
                problem = (f"chunk record unreadable ({type(e).__name__}: {e})", None, None)
            if problem is not None:
                reason, exp, act = problem
                damage.append(ChunkDamage(path, k, ci.chunk_start_offset, reason, exp, act,
                                          _lost_messages(fh, ci, topics)))
        return damage


class McapCheckedSource(_McapRecoverySource):
    """MCAP files read chunk by chunk through their chunk index (chunks in time order,
    messages in time order within a chunk), skipping the chunks in ``damage``.
    ``damage``: every :class:`ChunkDamage` found (reported by the replay)."""

    def __init__(self, path: Path, files: list[Path], damage: list[ChunkDamage]) -> None:
        self._bad = {(d.file, d.offset) for d in damage}
        super().__init__(path, files, f"{len(damage)} damaged chunk(s) skipped")
        self.damage = list(damage)
        self.recovered = False

    def _schema(self, s: Schema) -> None:
        self._schemas[s.id] = (s.name, s.encoding, bytes(s.data))
        self._register_schema(s.name, s.encoding, bytes(s.data))

    def _channel(self, c: Channel) -> None:
        name = self._schemas.get(c.schema_id, ("", "", b""))[0]
        self._channels[c.id] = (c.topic, name)
        if name:
            self.topics.setdefault(c.topic, name)

    def _records_of(self, f: Path) -> Iterator[RawMessage]:
        with open(f, "rb") as fh:
            summary = _summary(fh)
            if summary is None:
                yield from super()._records_of(f)
                return
            for s in summary.schemas.values():
                self._schema(s)
            for c in summary.channels.values():
                self._channel(c)
            chunks = sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset))
            for ci in chunks:
                if (f, ci.chunk_start_offset) in self._bad:
                    continue
                if self._scan:
                    self._scan_count += sum(_lost_messages(fh, ci, {}).values())
                    continue
                try:
                    records = breakup_chunk(read_chunk(fh, ci), validate_crc=True)
                except Exception as e:  # noqa: BLE001 - damage the scan could not see (no CRC recorded)
                    raise _Truncated(f"{f.name}: chunk at byte {ci.chunk_start_offset} unreadable: "
                                     f"{type(e).__name__}: {e}") from None
                yield from self._chunk_messages(records)

    def _chunk_messages(self, records: list) -> Iterator[RawMessage]:
        msgs = []
        for rec in records:
            if isinstance(rec, Schema):
                self._schema(rec)
            elif isinstance(rec, Channel):
                self._channel(rec)
            elif isinstance(rec, Message) and rec.channel_id in self._channels:
                msgs.append(rec)
        for m in sorted(msgs, key=lambda m: m.log_time):
            topic, msgtype = self._channels[m.channel_id]
            yield RawMessage(topic, msgtype, m.log_time, bytes(m.data))


def checked_source(path: Path, files: list[Path]) -> McapCheckedSource | None:
    """A :class:`McapCheckedSource` when any of ``files`` has a damaged chunk, else None
    (the files are fine, or have no summary and are checked while reading)."""
    damage: list[ChunkDamage] = []
    for f in files:
        found = scan_mcap(f)
        if found:
            damage.extend(found)
    return McapCheckedSource(path, files, damage) if damage else None
