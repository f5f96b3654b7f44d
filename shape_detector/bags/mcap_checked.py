"""MCAP files with damaged chunks, read through their summary's chunk index around the damage.

:func:`checked_source` scans every chunk (:func:`~.mcap_check.scan_mcap`); when any is damaged,
:class:`McapCheckedSource` reads the file chunk by chunk (the ``mcap`` library reads and
decompresses them), skipping the damaged ones, so their messages are reported (file, chunk,
byte offset, expected vs actual CRC, messages per topic) instead of being replayed as corrupt data.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import breakup_chunk

from .mcap_check import ChunkDamage, Truncated, lost_messages, read_chunk, read_summary, scan_mcap
from .mcap_recovery import McapRecoverySource
from .source import RawMessage


class McapCheckedSource(McapRecoverySource):
    """MCAP files read chunk by chunk through their chunk index (chunks in time order,
    messages in time order within a chunk), skipping the chunks in ``damage``.
    ``damage``: every :class:`ChunkDamage` found (reported by the replay)."""

    def __init__(self, path: Path, files: list[Path], damage: list[ChunkDamage]) -> None:
        self._bad = {(d.file, d.offset) for d in damage}
        super().__init__(path, files, f"{len(damage)} damaged chunk(s) skipped")
        self.damage = list(damage)
        self.recovered = False

    def _records_of(self, f: Path) -> Iterator[RawMessage]:
        with open(f, "rb") as fh:
            summary = read_summary(fh)
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
                    self._scan_count += sum(lost_messages(fh, ci, {}).values())
                    continue
                try:
                    records = breakup_chunk(read_chunk(fh, ci), validate_crc=True)
                except Exception as e:  # noqa: BLE001 - damage the scan could not see (no CRC recorded)
                    raise Truncated(f"{f.name}: chunk at byte {ci.chunk_start_offset} unreadable: "
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
