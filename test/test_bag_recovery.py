"""Sequential MCAP recovery: a cut-off chunk gives up its complete records, an unfinalised file
reads to its end, a chunk whose header does not parse is skipped and reading goes on."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from shape_detector.bags.mcap_recovery import McapRecoverySource
from shape_detector.bags.source import BagReadError, open_bag
from test_replay import synthetic_frames

IMAGE = "/camera/color/image_raw"
N = 8


def _bag(tmp_path: Path, compression: str) -> Path:
    """An MCAP (one file) with one small chunk per frame, written with the mcap library."""
    from mcap.writer import CompressionType, Writer

    from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image, rosbags_types

    types = rosbags_types()
    store = types.typestore
    path = tmp_path / f"bag_{compression}.mcap"
    comp = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}[compression]
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=20_000, compression=comp)  # about one frame per chunk
        w.start("ros2", "test")
        ids = {}
        for topic, typ in ((IMAGE, "sensor_msgs/msg/Image"), ("/camera/depth/image_raw", "sensor_msgs/msg/Image"),
                           ("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo")):
            sid = w.register_schema(typ, "ros2msg", b"")
            ids[topic] = (w.register_channel(topic, "cdr", sid), typ)
        for t, rgb, depth, K in synthetic_frames(N, 64, 48):
            msgs = {IMAGE: numpy_to_image(rgb, "rgb8", types, t, "cam"),
                    "/camera/depth/image_raw": depth_to_image(depth, types, "16UC1", t, "cam"),
                    "/camera/color/camera_info": K_to_camera_info(K, 64, 48, types, t, "cam")}
            for topic, msg in msgs.items():
                cid, typ = ids[topic]
                w.add_message(cid, t, store.serialize_cdr(msg, typ), t)
        w.finish()
    return path


def _read_all(src) -> tuple[list, BagReadError | None]:
    got, err = [], None
    try:
        for m in src.messages():
            got.append(m)
    except BagReadError as e:
        err = e
    return got, err


def _chunks(path: Path) -> list[tuple[int, int, int]]:
    """(offset, length, messages) of every chunk, in file order."""
    from mcap.reader import make_reader

    from shape_detector.bags.mcap_check import lost_messages

    with open(path, "rb") as f:
        cis = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
        return [(c.chunk_start_offset, c.chunk_length, sum(lost_messages(f, c, {}).values())) for c in cis]


@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_cut_inside_a_chunk_recovers_its_complete_records(tmp_path, compression):
    good = _bag(tmp_path, compression)
    chunks = _chunks(good)
    k = len(chunks) // 2
    off, length, n_cut = chunks[k]
    assert n_cut >= 2
    before = sum(c[2] for c in chunks[:k])
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(good.read_bytes()[: off + length - 10])  # the chunk's last bytes are missing
    src = open_bag(bad)
    assert src.recovered
    got, err = _read_all(src)
    assert err is not None and "cut off inside a chunk" in str(err)
    assert before <= len(got) < before + n_cut
    if compression == "none":  # the records before the cut come out of the cut-off chunk
        assert len(got) > before


def test_unfinalised_file_reads_to_the_end(tmp_path):
    good = _bag(tmp_path, "zstd")
    chunks = _chunks(good)
    last_end = chunks[-1][0] + chunks[-1][1]
    data = good.read_bytes()
    # keep every chunk and its message indexes, drop the summary and footer
    head = data[last_end:]
    cut = last_end
    while head and head[0] == 0x07:  # message index records after the last chunk
        (n,) = struct.unpack_from("<Q", head, 1)
        cut += 9 + n
        head = data[cut:]
    bad = tmp_path / "open.mcap"
    bad.write_bytes(data[:cut])
    got, err = _read_all(open_bag(bad))
    assert len(got) == 3 * N
    assert err is not None and "no footer" in str(err)


def test_unparsable_chunk_header_is_damage_and_reading_goes_on(tmp_path):
    good = _bag(tmp_path, "none")
    chunks = _chunks(good)
    off, _, lost = chunks[2]
    data = bytearray(good.read_bytes())
    # the compression string's length field (after 9 + 28 header bytes) made absurd
    struct.pack_into("<I", data, off + 9 + 28, 0x7FFFFFF0)
    bad = tmp_path / "hdr.mcap"
    bad.write_bytes(bytes(data[: chunks[-1][0] + chunks[-1][1]]))  # no summary: sequential reading
    src = McapRecoverySource(bad, [bad], "test")
    got, err = _read_all(src)
    assert len(got) == 3 * N - lost
    assert len(src.damage) == 1 and src.damage[0].offset == off and "unreadable" in src.damage[0].reason
    assert err is not None and "no footer" in str(err)
