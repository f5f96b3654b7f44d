"""Reading synchronised frames from bags (rosbag2 MCAP / sqlite3, ROS 1), damage handling,
frame preparation and the output bag writer."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image, rosbags_types
from shape_detector.bags.output import OutputBag
from shape_detector.bags.reader import BagFrameReader
from shape_detector.bags.ros1 import convert_message
from shape_detector.bags.source import BagReadError, open_bag, read_messages
from shape_detector.bags.topics import select_topics
from shape_detector.frame_prep import FrameError, prepare_frame
from shape_detector.synth.bag import write_rgbd_bag
from shape_detector.types import Object3D

MS = 1_000_000
K = np.array([[120.0, 0, 39.5], [0, 120.0, 29.5], [0, 0, 1]])


def frames(n=6, w=80, h=60, hz=5.0, t0=1_700_000_000 * 10**9):
    out = []
    for k in range(n):
        rgb = np.full((h, w, 3), 10 * k, np.uint8)
        depth = np.full((h, w), 2.0 + 0.1 * k)
        depth[0, 0] = np.nan
        out.append((t0 + int(k * 1e9 / hz), rgb, depth, K))
    return out


@pytest.mark.parametrize("storage,name", [("mcap", "bag_mcap"), ("sqlite3", "bag_sqlite"), ("ros1", "bag.bag")])
def test_read_frames_all_formats(tmp_path, storage, name):
    fr = frames()
    p = write_rgbd_bag(tmp_path / name, fr, storage=storage, depth_offset_ns=4 * MS)
    with BagFrameReader(p) as reader:
        assert reader.selection.image == "/camera/color/image_raw"
        assert reader.selection.depth == "/camera/depth/image_raw"
        assert reader.selection.camera_info == "/camera/color/camera_info"
        got = list(reader.frames())
        assert reader.stats.synced == len(fr) and reader.stats.no_camera_info == 0
    assert [f.stamp_ns for f in got] == [s for s, *_ in fr]
    assert all(f.frame_id == "camera_color_optical_frame" for f in got)
    pf = got[3].prepare()
    assert pf.rgb.shape == (60, 80, 3) and pf.rgb[0, 1, 0] == 30
    assert np.isnan(pf.depth[0, 0]) and abs(pf.depth[5, 5] - 2.3) < 1e-3
    np.testing.assert_allclose(pf.K, K)


def test_single_file_and_plain_directory(tmp_path):
    p = write_rgbd_bag(tmp_path / "b", frames(3), storage="mcap")
    mcap = next(p.glob("*.mcap"))
    assert len(list(BagFrameReader(mcap).frames())) == 3
    # a directory holding just one .mcap (metadata.yaml lost) is read too
    (p / "metadata.yaml").unlink()
    assert len(list(BagFrameReader(p).frames())) == 3


def test_missing_and_not_a_bag(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_bag(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagReadError, match="not a rosbag2 bag"):
        open_bag(tmp_path / "empty")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(BagReadError, match="unknown bag file type"):
        open_bag(tmp_path / "x.txt")


def test_sync_drops_unmatched_and_uses_nearest_camera_info(tmp_path):
    """A depth frame missing, camera_info written after the images, distractor topics."""
    T = rosbags_types()
    st = T.typestore
    from rosbags.rosbag2 import StoragePlugin, Writer

    p = tmp_path / "b"
    fr = frames(6)
    with Writer(p, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c_img = w.add_connection("/cam/color/image_raw", "sensor_msgs/msg/Image", typestore=st)
        c_ir = w.add_connection("/cam/infra1/image_rect_raw", "sensor_msgs/msg/Image", typestore=st)
        c_dep = w.add_connection("/cam/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", typestore=st)
        c_dep2 = w.add_connection("/cam/depth/image_rect_raw", "sensor_msgs/msg/Image", typestore=st)
        c_info = w.add_connection("/cam/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=st)
        c_info2 = w.add_connection("/cam/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=st)
        for k, (t, rgb, depth, KK) in enumerate(fr):
            img = numpy_to_image(rgb, "rgb8", T, t, "cam")
            w.write(c_img, t, st.serialize_cdr(img, "sensor_msgs/msg/Image"))
            ir = numpy_to_image(rgb[..., 0], "mono8", T, t, "ir")
            w.write(c_ir, t, st.serialize_cdr(ir, "sensor_msgs/msg/Image"))
            if k != 2:  # depth of frame 2 lost
                d = depth_to_image(depth, T, "16UC1", t + 2 * MS, "cam")
                w.write(c_dep, t + 2 * MS, st.serialize_cdr(d, "sensor_msgs/msg/Image"))
            d2 = depth_to_image(depth[::2, ::2], T, "16UC1", t, "depth")
            w.write(c_dep2, t + 1, st.serialize_cdr(d2, "sensor_msgs/msg/Image"))
            KK2 = KK.copy()
            KK2[0, 0] = 100 + k  # tells the frames' camera_infos apart
            info = K_to_camera_info(KK2, 80, 60, T, t, "cam")
            w.write(c_info, t + 3 * MS, st.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            info2 = K_to_camera_info(KK * 0.5, 40, 30, T, t, "depth")
            w.write(c_info2, t + 3 * MS, st.serialize_cdr(info2, "sensor_msgs/msg/CameraInfo"))
    with BagFrameReader(p) as reader:
        sel = reader.selection
        assert (sel.image, sel.depth, sel.camera_info) == (
            "/cam/color/image_raw", "/cam/aligned_depth_to_color/image_raw", "/cam/color/camera_info")
        got = list(reader.frames())
    assert [f.stamp_ns for f in got] == [fr[k][0] for k in (0, 1, 3, 4, 5)]
    # each frame got the camera_info with its own stamp (written 3 ms after the images)
    assert [int(f.prepare().K[0, 0]) for f in got] == [100, 101, 103, 104, 105]
    # explicit topics are honoured and checked
    with BagFrameReader(p, depth="/cam/depth/image_rect_raw", camera_info="/cam/color/camera_info") as r:
        assert r.selection.depth == "/cam/depth/image_rect_raw"
        f = next(iter(r.frames()))
        pf = f.prepare()  # depth at half resolution: colour resized, K scaled
        assert pf.rgb.shape == (30, 40, 3) and any("intrinsics rescaled" in n for n in pf.notes)
    with pytest.raises(ValueError, match="no such topic"):
        BagFrameReader(p, image="/nope")
    with pytest.raises(ValueError, match="expected sensor_msgs/msg/Image"):
        BagFrameReader(p, image="/cam/color/camera_info")


def test_no_camera_info_topic_is_a_clear_error(tmp_path):
    T = rosbags_types()
    from rosbags.rosbag2 import StoragePlugin, Writer

    p = tmp_path / "b"
    with Writer(p, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=T.typestore)
        c2 = w.add_connection("/camera/depth/image_raw", "sensor_msgs/msg/Image", typestore=T.typestore)
        w.write(c, 1, T.typestore.serialize_cdr(numpy_to_image(np.zeros((4, 4, 3), np.uint8), "rgb8", T, 1, "c"),
                                               "sensor_msgs/msg/Image"))
        w.write(c2, 1, T.typestore.serialize_cdr(depth_to_image(np.ones((4, 4)), T, "16UC1", 1, "c"),
                                                "sensor_msgs/msg/Image"))
    with pytest.raises(ValueError, match="CameraInfo"):
        BagFrameReader(p)


def _truncate(src: Path, dst: Path, keep_fraction: float) -> Path:
    shutil.copytree(src, dst)
    f = next(dst.glob("*.mcap"))
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * keep_fraction)])
    return dst


def test_truncated_mcap_yields_frames_before_damage(tmp_path):
    fr = frames(10, w=160, h=120)
    p = write_rgbd_bag(tmp_path / "good", fr)
    bad = _truncate(p, tmp_path / "bad", 0.55)
    got = []
    with BagFrameReader(bad) as reader:
        assert reader.source.recovered
        with pytest.raises(BagReadError) as ei:
            for f in reader.frames():
                got.append(f)
    assert 3 <= len(got) < 10
    assert [f.stamp_ns for f in got] == [s for s, *_ in fr[: len(got)]]
    assert all(f.camera_info is not None for f in got)
    msg = str(ei.value)
    assert "bad" in msg and "cut off" in msg and ei.value.messages_read > 0
    # the recovered frames decode
    assert got[-1].prepare().rgb.shape == (120, 160, 3)


def test_garbage_bags(tmp_path):
    (tmp_path / "junk.mcap").write_bytes(b"\x00" * 100)
    with pytest.raises(BagReadError):
        BagFrameReader(tmp_path / "junk.mcap")
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\x01" * 50)
    with pytest.raises(BagReadError):
        BagFrameReader(tmp_path / "junk.bag")
    (tmp_path / "junk.db3").write_bytes(b"SQLite format 3\x00" + b"\xff" * 200)
    with pytest.raises(BagReadError):
        BagFrameReader(tmp_path / "junk.db3")
    d = tmp_path / "meta"
    d.mkdir()
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information: [unbalanced")
    with pytest.raises(BagReadError):
        BagFrameReader(d)


def _img(T, arr, enc, stamp=5, frame="cam"):
    return numpy_to_image(arr, enc, T, stamp, frame)


def test_prepare_frame_errors_and_fixes():
    T = rosbags_types()
    rgb = np.zeros((60, 80, 3), np.uint8)
    depth = np.full((60, 80), 1.0)
    info = K_to_camera_info(K, 80, 60, T, 5, "cam")
    good = prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(depth, T, "16UC1", 5, "cam"), info)
    assert good.stamp_ns == 5 and good.frame_id == "cam" and good.valid_depth_fraction == 1.0
    # missing camera_info
    with pytest.raises(FrameError, match="camera_info") as e:
        prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(depth, T), None)
    assert e.value.kind == "camera_info"
    # all-zero K
    zero = K_to_camera_info(np.zeros((3, 3)), 80, 60, T)
    with pytest.raises(FrameError, match="all zero"):
        prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(depth, T), zero)
    # swapped topics / wrong encodings
    with pytest.raises(FrameError, match="colour image unusable") as e:
        prepare_frame(depth_to_image(depth, T), depth_to_image(depth, T), info)
    assert e.value.kind == "encoding"
    with pytest.raises(FrameError, match="depth image unusable"):
        prepare_frame(_img(T, rgb, "rgb8"), _img(T, rgb, "rgb8"), info)
    # empty images
    with pytest.raises(FrameError, match="empty"):
        prepare_frame(_img(T, np.zeros((0, 0, 3), np.uint8), "rgb8"), depth_to_image(depth, T), info)
    # depth at half resolution: colour resized, K halved (pixel-centre convention)
    half = prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(depth[::2, ::2], T), info)
    assert half.rgb.shape == (30, 40, 3) and abs(half.K[0, 0] - 60.0) < 1e-9
    with pytest.raises(FrameError, match=r"depth image is 40x30 but the colour image is 80x60") as e:
        prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(depth[::2, ::2], T), info, size_mismatch="skip")
    assert e.value.kind == "size"
    # different aspect ratio cannot be rescaled
    with pytest.raises(FrameError, match=r"80x45 but the colour image is 80x60"):
        prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(np.ones((45, 80)), T), info)
    # camera_info of another resolution: K rescaled
    big = K_to_camera_info(K * np.array([[2], [2], [1]]), 160, 120, T)
    pf = prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(depth, T), big)
    assert abs(pf.K[0, 0] - 120.0) < 1e-9 and pf.notes
    # NaN / Inf depth -> NaN; all-invalid depth is reported, not an error
    d32 = np.full((60, 80), np.inf, np.float32)
    d32[:10] = np.nan
    pf = prepare_frame(_img(T, rgb, "rgb8"), depth_to_image(d32, T, "32FC1"), info)
    assert pf.valid_depth_fraction == 0.0 and "no valid pixels" in pf.notes[-1]
    # bgr8 is converted
    bgr = rgb.copy()
    bgr[..., 0] = 255
    assert prepare_frame(_img(T, bgr, "bgr8"), depth_to_image(depth, T), info).rgb[0, 0, 2] == 255


def test_output_bag_and_ros1_conversion(tmp_path):
    p = write_rgbd_bag(tmp_path / "in.bag", frames(3), storage="ros1")
    out = tmp_path / "out"
    obj = Object3D("chair", 0.8, [0, 0, 2], [0.5, 0.5, 0.9], np.eye(3))
    with open_bag(p) as src, OutputBag(out) as ob:
        assert src.is_ros1
        for m in src.messages():
            ob.copy(m, src)
        ob.write_objects([obj], 123, "cam")
    topics = {}
    for topic, _t, msg in read_messages(out):
        topics.setdefault(topic, []).append(msg)
    assert len(topics["/camera/color/image_raw"]) == 3
    info = topics["/camera/color/camera_info"][0]
    assert info.__msgtype__ == "sensor_msgs/msg/CameraInfo" and abs(info.k[0] - 120.0) < 1e-9
    assert len(topics["/shape_detector/markers"]) == 1 and len(topics["/shape_detector/detections"]) == 1
    det = topics["/shape_detector/detections"][0]
    assert det.detections[0].results[0].hypothesis.class_id == "chair"
    with pytest.raises(FileExistsError):
        OutputBag(out)
    OutputBag(out, overwrite=True).close()


def test_convert_message_ros1_header():
    from rosbags.typesys import Stores, get_typestore

    T = rosbags_types()
    ros1 = get_typestore(Stores.ROS1_NOETIC)
    img = numpy_to_image(np.zeros((2, 3, 3), np.uint8), "rgb8", T, 7_000_000_123, "f")
    m1 = convert_message(img, "sensor_msgs/msg/Image", ros1)
    assert m1.header.seq == 0 and m1.header.stamp.sec == 7 and m1.header.stamp.nanosec == 123
    back = convert_message(m1, "sensor_msgs/msg/Image", T.typestore)
    assert back.width == 3 and bytes(back.data) == bytes(img.data)


def test_select_topics_explicit_type_checks(tmp_path):
    p = write_rgbd_bag(tmp_path / "b", frames(2))
    with open_bag(p) as src:
        with pytest.raises(ValueError, match="expected sensor_msgs/msg/CameraInfo"):
            select_topics(src, camera_info="/camera/color/image_raw")
        with pytest.raises(ValueError, match="no such topic"):
            select_topics(src, imu="/imu")
