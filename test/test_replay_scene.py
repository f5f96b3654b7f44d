"""Replay with a scene: poses from /tf, /odom or none, scene + map topics per frame, the JSON."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from msg_conversion import occupancy_to_cells
from shape_detector.bags.scene_record import SceneOptions, load_poses
from shape_detector.bags.source import MAP_TOPIC, MARKERS_TOPIC, SCENE_TOPIC, read_messages
from shape_detector.replay import configure_parser, replay_bag, scene_options
from shape_detector.synth.bag import read_sidecar
from shape_detector.synth.walkthrough_bag import read_world_sidecar, write_walkthrough_bag
from shape_detector.types import Object3D

FRAMES = 8


@pytest.fixture(scope="module")
def walk_bag(tmp_path_factory):
    return write_walkthrough_bag(tmp_path_factory.mktemp("walk") / "walk", frames=FRAMES, seed=1, width=160, height=120)


class GTDetector:
    """Returns each frame's ground-truth objects (camera frame), in bag order."""

    def __init__(self, bag):
        sidecar = read_sidecar(bag)
        self.frames = [sidecar[s]["objects"] for s in sorted(sidecar)]
        self.calls = 0

    def detect(self, rgb, depth, K, boxes2d=None, up=None):
        gts = self.frames[min(self.calls, len(self.frames) - 1)]
        self.calls += 1
        return [Object3D(g.class_name, 0.9, g.center, g.size, g.rotation) for g in gts if g.visible_fraction > 0.3]


def _topic_count(out, topic):
    return sum(1 for t, _, _ in read_messages(out, [topic]) if t == topic)


def test_walkthrough_bag_topics_and_world_gt(walk_bag):
    topics = {t for t, _, _ in read_messages(walk_bag)}
    assert {"/tf", "/tf_static", "/odom", "/camera/color/image_raw"} <= topics
    world = read_world_sidecar(walk_bag)
    assert world["frame_id"] == "odom" and len(world["poses"]) == FRAMES and world["objects"]


@pytest.mark.parametrize("opts", [SceneOptions(), SceneOptions(odom_topic="/odom")], ids=["tf", "odom"])
def test_poses_match_the_walkthrough(walk_bag, opts):
    poses, what = load_poses(walk_bag, opts)
    assert poses is not None and what
    for p in read_world_sidecar(walk_bag)["poses"]:
        T = poses.T_world_camera("camera_color_optical_frame", p["stamp_ns"])
        np.testing.assert_allclose(T, p["T_world_camera"], atol=1e-6)


def test_replay_writes_scene_and_map_per_frame_and_json(walk_bag, tmp_path):
    out, js = tmp_path / "out", tmp_path / "scene.json"
    s = replay_bag(walk_bag, out, GTDetector(walk_bag), progress=False, scene=SceneOptions(scene_out=js))
    assert s.scene is not None and s.scene.frames == s.frames_out == FRAMES and not s.scene.skipped
    assert _topic_count(out, SCENE_TOPIC) == FRAMES and _topic_count(out, MAP_TOPIC) == FRAMES
    assert _topic_count(out, MARKERS_TOPIC) == FRAMES
    last_map = [m for t, _, m in read_messages(out, [MAP_TOPIC])][-1]
    assert last_map.header.frame_id == "odom" and occupancy_to_cells(last_map).shape == (
        last_map.info.height, last_map.info.width)
    scene_msgs = [m for t, _, m in read_messages(out, [SCENE_TOPIC])]
    assert all(m.markers[0].action == 3 for m in scene_msgs)  # DELETEALL first
    d = json.loads(js.read_text())
    assert d["frame_id"] == "odom" and "grid" in d and len(d["objects"]) >= 1
    assert "scene: world odom, pose /tf + /tf_static" in s.format()
    # objects seen in enough frames end up near their world-frame ground truth
    gt = read_world_sidecar(walk_bag)["objects"]
    for o in d["objects"]:
        nearest = min(np.linalg.norm(np.asarray(o["center"]) - g.center) for g in gt)
        assert nearest < 0.3, o


