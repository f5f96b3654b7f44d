"""The committed sample bag: readable by rosbags and mcap, monotonic stamps, GT sidecar; the writer."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shape_detector.synth.bag import COLOR_TOPIC, DEPTH_TOPIC, INFO_TOPIC, read_sidecar, write_bag
from shape_detector.synth.generate import SynthConfig, generate_sequence


def _read_anyreader(bag: Path):
    from rosbags.highlevel import AnyReader

    from msg_conversion.image import image_to_depth, image_to_rgb

    out: dict[str, list] = {}
    with AnyReader([bag]) as reader:
        for conn, t, raw in reader.messages():
            msg: Any = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            item = {"t": t, "stamp": stamp, "frame_id": msg.header.frame_id, "msg": msg}
            if conn.topic == COLOR_TOPIC:
                item["rgb"] = image_to_rgb(msg)
            elif conn.topic == DEPTH_TOPIC:
                item["depth"] = image_to_depth(msg)
            out.setdefault(conn.topic, []).append(item)
    return out


def _check_bag(bag: Path, min_frames: int, rate: float = 5.0) -> None:
    msgs = _read_anyreader(bag)
    for topic in (COLOR_TOPIC, DEPTH_TOPIC, INFO_TOPIC):
        items = msgs[topic]
        assert len(items) >= min_frames
        stamps = [m["stamp"] for m in items]
        times = [m["t"] for m in items]
        assert all(b > a for a, b in zip(stamps, stamps[1:])), topic
        assert all(b >= a for a, b in zip(times, times[1:])), topic
        assert {m["frame_id"] for m in items} == {"camera_color_optical_frame"}
    col = msgs[COLOR_TOPIC]
    dep = msgs[DEPTH_TOPIC]
    assert col[0]["msg"].encoding == "rgb8" and dep[0]["msg"].encoding == "16UC1"
    dt = np.diff([m["stamp"] for m in col]) / 1e9
    assert np.allclose(dt, 1.0 / rate, atol=1e-6)
    offs = np.array([d["stamp"] - c["stamp"] for c, d in zip(col, dep)]) / 1e6
    assert np.all(np.abs(offs) < 20) and np.any(offs != 0)  # small colour/depth stamp offsets
    gt = read_sidecar(bag)
    assert sorted(gt) == [m["stamp"] for m in col]
    first = gt[col[0]["stamp"]]
    h, w = col[0]["rgb"].shape[:2]
    assert first["width"] == w and first["height"] == h
    assert any(len(v["objects"]) for v in gt.values())
    d = dep[0]["depth"]
    assert d.shape == (h, w) and np.isfinite(d).mean() > 0.3
    # the mcap reader sees the same messages
    from mcap.reader import make_reader

    (mcap_file,) = sorted(bag.glob("*.mcap"))
    counts: dict[str, int] = {}
    with open(mcap_file, "rb") as fh:
        reader = make_reader(fh)
        last = -1
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            assert message.log_time >= last
            last = message.log_time
    assert {k: v for k, v in counts.items() if k in msgs} == {k: len(v) for k, v in msgs.items()}


def test_sample_bag(sample_bag):
    if not (sample_bag / "metadata.yaml").is_file():
        pytest.skip("no sample bag committed yet")
    size = sum(p.stat().st_size for p in sample_bag.iterdir())
    assert size <= 5 * 1024 * 1024
    _check_bag(sample_bag, 10)


def test_write_bag(tmp_path):
    frames = generate_sequence(4, 3, 5.0, SynthConfig(width=96, height=72))
    bag = write_bag(frames, tmp_path / "bag", rate_hz=5.0, seed=1)
    _check_bag(bag, 3)
    meta = (bag / "metadata.yaml").read_text()
    assert "mcap" in meta
    side = json.loads((bag / "gt.json").read_text())
    assert len(side["frames"]) == 3
