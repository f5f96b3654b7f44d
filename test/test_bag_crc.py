"""Output bags carry chunk and data-section CRCs; a damaged chunk in an input is named
(file, chunk, offset, CRCs) and its frames are counted as skipped, never replayed."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType

from shape_detector.bags.source import MARKERS_TOPIC, open_bag, read_messages
from shape_detector.synth.bag import write_rgbd_bag
from shape_detector.replay import replay_bag
from test_replay import FakeDetector, _cli, synthetic_frames

IMAGE = "/camera/color/image_raw"
N = 12


def _chunks(mcap_file: Path) -> list:
    from mcap.reader import make_reader

    with open(mcap_file, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)


@pytest.fixture()
def crc_bag(tmp_path, monkeypatch, request) -> Path:
    """A replay output (CRC writer) of 12 frames of 320x240 in several chunks; uncompressed
    when the test is parametrised with ``'none'``."""
    import shape_detector.bags.mcap_writer as mw

    if getattr(request, "param", "zstd") == "none":
        monkeypatch.setattr(mw.CrcMcapStorage, "COMPRESSION", CompressionType.NONE)
    rng = np.random.default_rng(1)
    fr = [(t, rng.integers(0, 256, rgb.shape, dtype=np.uint8), d, k) for t, rgb, d, k in synthetic_frames(N, 320, 240)]
    src = write_rgbd_bag(tmp_path / "src", fr)
    s = replay_bag(src, tmp_path / "crc", FakeDetector(), progress=False)
    assert s.ok and s.frames_out == N
    monkeypatch.undo()
    return tmp_path / "crc"


def _damage(bag: Path, dst: Path, chunk: int = 1, nbytes: int = 4096) -> tuple[Path, object]:
    shutil.copytree(bag, dst)
    f = next(dst.glob("*.mcap"))
    ci = _chunks(f)[chunk]
    data = bytearray(f.read_bytes())
    mid = ci.chunk_start_offset + ci.chunk_length // 2
    data[mid : mid + nbytes] = bytes((b ^ 0x5A) for b in data[mid : mid + nbytes])
    f.write_bytes(bytes(data))
    return dst, ci


def test_output_has_chunk_and_data_crcs(crc_bag):
    from mcap.reader import NonSeekingReader, make_reader
    from mcap.records import Chunk, DataEnd
    from mcap.stream_reader import StreamReader

    f = next(crc_bag.glob("*.mcap"))
    records = list(StreamReader(open(f, "rb"), emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) >= 2 and all(c.uncompressed_crc != 0 for c in chunks)
    assert [r for r in records if isinstance(r, DataEnd)][0].data_section_crc != 0
    with open(f, "rb") as fh:
        assert sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages()) > N
    with open(f, "rb") as fh:  # validates the data-section CRC too
        assert sum(1 for _ in NonSeekingReader(fh, validate_crcs=True).iter_messages()) > N
    assert sum(1 for t, _, _ in read_messages(crc_bag) if t == MARKERS_TOPIC) == N  # rosbags reads it


@pytest.mark.parametrize("crc_bag", ["none", "zstd"], indirect=True)
def test_damaged_chunk_is_named_and_its_frames_skipped(crc_bag, tmp_path):
    bad, ci = _damage(crc_bag, tmp_path / "bad")
    with open_bag(bad) as src:
        assert len(src.damage) == 1
        d = src.damage[0]
        assert d.offset == ci.chunk_start_offset and d.index == 1
        lost = d.lost(IMAGE)
        assert lost and lost >= 1
        text = str(d)
        assert "crc.mcap" in text and "chunk 1" in text and f"byte {ci.chunk_start_offset}" in text
        if ci.compression == "":  # the bytes changed in place: only the CRC can tell
            assert d.expected_crc and d.actual_crc and d.expected_crc != d.actual_crc
            assert f"0x{d.expected_crc:08x}" in text
    det = FakeDetector()
    s = replay_bag(bad, tmp_path / "out", det, progress=False)
    assert s.skipped["corrupt_chunk"] == lost and s.frames_out == N - lost == len(det.calls)
    assert not s.ok and "chunk 1" in s.format()
    r = _cli(str(bad), "-o", str(tmp_path / "cli"), "--detector", "test_replay:FakeDetector", "--no-progress")
    assert r.returncode == 1 and "Traceback" not in r.stderr and "OverflowError" not in r.stderr
    assert "damaged chunk" in r.stderr and "chunk 1" in r.stderr
    assert f"corrupt_chunk: {lost}" in r.stdout


def test_unchecked_bag_with_broken_records_is_reported(tmp_path):
    """Bags written without CRCs (rosbags' writer): broken record framing inside a chunk
    is caught, not an OverflowError."""
    src = write_rgbd_bag(tmp_path / "plain", synthetic_frames(12, 320, 240))
    f = next(src.glob("*.mcap"))
    ci = _chunks(f)[1]
    assert ci.compression == ""
    data = bytearray(f.read_bytes())
    first = ci.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(ci.compression) + 8  # first inner record
    data[first + 1 : first + 9] = b"\xff" * 8  # its length field
    f.write_bytes(bytes(data))
    with open_bag(src) as s:
        assert len(s.damage) == 1 and "do not parse" in s.damage[0].reason
    s = replay_bag(src, tmp_path / "out", FakeDetector(), progress=False)
    assert s.damage and s.skipped["corrupt_chunk"] >= 1 and s.frames_out >= 1


@pytest.mark.parametrize("crc_bag", ["none"], indirect=True)
def test_truncated_bag_with_a_damaged_chunk_keeps_the_rest(crc_bag, tmp_path):
    bad, ci = _damage(crc_bag, tmp_path / "bad", chunk=1, nbytes=64)
    f = next(bad.glob("*.mcap"))
    chunks = _chunks(f)
    data = f.read_bytes()
    cut = chunks[-1].chunk_start_offset + chunks[-1].chunk_length // 2
    f.write_bytes(data[:cut])
    det = FakeDetector()
    s = replay_bag(bad, tmp_path / "out", det, progress=False)
    assert s.error and "cut off" in s.error  # truncated: read sequentially up to the cut
    assert s.damage and "chunk 1" in s.damage[0] and "CRC mismatch" in s.damage[0]
    assert 1 <= s.frames_out < N and s.frames_out == len(det.calls)
    assert s.skipped["corrupt_chunk"] >= 1


@pytest.mark.parametrize("crc_bag", ["none", "zstd"], indirect=True)
def test_random_byte_damage_never_escapes(crc_bag, tmp_path):
    """Scattered byte damage: a summary (damage named, frames counted) or a clear
    BagReadError / ValueError - never another exception."""
    from shape_detector.bags.source import BagReadError

    data = bytearray(next(crc_bag.glob("*.mcap")).read_bytes())
    rng = np.random.default_rng(7)
    seen_damage = 0
    for k in range(8):
        d = bytearray(data)
        for pos in rng.integers(0, len(d), size=int(rng.integers(1, 20))):
            d[pos] ^= 0xFF
        bad = tmp_path / f"c{k}.mcap"
        bad.write_bytes(bytes(d))
        try:
            s = replay_bag(bad, tmp_path / f"o{k}", FakeDetector(), progress=False)
        except (BagReadError, ValueError) as e:
            assert str(e)
            continue
        assert s.frames_out + s.skipped["corrupt_chunk"] <= N
        seen_damage += bool(s.damage or s.error)
    assert seen_damage >= 4