def test_missing_transform_frames_are_skipped_and_counted(walk_bag, tmp_path):
    s = replay_bag(walk_bag, tmp_path / "out", GTDetector(walk_bag), progress=False,
                   scene=SceneOptions(world_frame="map"))
    assert s.scene.frames == 0 and s.scene.skipped["no transform"] == FRAMES
    assert "'map'" in s.scene.first_problem and s.frames_out == FRAMES
    # still one (empty) scene and map per frame
    assert _topic_count(tmp_path / "out", SCENE_TOPIC) == FRAMES == _topic_count(tmp_path / "out", MAP_TOPIC)


def test_bag_without_poses_is_a_static_camera(tmp_path):
    from test_replay import FakeDetector, synthetic_frames

    from shape_detector.synth.bag import write_rgbd_bag

    bag = write_rgbd_bag(tmp_path / "plain", synthetic_frames(4))
    s = replay_bag(bag, tmp_path / "out", FakeDetector(), progress=False, scene=SceneOptions(), up=(0, -1, 0))
    assert "static camera" in s.scene.pose_source
    assert s.scene.frames == 4 and _topic_count(tmp_path / "out", MAP_TOPIC) == 4


def test_wrong_pose_topic_is_a_clear_error(walk_bag, tmp_path):
    with pytest.raises(ValueError, match="--odom-topic '/tf' has type tf2_msgs/msg/TFMessage"):
        replay_bag(walk_bag, tmp_path / "out", GTDetector(walk_bag), progress=False,
                   scene=SceneOptions(odom_topic="/tf"))
    with pytest.raises(ValueError, match="no such topic"):
        replay_bag(walk_bag, tmp_path / "out", GTDetector(walk_bag), progress=False,
                   scene=SceneOptions(pose_topic="/nope"))


def test_scene_flags():
    p = argparse.ArgumentParser()
    configure_parser(p)
    assert scene_options(p.parse_args(["bag", "-o", "o"])) is None
    opts = scene_options(p.parse_args(["bag", "-o", "o", "--scene-out", "s.json", "--odom-topic", "/odom"]))
    assert opts.world_frame == "odom" and opts.odom_topic == "/odom" and str(opts.scene_out) == "s.json"
    assert scene_options(p.parse_args(["bag", "-o", "o", "--world-frame", "map"])).world_frame == "map"
    cfg = opts.config  # the node's defaults
    assert (cfg.grid_resolution, cfg.confirm_observations, cfg.delete_misses) == (0.05, 3, 3)
    opts = scene_options(p.parse_args(["bag", "-o", "o", "--scene-out", "s.json", "--grid-resolution", "0.1",
                                       "--scene-confirm-observations", "5", "--scene-delete-misses", "2",
                                       "--inflation-radius", "0.3"]))
    cfg = opts.config
    assert (cfg.grid_resolution, cfg.confirm_observations, cfg.delete_misses, cfg.inflation_radius) == (0.1, 5, 2, 0.3)
    for bad in (["--grid-resolution", "5"], ["--scene-confirm-observations", "0"]):
        with pytest.raises(SystemExit):
            p.parse_args(["bag", "-o", "o", *bad])
    with pytest.raises(SystemExit):
        p.parse_args(["bag", "-o", "o", "--odom-topic", "/a", "--pose-topic", "/b"])


def test_cli_scene_out_with_odometry(walk_bag, tmp_path):
    from test_replay import _cli

    out, js = tmp_path / "out", tmp_path / "scene.json"
    r = _cli(str(walk_bag), "-o", str(out), "--scene-out", str(js), "--odom-topic", "/odom", "--no-progress",
             "--json", "--detector", "test_replay:FakeDetector", "--max-objects", "5", "--grid-resolution", "0.1")
    assert r.returncode == 0, r.stderr + r.stdout
    summary = json.loads(r.stdout)
    assert summary["scene"]["pose_source"] == "/odom" and summary["scene"]["frames"] == FRAMES
    scene = json.loads(js.read_text())
    assert scene["frame_id"] == "odom" and scene["grid"]["resolution"] == pytest.approx(0.1)
    assert _topic_count(out, SCENE_TOPIC) == FRAMES


