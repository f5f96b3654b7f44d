"""Chunk-level integrity of MCAP inputs: find damaged chunks.

A chunk is damaged when its recorded CRC (of the uncompressed records) does not match,
when it does not decompress, or when its records do not parse. :func:`scan_mcap` checks
every chunk of a file through its summary's chunk index (the ``mcap`` library reads the
summary, the chunks and decompresses them); :mod:`.mcap_checked` then reads around the
damaged ones. Files written with CRC 0 ("not recorded") can only be checked for
decompression and record framing.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.records import Chunk, ChunkIndex
from mcap.stream_reader import CRCValidationError, get_chunk_data_stream

_OP_CHUNK, _OP_MESSAGE_INDEX = 0x06, 0x07


class Truncated(Exception):
    """Bytes end inside a record (or a record cannot be framed)."""


def iter_records(buf: bytes, partial_ok: bool) -> Iterator[tuple[int, bytes]]:
    """``(opcode, content)`` of the records framed in ``buf``; a cut-off last record ends the
    iteration when ``partial_ok``, else raises :class:`Truncated`.

    The ``mcap`` library parses records but stops with an error at the first cut-off one; this
    framing is what lets the records before the cut (inside a cut-off chunk) be read.
    """
    off, n = 0, len(buf)
    while off < n:
        if off + 9 > n:
            if partial_ok:
                return
            raise Truncated("record header cut off")
        op = buf[off]
        (length,) = struct.unpack_from("<Q", buf, off + 1)
        if off + 9 + length > n:
            if partial_ok:
                return
            raise Truncated("record cut off")
        yield op, buf[off + 9 : off + 9 + length]
        off += 9 + length


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
        for op, content in iter_records(data, partial_ok=False):
            if op == 0x05 and len(content) < 22:
                raise Truncated("message record shorter than its header")
    except (Truncated, struct.error) as e:
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


def lost_messages(fh: IO[bytes], ci: ChunkIndex, topics: dict[int, str]) -> dict[str, int]:
    """Topic -> messages in the chunk ``ci``, from its message-index records."""
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


def read_summary(fh: IO[bytes]) -> Any:
    """The file's summary (``mcap`` library), or None when it has no readable one."""
    from mcap.reader import make_reader

    try:
        return make_reader(fh).get_summary()
    except Exception:  # noqa: BLE001 - no readable summary: the caller falls back to recovery
        return None


def scan_mcap(path: Path) -> list[ChunkDamage] | None:
    """Damaged chunks of one MCAP file (``[]``: all good); None when the file has no
    readable summary (truncated or unfinalised - checked while reading instead)."""
    with open(path, "rb") as fh:
        summary = read_summary(fh)
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
                                          lost_messages(fh, ci, topics)))
        return damage