def test_scene_out_must_be_a_file_outside_the_input(walk_bag, tmp_path):
    with pytest.raises(ValueError, match="directory"):
        replay_bag(walk_bag, tmp_path / "out", GTDetector(walk_bag), progress=False,
                   scene=SceneOptions(scene_out=tmp_path))
    with pytest.raises(ValueError, match="inside the input"):
        replay_bag(walk_bag, tmp_path / "out", GTDetector(walk_bag), progress=False,
                   scene=SceneOptions(scene_out=walk_bag / "scene.json"))
    assert not (tmp_path / "out").exists() and not (walk_bag / "scene.json").exists()


def test_scene_in_continues_a_saved_map(walk_bag, tmp_path):
    first = tmp_path / "first.json"
    replay_bag(walk_bag, tmp_path / "o1", GTDetector(walk_bag), progress=False, scene=SceneOptions(scene_out=first))
    before = json.loads(first.read_text())["objects"]
    assert before
    second = tmp_path / "second.json"

    class Nothing:
        def detect(self, rgb, depth, K, boxes2d=None, up=None):
            return []

    # the same walk again with no detections: the continued map keeps its objects and ids
    s = replay_bag(walk_bag, tmp_path / "o2", Nothing(), progress=False,
                   scene=SceneOptions(scene_out=second, scene_in=first))
    assert s.scene.frames == FRAMES
    after = json.loads(second.read_text())["objects"]
    assert {o["id"] for o in after} == {o["id"] for o in before}
    with pytest.raises(ValueError, match="frame 'odom'"):
        replay_bag(walk_bag, tmp_path / "o3", Nothing(), progress=False,
                   scene=SceneOptions(world_frame="map", scene_in=first))
    with pytest.raises(ValueError, match="--scene-in"):
        replay_bag(walk_bag, tmp_path / "o4", Nothing(), progress=False,
                   scene=SceneOptions(scene_in=tmp_path / "missing.json"))
    p = argparse.ArgumentParser()
    configure_parser(p)
    assert str(scene_options(p.parse_args(["bag", "-o", "o", "--scene-in", str(first)])).scene_in) == str(first)


def test_with_a_scene_the_detector_gets_gravity_from_each_frames_pose(walk_bag, tmp_path):
    class UpRecorder(GTDetector):
        def __init__(self, bag):
            super().__init__(bag)
            self.ups = []

        def detect(self, rgb, depth, K, boxes2d=None, up=None):
            self.ups.append(up)
            return super().detect(rgb, depth, K, boxes2d, up)

    det = UpRecorder(walk_bag)
    replay_bag(walk_bag, tmp_path / "out", det, progress=False, scene=SceneOptions())
    poses = read_world_sidecar(walk_bag)["poses"]
    assert len(det.ups) == len(poses) == FRAMES
    for up, p in zip(det.ups, poses):  # world z (up) in the camera's optical frame
        np.testing.assert_allclose(up, np.asarray(p["T_world_camera"])[:3, :3].T @ [0.0, 0.0, 1.0], atol=1e-6)
    fixed = UpRecorder(walk_bag)  # a fixed --up wins over the pose
    replay_bag(walk_bag, tmp_path / "out2", fixed, progress=False, scene=SceneOptions(), up="0,0,1")
    assert all(np.allclose(u, [0.0, 0.0, 1.0]) for u in fixed.ups)
    plain = UpRecorder(walk_bag)  # no scene: no poses read, the detector estimates gravity
    replay_bag(walk_bag, tmp_path / "out3", plain, progress=False)
    assert plain.ups == [None] * FRAMES
